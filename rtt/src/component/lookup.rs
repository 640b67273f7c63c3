//! Finding a component's ports and operations by name, calling with dynamic values.

use super::TaskContext;
use super::dynport::DynPort;
use crate::error::{CallOrIntrospect, IntrospectError};
use crate::info::PortInfo;
use crate::operation::{Args, DynOperation, OperationCaller, OperationEntry, OperationInfo};
use crate::property::PropertyBag;
use serde::Serialize;
use serde_json::Value;
use std::sync::Arc;

impl TaskContext {
    /// Every port.
    pub fn ports(&self) -> Vec<PortInfo> {
        self.core.ports.load().iter().map(|p| p.info()).collect()
    }

    /// The port `name`, or an error listing the ports.
    pub fn port(&self, name: &str) -> Result<Arc<dyn DynPort>, IntrospectError> {
        self.core
            .ports
            .load()
            .iter()
            .find(|p| p.info().name == name)
            .cloned()
            .ok_or_else(|| IntrospectError::NotFound {
                component: self.core.name.clone(),
                kind: "port",
                name: name.to_string(),
                known: self.ports().into_iter().map(|p| p.name).collect(),
            })
    }

    /// Every operation.
    pub fn operations(&self) -> Vec<OperationInfo> {
        self.core
            .operations
            .iter()
            .map(|o| o.info().clone())
            .collect()
    }

    fn find_operation(&self, name: &str) -> Result<&Arc<dyn DynOperation>, IntrospectError> {
        self.core
            .operations
            .iter()
            .find(|o| o.info().name == name)
            .ok_or_else(|| IntrospectError::NotFound {
                component: self.core.name.clone(),
                kind: "operation",
                name: name.to_string(),
                known: self
                    .core
                    .operations
                    .iter()
                    .map(|o| o.info().name.clone())
                    .collect(),
            })
    }

    /// A typed caller of operation `name`; the argument tuple and result types must match.
    pub fn operation<A: Args, R: Serialize + 'static>(
        &self,
        name: &str,
    ) -> Result<OperationCaller<A, R>, IntrospectError> {
        let op = self.find_operation(name)?;
        match op.as_any().downcast_ref::<OperationEntry<A, R>>() {
            Some(e) => Ok(e.caller.clone()),
            None => Err(IntrospectError::WrongType {
                what: format!("operation {name:?}"),
                actual: op.rust_signature(),
                asked: format!(
                    "fn({}) -> {}",
                    A::type_names().join(", "),
                    std::any::type_name::<R>()
                ),
            }),
        }
    }

    /// Calls operation `name` with dynamically typed arguments.
    pub fn call_value(&self, name: &str, args: Vec<Value>) -> Result<Value, CallOrIntrospect> {
        let op = self.find_operation(name)?;
        Ok(op.call_value(args)?)
    }

    /// Sends operation `name` with dynamically typed arguments: the handle gives the
    /// result once it is done (an own-thread operation runs at its component's next step).
    pub fn send_value(
        &self,
        name: &str,
        args: Vec<Value>,
    ) -> Result<crate::operation::ValueHandle, CallOrIntrospect> {
        let op = self.find_operation(name)?;
        Ok(op.send_value(args)?)
    }

    /// The properties.
    pub fn properties(&self) -> &PropertyBag {
        &self.core.properties
    }

    /// The attributes.
    pub fn attributes(&self) -> &PropertyBag {
        &self.core.attributes
    }
}
