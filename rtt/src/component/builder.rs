//! The interface a component declares when it is built: ports, operations, properties
//! and attributes, each named and documented.

use super::dynport::{Check, DynPort, InEntry, OutEntry, ReadBack};
use crate::activity::Waker;
use crate::error::IntrospectError;
use crate::info::PortData;
use crate::operation::{
    ArgInfo, Args, ClientOp, DynOperation, Engine, ExecutionThread, OperationCaller,
    OperationEntry, OperationInfo, OwnOp,
};
use crate::port::{InputPort, OutputPort};
use crate::property::PropertyBag;
use device_interface::Registry;
use serde::Serialize;
use std::sync::{Arc, Weak};

/// What a built interface holds, for the component's core.
pub(crate) struct BuiltInterface {
    pub(crate) ports: Vec<Arc<dyn DynPort>>,
    pub(crate) operations: Vec<Arc<dyn DynOperation>>,
    pub(crate) properties: PropertyBag,
    pub(crate) attributes: PropertyBag,
    pub(crate) provided: Vec<crate::service::ProvidedInfo>,
    pub(crate) required: Vec<Arc<crate::service::Requirement>>,
    pub(crate) breaker: Option<Box<dyn Fn() + Send + Sync>>,
}

/// Builds a component's interface: handed to the component's constructor.
pub struct InterfaceBuilder<C> {
    name: String,
    engine: Weak<dyn Engine>,
    waker: Arc<dyn Waker>,
    ports: Vec<Arc<dyn DynPort>>,
    operations: Vec<Arc<dyn DynOperation>>,
    properties: PropertyBag,
    attributes: PropertyBag,
    pub(super) provided: Vec<crate::service::ProvidedInfo>,
    pub(super) required: Vec<Arc<crate::service::Requirement>>,
    breaker: Option<Box<dyn Fn() + Send + Sync>>,
    registry: Arc<Registry>,
    _component: std::marker::PhantomData<fn(&mut C)>,
}

