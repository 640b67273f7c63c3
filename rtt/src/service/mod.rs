//! Services, provided and required.
//!
//! RTT 2.0 road map: "A component always specifies if a service is provided or requested.
//! This allows run-time dependency and system state checking, but also automatic
//! connection/disconnection management" (L46); "Allow to specify requires interfaces …
//! such that they can be automatically connected during application deployment. The
//! required primitives are grouped in interfaces, such that they can be connected as a
//! group from provider to requirer" (L458–464); the `requires("Camera")->addMethod(...)`
//! example, where the deployment sets up the method (L614–628); and "Components are aware
//! of the available services … They are notified in time such that they can take proper
//! action and recover and resume when a service becomes available again" (L74–76).
//!
//! - **Provided**: [`InterfaceBuilder::provides`](crate::InterfaceBuilder::provides) opens a
//!   named service; its operations and ports are named `service.member`, so they are found,
//!   listed and called by name as any other (`hwgw call cam0 camera.set_resolution 640 480`).
//! - **Required operations**: [`InterfaceBuilder::requires`](crate::InterfaceBuilder::requires)
//!   declares a service the component needs and, typed, the operations it calls
//!   ([`RequiredOperation`]). [`TaskContext::bind_service`](crate::TaskContext::bind_service)
//!   binds them as a group to a provider's service, each operation checked for its type.
//! - **Required devices**: [`InterfaceBuilder::requires_devices`](crate::InterfaceBuilder::requires_devices)
//!   declares devices of one interface with a [`Multiplicity`] (`one`, `0..2`, `*`), bound
//!   by name with [`TaskContext::bind_devices`](crate::TaskContext::bind_devices).
//! - **Readiness**: a required service is ready while it is bound and its provider is
//!   Running; required devices while every bound device is online. `ready()` is an atomic
//!   load or two, no lock, for the real-time path.
//! - **Loss and return**: before each step of a running component its engine looks at
//!   every requirement; one that stopped being ready calls the component's
//!   [`service_lost`](crate::Component::service_lost) hook, one that is ready again
//!   [`service_back`](crate::Component::service_back); both are counted. Nothing has to
//!   rebind: a provider that is Running again makes the binding ready by itself.
//! - A requirement that is not optional and not bound refuses `configure` and `start`,
//!   naming it.
//! - **Remote providers**: [`TaskContext::bind_remote_service`](crate::TaskContext::bind_remote_service)
//!   binds a requirement to a [`RemoteProvider`] — a service of another process, its calls
//!   carried as JSON, its state kept current by its owner — lost and back like a local one.

use crate::operation::{Args, CallError, OperationCaller, SendHandle};
use crate::state::{StateCell, TaskState};
use arc_swap::{ArcSwap, ArcSwapOption};
use device_interface::{Registry, RegistryError, Served, Status};
use serde::Serialize;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

mod remote;
mod types;
pub use remote::{RemoteCall, RemoteProvider, RemoteState};
pub use types::{
    BindError, Multiplicity, MultiplicityError, OperationAt, ProvidedInfo, RequiredInfo,
    RequiredKind,
};

/// Whether a requirement can be used now: lock-free.
pub(crate) trait Readiness: Send + Sync {
    /// Bound (enough devices), whatever its provider's state.
    fn bound(&self) -> bool;
    /// Bound and usable now.
    fn ready(&self) -> bool;
}

/// Binds one required operation to a provider's operation, once every member of the
/// service has been found: the check and the change are apart so a binding applies whole
/// or not at all.
type Resolve = Box<
    dyn Fn(&crate::TaskContext, &str) -> Result<Box<dyn FnOnce() + Send>, ResolveError>
        + Send
        + Sync,
>;

/// Why one member did not resolve.
pub(crate) enum ResolveError {
    Missing,
    WrongType(String),
}

/// Binds one required operation to a remote provider's operation (`service.member`).
type ResolveRemote =
    Box<dyn Fn(&Arc<dyn RemoteCall>, &str) -> Box<dyn FnOnce() + Send> + Send + Sync>;

pub(crate) struct Member {
    name: String,
    signature: String,
    resolve: Resolve,
    resolve_remote: ResolveRemote,
    unbind: Box<dyn Fn() + Send + Sync>,
}

impl Member {
    pub(crate) fn name(&self) -> &str {
        &self.name
    }
}

