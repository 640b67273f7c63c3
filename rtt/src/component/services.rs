//! A component's services: declared through the interface builder ([`Provides`],
//! [`Requires`], required devices), listed and bound on the [`TaskContext`]. The model and
//! the seed lines it follows are in [`crate::service`].

use super::ErasedComponent;
use super::{InterfaceBuilder, TaskContext};
use crate::activity::{FdEvents, StepTiming};
use crate::error::IntrospectError;
use crate::error::LifecycleError;
use crate::info::PortData;
use crate::operation::Args;
use crate::port::{InputPort, OutputPort};
use crate::service::{
    BindError, Multiplicity, ProvidedInfo, RequiredDevices, RequiredInfo, RequiredOperation,
    Requirement,
};
use crate::state::TaskState;
use device_interface::Served;
use serde::Serialize;
use std::sync::Arc;
use std::sync::atomic::Ordering;

impl<C: Send + 'static> InterfaceBuilder<C> {
    /// Opens provided service `service` (RTT 2.0's `provides("camera")`): what is added
    /// through it is named `service.member`.
    pub fn provides(&mut self, service: &str) -> Provides<'_, C> {
        if !self.provided.iter().any(|p| p.name == service) {
            self.provided.push(ProvidedInfo {
                name: service.to_string(),
                operations: Vec::new(),
                ports: Vec::new(),
            });
        }
        Provides {
            iface: self,
            service: service.to_string(),
        }
    }

    /// Declares required service `service` (RTT 2.0's `requires("camera")`): its
    /// operations are added with [`Requires::operation`] and bound as a group at
    /// deployment.
    pub fn requires(&mut self, service: &str) -> Requires<'_, C> {
        let index = match self.required.iter().position(|r| r.name == service) {
            Some(i) => i,
            None => {
                self.required.push(Arc::new(Requirement::service(service)));
                self.required.len() - 1
            }
        };
        Requires { iface: self, index }
    }

    /// Declares required devices `name` of interface `T` (`dyn DigitalOut`, …), bound by
    /// device name at deployment; `multiplicity` says how many it takes. A minimum of zero
    /// makes it optional.
    pub fn requires_devices<T: Served + ?Sized>(
        &mut self,
        name: &str,
        multiplicity: Multiplicity,
    ) -> Result<RequiredDevices<T>, IntrospectError> {
        if self.required.iter().any(|r| r.name == name) {
            return Err(IntrospectError::Duplicate {
                component: self.name().to_string(),
                kind: "requirement",
                name: name.to_string(),
            });
        }
        let (devices, req) = RequiredDevices::<T>::declare(name, multiplicity);
        req.optional
            .store(multiplicity.min == 0, std::sync::atomic::Ordering::Relaxed);
        self.required.push(Arc::new(req));
        Ok(devices)
    }
}

/// Adds operations and ports to a provided service; see [`InterfaceBuilder::provides`].
pub struct Provides<'a, C> {
    iface: &'a mut InterfaceBuilder<C>,
    service: String,
}

impl<C: Send + 'static> Provides<'_, C> {
    fn full(&self, member: &str) -> String {
        format!("{}.{member}", self.service)
    }

    fn info(&mut self) -> &mut ProvidedInfo {
        let service = &self.service;
        let i = self
            .iface
            .provided
            .iter()
            .position(|p| &p.name == service)
            .unwrap_or(0);
        &mut self.iface.provided[i]
    }

    /// An operation of the service run in the caller's thread; see
    /// [`InterfaceBuilder::client_operation`].
    pub fn client_operation<A: Args, R: Serialize + Send + 'static>(
        &mut self,
        name: &str,
        doc: &str,
        args: &[(&str, &str)],
        f: impl Fn(A) -> R + Send + Sync + 'static,
    ) -> Result<&mut Self, IntrospectError> {
        self.iface
            .client_operation(&self.full(name), doc, args, f)?;
        self.info().operations.push(name.to_string());
        Ok(self)
    }

    /// An operation of the service run in the component's thread; see
    /// [`InterfaceBuilder::own_operation`].
    pub fn own_operation<A: Args, R: Serialize + Send + 'static>(
        &mut self,
        name: &str,
        doc: &str,
        args: &[(&str, &str)],
        f: impl Fn(&mut C, A) -> R + Send + Sync + 'static,
    ) -> Result<&mut Self, IntrospectError> {
        self.iface.own_operation(&self.full(name), doc, args, f)?;
        self.info().operations.push(name.to_string());
        Ok(self)
    }

    /// An output port of the service.
    pub fn output<T: PortData + Default>(
        &mut self,
        name: &str,
        doc: &str,
    ) -> Result<OutputPort<T>, IntrospectError> {
        let port = self.iface.output(&self.full(name), doc)?;
        self.info().ports.push(name.to_string());
        Ok(port)
    }

    /// An input port of the service.
    pub fn input<T: PortData + Default>(
        &mut self,
        name: &str,
        doc: &str,
    ) -> Result<InputPort<T>, IntrospectError> {
        let port = self.iface.input(&self.full(name), doc)?;
        self.info().ports.push(name.to_string());
        Ok(port)
    }
}

/// Adds operations to a required service; see [`InterfaceBuilder::requires`].
pub struct Requires<'a, C> {
    iface: &'a mut InterfaceBuilder<C>,
    index: usize,
}