impl<C: Send + 'static> InterfaceBuilder<C> {
    pub(crate) fn new(
        name: &str,
        engine: Weak<dyn Engine>,
        waker: Arc<dyn Waker>,
        registry: Arc<Registry>,
    ) -> Self {
        InterfaceBuilder {
            name: name.to_string(),
            engine,
            waker,
            ports: Vec::new(),
            operations: Vec::new(),
            properties: PropertyBag::new("properties"),
            attributes: PropertyBag::new("attributes"),
            provided: Vec::new(),
            required: Vec::new(),
            breaker: None,
            registry,
            _component: std::marker::PhantomData,
        }
    }

    /// What was built: ports, operations, properties and attributes.
    pub(crate) fn into_parts(self) -> BuiltInterface {
        BuiltInterface {
            ports: self.ports,
            operations: self.operations,
            properties: self.properties,
            attributes: self.attributes,
            provided: self.provided,
            required: self.required,
            breaker: self.breaker,
        }
    }

    /// Gives port `port`'s values names (a DBC value description: 3 is "D"): `describe`
    /// lists them, and a write through the dynamic layer takes a name for its value.
    pub fn name_values(
        &mut self,
        port: &str,
        values: Vec<crate::info::NamedValue>,
    ) -> Result<(), IntrospectError> {
        let entry = self
            .ports
            .iter()
            .find(|p| p.info().name == port)
            .ok_or_else(|| IntrospectError::NotFound {
                component: self.name.clone(),
                kind: "port",
                name: port.to_string(),
                known: self.ports.iter().map(|p| p.info().name).collect(),
            })?;
        entry.name_values(values);
        Ok(())
    }

    fn check_port_name(&self, name: &str) -> Result<(), IntrospectError> {
        if self.ports.iter().any(|p| p.info().name == name) {
            return Err(IntrospectError::Duplicate {
                component: self.name.clone(),
                kind: "port",
                name: name.to_string(),
            });
        }
        Ok(())
    }

    /// Adds an output port with `T::default()` as its data sample.
    pub fn output<T: PortData + Default>(
        &mut self,
        name: &str,
        doc: &str,
    ) -> Result<OutputPort<T>, IntrospectError> {
        self.output_with_sample(name, doc, T::default())
    }

    /// Adds an output port whose connections pre-allocate copies of `sample`.
    pub fn output_with_sample<T: PortData>(
        &mut self,
        name: &str,
        doc: &str,
        sample: T,
    ) -> Result<OutputPort<T>, IntrospectError> {
        self.check_port_name(name)?;
        let (port, entry) = output_entry(name, doc, sample);
        self.ports.push(entry);
        Ok(port)
    }

    /// Adds an input port with `T::default()` as its sample.
    pub fn input<T: PortData + Default>(
        &mut self,
        name: &str,
        doc: &str,
    ) -> Result<InputPort<T>, IntrospectError> {
        self.input_with_sample(name, doc, T::default(), false)
    }

    /// Adds an event input port: new data on it wakes a non-periodic or file-descriptor
    /// activity.
    pub fn event_input<T: PortData + Default>(
        &mut self,
        name: &str,
        doc: &str,
    ) -> Result<InputPort<T>, IntrospectError> {
        self.input_with_sample(name, doc, T::default(), true)
    }

    /// Adds an event input port that drives something whose current value can be read
    /// back (a device output): its value, as the control socket's `get` shows it, is
    /// `read_back()` rather than the last sample read; a value written through the dynamic
    /// layer's [`writer`](super::DynPort::writer) must pass `check` first; a value set
    /// through [`drive`](super::DynPort::drive) (the control socket's `set`) is handed to
    /// `apply` at once, which writes it where it goes and answers whether it got there.
    pub fn event_input_driving<T: PortData + Default>(
        &mut self,
        name: &str,
        doc: &str,
        read_back: impl Fn() -> Option<T> + Send + Sync + 'static,
        check: impl Fn(&T) -> Result<(), String> + Send + Sync + 'static,
        apply: impl Fn(&T) -> Result<(), String> + Send + Sync + 'static,
    ) -> Result<InputPort<T>, IntrospectError> {
        let check: Check<T> = Arc::new(check);
        let apply: Check<T> = Arc::new(apply);
        self.add_input(
            name,
            doc,
            T::default(),
            true,
            Some(Box::new(read_back)),
            Some((check, apply)),
        )
    }

    /// Adds an input port keeping its sample in a copy of `sample`.
    pub fn input_with_sample<T: PortData>(
        &mut self,
        name: &str,
        doc: &str,
        sample: T,
        event: bool,
    ) -> Result<InputPort<T>, IntrospectError> {
        self.add_input(name, doc, sample, event, None, None)
    }

    fn add_input<T: PortData>(
        &mut self,
        name: &str,
        doc: &str,
        sample: T,
        event: bool,
        read_back: Option<ReadBack<T>>,
        driving: Option<(Check<T>, Check<T>)>,
    ) -> Result<InputPort<T>, IntrospectError> {
        self.check_port_name(name)?;
        let waker = event.then(|| self.waker.clone());
        let (port, entry) = input_entry(name, doc, sample, waker, read_back, driving);
        self.ports.push(entry);
        Ok(port)
    }

    fn add_operation<A: Args, R: Serialize + Send + 'static>(
        &mut self,
        name: &str,
        doc: &str,
        args: &[(&str, &str)],
        thread: ExecutionThread,
        inner: Arc<dyn crate::operation::Invoke<A, R>>,
    ) -> Result<(), IntrospectError> {
        if self.operations.iter().any(|o| o.info().name == name) {
            return Err(IntrospectError::Duplicate {
                component: self.name.clone(),
                kind: "operation",
                name: name.to_string(),
            });
        }
        let info = OperationInfo {
            name: name.to_string(),
            doc: doc.to_string(),
            args: A::type_names()
                .into_iter()
                .enumerate()
                .map(|(i, t)| {
                    let (n, d) = args.get(i).copied().unwrap_or(("", ""));
                    ArgInfo {
                        name: if n.is_empty() {
                            format!("arg{i}")
                        } else {
                            n.to_string()
                        },
                        doc: d.to_string(),
                        type_name: crate::typename::wire(t),
                    }
                })
                .collect(),
            result: crate::typename::of::<R>(),
            thread,
        };
        self.operations.push(Arc::new(OperationEntry {
            info,
            caller: OperationCaller {
                name: Arc::from(name),
                inner,
            },
        }));
        Ok(())
    }

    /// Adds an operation run in the caller's thread. `args` documents the arguments as
    /// (name, doc) pairs, in order.
    pub fn client_operation<A: Args, R: Serialize + Send + 'static>(
        &mut self,
        name: &str,
        doc: &str,
        args: &[(&str, &str)],
        f: impl Fn(A) -> R + Send + Sync + 'static,
    ) -> Result<(), IntrospectError> {
        let inner = Arc::new(ClientOp {
            name: Arc::from(name),
            f,
        });
        self.add_operation(name, doc, args, ExecutionThread::ClientThread, inner)
    }

    /// Adds an operation run in the component's own thread, with `&mut` access to it.
    pub fn own_operation<A: Args, R: Serialize + Send + 'static>(
        &mut self,
        name: &str,
        doc: &str,
        args: &[(&str, &str)],
        f: impl Fn(&mut C, A) -> R + Send + Sync + 'static,
    ) -> Result<(), IntrospectError> {
        let inner: Arc<dyn crate::operation::Invoke<A, R>> =
            Arc::new(OwnOp::new(name, f, self.engine.clone()));
        self.add_operation(name, doc, args, ExecutionThread::OwnThread, inner)
    }

    /// The component's break hook (RTT's `breakUpdateHook`): called from the stopping
    /// thread before the component's own thread is joined, to interrupt a step blocked in
    /// the component's own code (a read with no timeout: close or signal what it waits on).
    pub fn on_break(&mut self, f: impl Fn() + Send + Sync + 'static) {
        self.breaker = Some(Box::new(f));
    }

    /// The component's properties (configuration).
    pub fn properties(&self) -> &PropertyBag {
        &self.properties
    }

    /// The component's attributes (run-time values).
    pub fn attributes(&self) -> &PropertyBag {
        &self.attributes
    }

    /// The device registry.
    pub fn registry(&self) -> &Arc<Registry> {
        &self.registry
    }

    /// The component's name.
    pub fn name(&self) -> &str {
        &self.name
    }
}