/// The provider side of a service requirement: whose state tells readiness.
#[derive(Default)]
pub(crate) struct ServiceCell {
    provider: ArcSwapOption<StateCell>,
    /// A remote provider's caller, held while it is bound (not read on any hot path).
    remote: Mutex<Option<Arc<dyn RemoteCall>>>,
}

impl Readiness for ServiceCell {
    fn bound(&self) -> bool {
        self.provider.load().is_some()
    }

    fn ready(&self) -> bool {
        self.provider
            .load()
            .as_ref()
            .is_some_and(|s| s.get() == TaskState::Running)
    }
}

type DeviceBind = Box<
    dyn Fn(&Registry, &[String]) -> Result<Box<dyn FnOnce() + Send>, RegistryError> + Send + Sync,
>;

pub(crate) enum Kind {
    Service {
        cell: Arc<ServiceCell>,
        members: Mutex<Vec<Member>>,
    },
    Devices {
        interface: device_interface::Interface,
        multiplicity: Multiplicity,
        ready: Arc<dyn Readiness>,
        bind: DeviceBind,
        clear: Box<dyn Fn() + Send + Sync>,
    },
}

/// One requirement of a component.
pub(crate) struct Requirement {
    pub(crate) name: String,
    pub(crate) optional: AtomicBool,
    pub(crate) kind: Kind,
    /// Readiness at the last look (the engine's, before a step).
    pub(crate) last_ready: AtomicBool,
    lost: AtomicU64,
    back: AtomicU64,
    bound_to: Mutex<Vec<String>>,
}

impl Requirement {
    pub(crate) fn service(name: &str) -> Requirement {
        Requirement::new(
            name,
            Kind::Service {
                cell: Arc::new(ServiceCell::default()),
                members: Mutex::new(Vec::new()),
            },
        )
    }

    fn new(name: &str, kind: Kind) -> Requirement {
        Requirement {
            name: name.to_string(),
            optional: AtomicBool::new(false),
            kind,
            last_ready: AtomicBool::new(false),
            lost: AtomicU64::new(0),
            back: AtomicU64::new(0),
            bound_to: Mutex::new(Vec::new()),
        }
    }

    fn readiness(&self) -> &dyn Readiness {
        match &self.kind {
            Kind::Service { cell, .. } => &**cell,
            Kind::Devices { ready, .. } => &**ready,
        }
    }

    /// Whether it is bound and usable now (lock-free).
    pub(crate) fn ready(&self) -> bool {
        self.readiness().ready()
    }

    /// Whether a component needing it may configure and start.
    pub(crate) fn satisfied(&self) -> bool {
        self.optional.load(Ordering::Relaxed) || self.readiness().bound()
    }

    /// Notes a change of readiness seen by the engine: `Some(true)` back, `Some(false)`
    /// lost, `None` no change.
    pub(crate) fn look(&self) -> Option<bool> {
        let now = self.ready();
        if self.last_ready.swap(now, Ordering::Relaxed) == now {
            return None;
        }
        let counter = if now { &self.back } else { &self.lost };
        counter.fetch_add(1, Ordering::Relaxed);
        Some(now)
    }

    /// Lost and back start again from zero (at `cleanup`).
    pub(crate) fn reset_counts(&self) {
        self.lost.store(0, Ordering::Relaxed);
        self.back.store(0, Ordering::Relaxed);
    }

    /// (lost, back).
    pub(crate) fn counts(&self) -> (u64, u64) {
        (
            self.lost.load(Ordering::Relaxed),
            self.back.load(Ordering::Relaxed),
        )
    }

    pub(crate) fn info(&self) -> RequiredInfo {
        let kind = match &self.kind {
            Kind::Service { members, .. } => RequiredKind::Service {
                operations: crate::lock(members)
                    .iter()
                    .map(|m| format!("{}{}", m.name, m.signature))
                    .collect(),
            },
            Kind::Devices {
                interface,
                multiplicity,
                ..
            } => RequiredKind::Devices {
                interface: interface.to_string(),
                multiplicity: multiplicity.to_string(),
            },
        };
        RequiredInfo {
            name: self.name.clone(),
            kind,
            optional: self.optional.load(Ordering::Relaxed),
            bound_to: crate::lock(&self.bound_to).clone(),
            ready: self.ready(),
            lost: self.lost.load(Ordering::Relaxed),
            back: self.back.load(Ordering::Relaxed),
        }
    }

    /// What it is, for an error.
    fn kind_text(&self) -> String {
        match &self.kind {
            Kind::Service { .. } => "a service".into(),
            Kind::Devices { interface, .. } => format!("{interface} devices"),
        }
    }