impl<C: Send + 'static> Requires<'_, C> {
    /// The component configures and starts without this service bound.
    pub fn optional(self) -> Self {
        self.iface.required[self.index]
            .optional
            .store(true, std::sync::atomic::Ordering::Relaxed);
        self
    }

    /// Requires operation `name` of type `fn(A) -> R`; bound to the provider's
    /// `service.name`, which must be of the same type.
    ///
    /// Its arguments are serializable and its result deserializable, so it can be bound
    /// to a provider in another process too ([`crate::service::RemoteProvider`]).
    pub fn operation<A, R>(
        &mut self,
        name: &str,
    ) -> Result<RequiredOperation<A, R>, IntrospectError>
    where
        A: Args + Serialize,
        R: Serialize + serde::de::DeserializeOwned + Send + 'static,
    {
        let req = &self.iface.required[self.index];
        let crate::service::Kind::Service { cell, members } = &req.kind else {
            return Err(IntrospectError::Duplicate {
                component: self.iface.name().to_string(),
                kind: "requirement",
                name: req.name.clone(),
            });
        };
        let mut members = crate::lock(members);
        if members.iter().any(|m| m.name() == name) {
            return Err(IntrospectError::Duplicate {
                component: self.iface.name().to_string(),
                kind: "required operation",
                name: format!("{}.{name}", req.name),
            });
        }
        let (op, member) = RequiredOperation::<A, R>::declare(name, cell.clone());
        members.push(member);
        Ok(op)
    }
}

impl TaskContext {
    /// The services this component provides.
    pub fn provided(&self) -> Vec<ProvidedInfo> {
        self.core.provided.clone()
    }

    /// What this component requires, with each binding and whether it is ready.
    pub fn required(&self) -> Vec<RequiredInfo> {
        self.core.required.iter().map(|r| r.info()).collect()
    }

    fn requirement(&self, name: &str) -> Result<&Requirement, BindError> {
        self.core
            .required
            .iter()
            .find(|r| r.name == name)
            .map(|r| &**r)
            .ok_or_else(|| BindError::UnknownRequirement {
                component: self.name().to_string(),
                name: name.to_string(),
                known: self.core.required.iter().map(|r| r.name.clone()).collect(),
            })
    }

    /// Binds required service `requirement` to `provider`'s service `service`: every
    /// required operation to the provided operation of the same name, each checked for its
    /// type; all or nothing. With `check_only` nothing changes.
    pub fn bind_service(
        &self,
        requirement: &str,
        provider: &TaskContext,
        service: &str,
        check_only: bool,
    ) -> Result<(), BindError> {
        self.requirement(requirement)?.bind_service(
            self.name(),
            provider,
            provider.core.state.clone(),
            service,
            check_only,
        )
    }

    /// Binds service requirement `requirement` to a provider in another process (a
    /// component of another gateway); its types are the provider's owner's to check.
    pub fn bind_remote_service(
        &self,
        requirement: &str,
        provider: &crate::service::RemoteProvider,
        check_only: bool,
    ) -> Result<(), BindError> {
        self.requirement(requirement)?
            .bind_remote(self.name(), provider, check_only)
    }

    /// Binds required devices `requirement` to the devices named `names` in the
    /// component's registry; all or nothing. With `check_only` nothing changes.
    pub fn bind_devices(
        &self,
        requirement: &str,
        names: &[String],
        check_only: bool,
    ) -> Result<(), BindError> {
        self.requirement(requirement)?.bind_devices(
            self.name(),
            &self.core.registry,
            names,
            check_only,
        )
    }

    /// Takes requirement `requirement`'s binding away.
    pub fn unbind(&self, requirement: &str) -> Result<(), BindError> {
        self.requirement(requirement)?.unbind();
        Ok(())
    }
}

impl super::TaskCore {
    /// Tells the component of each requirement that stopped or started being ready since
    /// the last look: atomic loads when nothing changed.
    pub(super) fn look_at_requirements(
        &self,
        comp: &mut dyn ErasedComponent,
        events: &FdEvents,
        timing: StepTiming,
    ) {
        for req in &self.required {
            let Some(back) = req.look() else { continue };
            let name = req.name.as_str();
            let (r, asked) = self.run_hook(comp, events, timing, |c, ctx| {
                if back {
                    c.service_back(ctx, name)
                } else {
                    c.service_lost(ctx, name)
                }
            });
            match r {
                Err(panic) => {
                    self.enter_exception(comp, format!("service hook panicked: {panic}"));
                    return;
                }
                Ok(()) if asked.exception.is_some() => {
                    let reason = asked.exception.unwrap_or_default();
                    self.enter_exception(
                        comp,
                        format!("service hook raised an exception: {reason}"),
                    );
                    return;
                }
                Ok(()) if asked.error && self.state() == TaskState::Running => {
                    self.runtime_errors.fetch_add(1, Ordering::Relaxed);
                    self.set_state(TaskState::RunTimeError);
                }
                Ok(()) if asked.recover && self.state() == TaskState::RunTimeError => {
                    self.set_state(TaskState::Running);
                }
                Ok(()) => {}
            }
        }
    }

    /// The first requirement that is neither bound nor optional, as the refusal of
    /// `command`.
    pub(super) fn unbound(&self) -> Result<(), LifecycleError> {
        match self.required.iter().find(|r| !r.satisfied()) {
            Some(r) => Err(LifecycleError::Unbound {
                component: self.name.clone(),
                requirement: r.name.clone(),
            }),
            None => Ok(()),
        }
    }
}