/// A new output port and its entry in the component's list.
pub(super) fn output_entry<T: PortData>(
    name: &str,
    doc: &str,
    sample: T,
) -> (OutputPort<T>, Arc<dyn DynPort>) {
    let port = OutputPort::with_sample(name, sample);
    let entry = Arc::new(OutEntry {
        shared: port.shared().clone(),
        doc: doc.to_string(),
        values: std::sync::OnceLock::new(),
    });
    (port, entry)
}

/// A new input port and its entry in the component's list; with a waker, an event port.
pub(super) fn input_entry<T: PortData>(
    name: &str,
    doc: &str,
    sample: T,
    waker: Option<Arc<dyn Waker>>,
    read_back: Option<ReadBack<T>>,
    driving: Option<(Check<T>, Check<T>)>,
) -> (InputPort<T>, Arc<dyn DynPort>) {
    let port = InputPort::with_sample(name, sample.clone());
    let event = waker.is_some();
    if let Some(w) = waker {
        let _ = port.shared().waker.set(w);
    }
    let entry = Arc::new(InEntry {
        shared: port.shared().clone(),
        doc: doc.to_string(),
        values: std::sync::OnceLock::new(),
        sample,
        event,
        read_back,
        check: driving.as_ref().map(|(c, _)| c.clone()),
        apply: driving.map(|(_, a)| a),
    });
    (port, entry)
}