    /// A service requirement's cell and members; [`BindError::WrongKind`] for devices.
    fn service_parts(
        &self,
        component: &str,
    ) -> Result<(&Arc<ServiceCell>, &Mutex<Vec<Member>>), BindError> {
        match &self.kind {
            Kind::Service { cell, members } => Ok((cell, members)),
            Kind::Devices { .. } => Err(BindError::WrongKind {
                component: component.to_string(),
                name: self.name.clone(),
                expected: self.kind_text(),
                given: "a service",
            }),
        }
    }

    /// Binds a service requirement to `provider`'s `service` (its state cell given), whole
    /// or not at all.
    pub(crate) fn bind_service(
        &self,
        component: &str,
        provider: &crate::TaskContext,
        provider_state: Arc<StateCell>,
        service: &str,
        check_only: bool,
    ) -> Result<(), BindError> {
        let (cell, members) = self.service_parts(component)?;
        let label = format!("{}.{service}", provider.name());
        let same = cell
            .provider
            .load()
            .as_ref()
            .is_some_and(|s| Arc::ptr_eq(s, &provider_state));
        if same && crate::lock(&self.bound_to).first() == Some(&label) {
            // Bound to that very provider already: nothing to change, nothing to tell.
            return Ok(());
        }
        let provided = provider.provided();
        if !provided.iter().any(|p| p.name == service) {
            return Err(BindError::NotProvided {
                provider: provider.name().to_string(),
                service: service.to_string(),
                known: provided.into_iter().map(|p| p.name).collect(),
            });
        }
        let members = crate::lock(members);
        let mut applies = Vec::with_capacity(members.len());
        for m in members.iter() {
            let full = format!("{service}.{}", m.name);
            match (m.resolve)(provider, &full) {
                Ok(apply) => applies.push(apply),
                Err(e) => {
                    let at = Box::new(OperationAt {
                        component: component.to_string(),
                        provider: provider.name().to_string(),
                        service: service.to_string(),
                        operation: m.name.clone(),
                    });
                    let required = m.signature.clone();
                    return Err(match e {
                        ResolveError::Missing => BindError::MissingOperation { at, required },
                        ResolveError::WrongType(provided) => BindError::WrongType {
                            at,
                            provided,
                            required,
                        },
                    });
                }
            }
        }
        if check_only {
            return Ok(());
        }
        // Not ready while the members change, so no call reaches a mix of two providers.
        let was_bound = cell.provider.swap(None).is_some();
        for apply in applies {
            apply();
        }
        cell.provider.store(Some(provider_state));
        *crate::lock(&cell.remote) = None;
        *crate::lock(&self.bound_to) = vec![label];
        if !was_bound {
            // Bound as ready: the engine's first look reports a provider that is not
            // running. A binding moved keeps what the engine last saw, so a loss is told
            // once, and the return once.
            self.last_ready.store(true, Ordering::Relaxed);
        }
        Ok(())
    }

    /// Binds a service requirement to a remote provider. Its types are the owner's to
    /// check (it keeps the provider's state not Running while they differ): nothing here
    /// can see the other process. Bound to that label already: nothing changes.
    pub(crate) fn bind_remote(
        &self,
        component: &str,
        provider: &RemoteProvider,
        check_only: bool,
    ) -> Result<(), BindError> {
        let (cell, members) = self.service_parts(component)?;
        let same = crate::lock(&cell.remote).is_some()
            && crate::lock(&self.bound_to).first() == Some(&provider.label);
        if same || check_only {
            return Ok(());
        }
        let members = crate::lock(members);
        let applies: Vec<_> = members
            .iter()
            .map(|m| {
                (m.resolve_remote)(&provider.call, &format!("{}.{}", provider.service, m.name))
            })
            .collect();
        let was_bound = cell.provider.swap(None).is_some();
        for apply in applies {
            apply();
        }
        *crate::lock(&cell.remote) = Some(provider.call.clone());
        cell.provider.store(Some(provider.state.0.clone()));
        *crate::lock(&self.bound_to) = vec![provider.label.clone()];
        if !was_bound {
            self.last_ready.store(true, Ordering::Relaxed);
        }
        Ok(())
    }

