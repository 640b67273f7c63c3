//! What a hook can see and ask for: the [`Context`] each hook gets — the component's
//! name, state, registry, clock, peers, its activity's events and timing — and the error
//! model's requests (manual L832–884): `error`, `recover`, `warning`, `recovered`,
//! `exception`, carried out once the hook returns.

use super::{IntrospectError, TaskContext, TaskCore};
use crate::activity::{Activity, FdEvents, StepTiming};
use crate::info::PortData;
use crate::lock::lock;
use crate::port::{InputPort, OutputPort};
use crate::state::TaskState;
use device_interface::Registry;
use device_interface::time::Timestamp;
use std::sync::Arc;
use std::sync::atomic::Ordering;

/// What a hook can see and ask for.
pub struct Context<'a> {
    pub(super) core: &'a TaskCore,
    pub(super) events: &'a FdEvents,
    pub(super) timing: StepTiming,
    pub(super) asked: Asked,
}

/// What a hook asked for through its [`Context`], done once it returns.
#[derive(Default)]
pub(super) struct Asked {
    pub(super) error: bool,
    pub(super) recover: bool,
    pub(super) exception: Option<String>,
}

impl Context<'_> {
    /// The component's name.
    pub fn name(&self) -> &str {
        &self.core.name
    }

    /// The component's state.
    pub fn state(&self) -> TaskState {
        self.core.state()
    }

    /// The device registry: look devices up by name here.
    pub fn registry(&self) -> &Arc<Registry> {
        &self.core.registry
    }

    /// The runtime's clock.
    pub fn now(&self) -> Timestamp {
        self.core.clock.now()
    }

    /// From `update_hook`: go to RunTimeError after this step (the error hook then runs
    /// instead of update until [`recover`](Self::recover)).
    pub fn error(&mut self) {
        self.asked.error = true;
    }

    /// From `error_hook`: return to Running after this step.
    pub fn recover(&mut self) {
        self.asked.recover = true;
    }

    /// Raises the component's warning flag (manual L832–884: the component keeps running,
    /// something is not as it should be): shown in `ls` and `status`, counted once per
    /// raise; [`recovered`](Self::recovered) clears it. Lock-free.
    pub fn warning(&mut self) {
        if !self.core.warning.swap(true, Ordering::Relaxed) {
            self.core.warnings.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Clears the warning flag and, from RunTimeError, returns to Running after this step.
    pub fn recovered(&mut self) {
        self.core.warning.store(false, Ordering::Relaxed);
        self.asked.recover = true;
    }

    /// From any hook: enter Exception once the hook returns (the manual's unrecoverable
    /// error: corrupt data, a broken invariant), with `reason` recorded. Its `reset_hook`
    /// runs when it is recovered.
    pub fn exception(&mut self, reason: impl Into<String>) {
        self.asked.exception = Some(reason.into());
    }

    /// What the component may keep of itself beyond a hook: it adds ports the component
    /// learns of only after it was built (a script declares its own while it configures,
    /// and again when it is reloaded) and finds peers outside hooks (a script's callbacks).
    pub fn self_ref(&self) -> SelfRef {
        SelfRef {
            core: self.core.me.clone(),
        }
    }

    /// For a file-descriptor activity: which descriptors woke this step, or the timeout.
    pub fn fd_events(&self) -> &FdEvents {
        self.events
    }

    /// When this step was due and when it began (for a lifecycle hook: when it was called).
    pub fn timing(&self) -> StepTiming {
        self.timing
    }

    /// The component's activity (to watch file descriptors, read statistics).
    pub fn activity(&self) -> &Activity {
        &self.core.activity
    }

    /// Another component of the same runtime, by name or by the alias the deployment gave
    /// it for this component (`peers = { device = "press_io" }`), for configure-time wiring
    /// as RTT peers (a reporter connecting to the ports it records). Not for real-time
    /// paths.
    pub fn peer(&self, name: &str) -> Result<TaskContext, IntrospectError> {
        find_peer(self.core, name)
    }
}

/// What a component keeps of itself beyond a hook (a weak reference: it never keeps the
/// component alive). It adds ports after the component was built — while it is
/// PreOperational or Stopped (configuring, or reloaded while stopped), never while it runs;
/// a port added is there for connections from then on, for the component's whole life —
/// and finds peers as [`Context::peer`] does. Neither is for real-time paths.
#[derive(Clone)]
pub struct SelfRef {
    core: std::sync::Weak<TaskCore>,
}

impl SelfRef {
    /// The component itself, while it exists.
    pub fn task(&self) -> Option<TaskContext> {
        self.core.upgrade().map(|core| TaskContext { core })
    }

    /// Another component of the same runtime, as [`Context::peer`] finds it.
    pub fn peer(&self, name: &str) -> Result<TaskContext, IntrospectError> {
        let core = self
            .core
            .upgrade()
            .ok_or_else(|| IntrospectError::NotFound {
                component: "runtime".into(),
                kind: "component",
                name: name.to_string(),
                known: Vec::new(),
            })?;
        find_peer(&core, name)
    }

    /// The component providing service `service`: the peer the component's alias of
    /// that name names (`peers = { limit = "thr" }`), else the one component of the
    /// runtime that provides it; none or several is an error naming them.
    pub fn provider(&self, service: &str) -> Result<TaskContext, IntrospectError> {
        let core = self
            .core
            .upgrade()
            .ok_or_else(|| IntrospectError::NotFound {
                component: "runtime".into(),
                kind: "service",
                name: service.to_string(),
                known: Vec::new(),
            })?;
        if lock(&core.peer_aliases).iter().any(|(a, _)| a == service) {
            return find_peer(&core, service);
        }
        let peers = core.peers.upgrade();
        let list = peers.as_ref().map(|p| lock(p).clone()).unwrap_or_default();
        let providing: Vec<TaskContext> = list
            .into_iter()
            .filter(|t| t.provided().iter().any(|p| p.name == service))
            .collect();
        match providing.as_slice() {
            [one] => Ok(one.clone()),
            _ => Err(IntrospectError::NotFound {
                component: core.name.clone(),
                kind: "single provider of service",
                name: service.to_string(),
                known: providing.iter().map(|t| t.name().to_string()).collect(),
            }),
        }
    }

    /// Adds output port `name`; refused while running or when the name is taken.
    pub fn add_output<T: PortData + Default>(
        &self,
        name: &str,
        doc: &str,
    ) -> Result<OutputPort<T>, IntrospectError> {
        let core = self.may_add(name)?;
        let (port, entry) = super::builder::output_entry(name, doc, T::default());
        push_port(&core, entry);
        Ok(port)
    }

    /// Adds input port `name`, as [`add_output`](Self::add_output); an `event` port wakes a
    /// non-periodic or file-descriptor activity when data comes.
    pub fn add_input<T: PortData + Default>(
        &self,
        name: &str,
        doc: &str,
        event: bool,
    ) -> Result<InputPort<T>, IntrospectError> {
        let core = self.may_add(name)?;
        let waker = event.then(|| core.activity.waker());
        let (port, entry) = super::builder::input_entry(name, doc, T::default(), waker, None, None);
        push_port(&core, entry);
        Ok(port)
    }

    fn may_add(&self, name: &str) -> Result<Arc<TaskCore>, IntrospectError> {
        let refused = |detail: String| IntrospectError::Refused {
            what: format!("port {name:?}"),
            detail,
        };
        let core = self
            .core
            .upgrade()
            .ok_or_else(|| refused("the component is gone".into()))?;
        let state = core.state();
        if !matches!(state, TaskState::PreOperational | TaskState::Stopped) {
            return Err(refused(format!(
                "{:?} adds ports while configured or stopped, not in {state:?}",
                core.name
            )));
        }
        if core.ports.load().iter().any(|p| p.info().name == name) {
            return Err(IntrospectError::Duplicate {
                component: core.name.clone(),
                kind: "port",
                name: name.to_string(),
            });
        }
        Ok(core)
    }
}

fn push_port(core: &TaskCore, entry: Arc<dyn super::DynPort>) {
    core.ports.rcu(|list| {
        let mut list = Vec::clone(list);
        list.push(entry.clone());
        list
    });
}

/// Component `name` of `core`'s runtime, by name or by `core`'s alias for it.
fn find_peer(core: &TaskCore, name: &str) -> Result<TaskContext, IntrospectError> {
    let aliased = lock(&core.peer_aliases)
        .iter()
        .find(|(a, _)| a == name)
        .map(|(_, t)| t.clone());
    let name = aliased.as_deref().unwrap_or(name);
    let peers = core.peers.upgrade();
    let list = peers.as_ref().map(|p| lock(p).clone()).unwrap_or_default();
    list.iter()
        .find(|t| t.name() == name)
        .cloned()
        .ok_or_else(|| IntrospectError::NotFound {
            component: core.name.clone(),
            kind: "peer",
            name: name.to_string(),
            known: list.iter().map(|t| t.name().to_string()).collect(),
        })
}