    /// Binds a device requirement to the devices `names`, whole or not at all.
    pub(crate) fn bind_devices(
        &self,
        component: &str,
        registry: &Registry,
        names: &[String],
        check_only: bool,
    ) -> Result<(), BindError> {
        let Kind::Devices {
            interface,
            multiplicity,
            bind,
            ..
        } = &self.kind
        else {
            return Err(BindError::WrongKind {
                component: component.to_string(),
                name: self.name.clone(),
                expected: self.kind_text(),
                given: "devices",
            });
        };
        if let Some((_, d)) = names
            .iter()
            .enumerate()
            .find(|(i, d)| names[..*i].contains(d))
        {
            return Err(BindError::DuplicateDevice {
                component: component.to_string(),
                name: self.name.clone(),
                device: d.clone(),
            });
        }
        if !multiplicity.admits(names.len()) {
            return Err(BindError::Multiplicity {
                component: component.to_string(),
                name: self.name.clone(),
                interface: interface.to_string(),
                multiplicity: *multiplicity,
                given: names.len(),
            });
        }
        let apply = bind(registry, names).map_err(|source| BindError::Device {
            component: component.to_string(),
            name: self.name.clone(),
            source: Box::new(source),
        })?;
        if check_only {
            return Ok(());
        }
        let was_bound = !crate::lock(&self.bound_to).is_empty();
        apply();
        *crate::lock(&self.bound_to) = names.to_vec();
        if !was_bound {
            self.last_ready.store(true, Ordering::Relaxed);
        }
        Ok(())
    }

    /// Takes the binding away (a provider unloaded): not ready, no hook.
    pub(crate) fn unbind(&self) {
        match &self.kind {
            Kind::Service { cell, members } => {
                cell.provider.store(None);
                for m in crate::lock(members).iter() {
                    (m.unbind)();
                }
                *crate::lock(&cell.remote) = None;
            }
            Kind::Devices { clear, .. } => clear(),
        }
        crate::lock(&self.bound_to).clear();
        self.last_ready.store(false, Ordering::Relaxed);
    }
}

/// An operation a component requires, bound at deployment to a provider's operation of the
/// same name and type (RTT 2.0's `Method<bool(int,int)> setreso("setResolution")` added to
/// `requires("Camera")`).
pub struct RequiredOperation<A, R> {
    name: Arc<str>,
    caller: Arc<ArcSwapOption<OperationCaller<A, R>>>,
    cell: Arc<ServiceCell>,
}

impl<A, R> Clone for RequiredOperation<A, R> {
    fn clone(&self) -> Self {
        RequiredOperation {
            name: self.name.clone(),
            caller: self.caller.clone(),
            cell: self.cell.clone(),
        }
    }
}

impl<A, R> RequiredOperation<A, R> {
    /// Bound, and its provider Running: a lock-free look, for the real-time path.
    pub fn ready(&self) -> bool {
        self.cell.ready() && self.caller.load().is_some()
    }

    /// Calls the provider's operation and waits for its result; refused with
    /// [`CallError::NotReady`] when the binding is not [`ready`](Self::ready) — also when
    /// the provider stopped between the look and the call (its queue drained, the call
    /// cancelled), so a caller treats one error as a lost service.
    pub fn call(&self, args: A) -> Result<R, CallError> {
        match &*self.caller.load() {
            Some(c) if self.cell.ready() => c.call(args).map_err(|e| self.lost(e)),
            _ => Err(self.not_ready()),
        }
    }

    /// A provider that went away during a call is a binding not ready.
    fn lost(&self, e: CallError) -> CallError {
        match e {
            CallError::NotRunning { .. }
            | CallError::Cancelled { .. }
            | CallError::Vanished { .. } => self.not_ready(),
            e => e,
        }
    }

    /// Starts the provider's operation; the handle collects the result.
    pub fn send(&self, args: A) -> SendHandle<R> {
        match &*self.caller.load() {
            Some(c) if self.cell.ready() => c.send(args),
            _ => SendHandle::ready(Err(self.not_ready())),
        }
    }

    /// The operation's name, without the service.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// No allocation: the name is shared.
    fn not_ready(&self) -> CallError {
        CallError::NotReady {
            operation: self.name.clone(),
        }
    }
}

impl<A, R> RequiredOperation<A, R>
where
    A: Args + Serialize,
    R: Serialize + serde::de::DeserializeOwned + Send + 'static,
{
    pub(crate) fn declare(name: &str, cell: Arc<ServiceCell>) -> (RequiredOperation<A, R>, Member) {
        let op = RequiredOperation {
            name: Arc::from(name),
            caller: Arc::new(ArcSwapOption::empty()),
            cell,
        };
        let slot = op.caller.clone();
        let remote_slot = op.caller.clone();
        let unbind_slot = op.caller.clone();
        let member = Member {
            name: name.to_string(),
            signature: signature(
                &A::type_names()
                    .into_iter()
                    .map(crate::typename::wire)
                    .collect::<Vec<_>>(),
                &crate::typename::of::<R>(),
            ),
            resolve: Box::new(move |provider, full| {
                let Some(info) = provider.operations().into_iter().find(|o| o.name == full) else {
                    return Err(ResolveError::Missing);
                };
                match provider.operation::<A, R>(full) {
                    Ok(caller) => {
                        let slot = slot.clone();
                        Ok(Box::new(move || slot.store(Some(Arc::new(caller)))))
                    }
                    Err(_) => Err(ResolveError::WrongType(info_signature(&info))),
                }
            }),
            resolve_remote: Box::new(move |call, full| {
                let caller = OperationCaller {
                    name: Arc::from(full),
                    inner: Arc::new(remote::RemoteOp::<A, R> {
                        name: Arc::from(full),
                        call: call.clone(),
                        _types: std::marker::PhantomData,
                    }),
                };
                let slot = remote_slot.clone();
                Box::new(move || slot.store(Some(Arc::new(caller))))
            }),
            unbind: Box::new(move || unbind_slot.store(None)),
        };
        (op, member)
    }
}

fn signature(args: &[String], result: &str) -> String {
    let r = if result.is_empty() {
        String::new()
    } else {
        format!(" -> {result}")
    };
    format!("({}){r}", args.join(", "))
}

/// An operation's type as listed: `(u32, u32) -> bool`.
pub fn info_signature(info: &crate::operation::OperationInfo) -> String {
    let args: Vec<String> = info.args.iter().map(|a| a.type_name.clone()).collect();
    signature(&args, &info.result)
}

/// Devices of one interface a component requires, bound by name at deployment.
pub struct RequiredDevices<T: ?Sized> {
    devices: Arc<ArcSwap<Vec<Arc<T>>>>,
    /// The fewest it works with.
    min: usize,
}

impl<T: ?Sized> Clone for RequiredDevices<T> {
    fn clone(&self) -> Self {
        RequiredDevices {
            devices: self.devices.clone(),
            min: self.min,
        }
    }
}

impl<T: Served + ?Sized> RequiredDevices<T> {
    pub(crate) fn declare(name: &str, multiplicity: Multiplicity) -> (Self, Requirement) {
        let devices: Arc<ArcSwap<Vec<Arc<T>>>> = Arc::new(ArcSwap::from_pointee(Vec::new()));
        let cell = devices.clone();
        let cleared = devices.clone();
        let ready: Arc<dyn Readiness> = Arc::new(DevicesReady {
            devices: devices.clone(),
            min: multiplicity.min as usize,
        });
        let bind: DeviceBind = Box::new(move |registry, names| {
            let found = names
                .iter()
                .map(|n| T::server(registry).lookup(n))
                .collect::<Result<Vec<_>, _>>()?;
            let cell = cell.clone();
            Ok(Box::new(move || cell.store(Arc::new(found))))
        });
        let req = Requirement::new(
            name,
            Kind::Devices {
                interface: T::INTERFACE,
                multiplicity,
                ready,
                bind,
                clear: Box::new(move || cleared.store(Arc::new(Vec::new()))),
            },
        );
        (
            RequiredDevices {
                devices,
                min: multiplicity.min as usize,
            },
            req,
        )
    }

    /// The bound devices, in the order the deployment names them (a lock-free load).
    pub fn get(&self) -> arc_swap::Guard<Arc<Vec<Arc<T>>>> {
        self.devices.load()
    }

    /// How many are bound.
    pub fn len(&self) -> usize {
        self.devices.load().len()
    }

    /// Whether none is bound.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bound (at least the multiplicity's minimum) and every bound device online.
    pub fn ready(&self) -> bool {
        let d = self.devices.load();
        d.len() >= self.min && d.iter().all(|x| x.health().status == Status::Online)
    }
}

struct DevicesReady<T: ?Sized> {
    devices: Arc<ArcSwap<Vec<Arc<T>>>>,
    min: usize,
}

impl<T: Served + ?Sized> Readiness for DevicesReady<T> {
    fn bound(&self) -> bool {
        self.devices.load().len() >= self.min
    }

    fn ready(&self) -> bool {
        let d = self.devices.load();
        d.len() >= self.min && d.iter().all(|x| x.health().status == Status::Online)
    }
}
