//! Components: the [`Component`] hooks, the [`TaskContext`] that runs them through the RTT
//! 2.x lifecycle, and the interface (ports, operations, properties, attributes) it exposes
//! by name.
//!
//! ```text
//!            configure            start
//! PreOperational ──► Stopped ───────────► Running ◄──┐ recover
//!        ▲  cleanup    ▲  ◄─────────────   │  error  │
//!        └─────────────┘      stop         ▼         │
//!                      ▲              RunTimeError ──┘
//!            recover   │
//!                  Exception ◄── a hook failed or panicked ──► FatalError (the exception
//!                                                             handling itself panicked)
//! ```
//!
//! `configure` and `start` hooks that return an error refuse the transition (the state
//! stays); an `update` hook that returns an error, and any hook that panics, put the
//! component in Exception (its stop hook runs if it was running). The panic is caught and
//! reported; the process and the other components keep running.

use crate::activity::StepTiming;
use crate::activity::{
    Activity, ActivityError, ActivitySpec, ActivityStats, FdEvents, Runner, Waker,
};
use crate::operation::{
    ArgInfo, Args, CallError, ClientOp, DynOperation, Engine, ExecutionThread, Message,
    OperationCaller, OperationEntry, OperationInfo, OwnOp,
};
use crate::port::{
    ConnPolicy, ConnectError, ConnectionInfo, FlowStatus, InputPort, InputShared, OutputPort,
    OutputShared, connect_shared, lock,
};
use crate::property::PropertyBag;
use crate::scope::ThreadScope;
use crossbeam_queue::SegQueue;
use device_interface::Registry;
use device_interface::time::{Clock, Timestamp};
use serde::Serialize;
use serde::de::DeserializeOwned;
use serde_json::Value;
use std::any::Any;
use std::fmt;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};

/// The lifecycle states of RTT 2.x.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TaskState {
    /// Being built.
    Init,
    /// Built; needs `configure`.
    PreOperational,
    /// Configured; not stepping.
    Stopped,
    /// Stepping: `update` runs at each step.
    Running,
    /// Stepping, but `error` runs instead of `update` until `recover`.
    RunTimeError,
    /// A hook failed or panicked; the component stopped. `recover` brings it to Stopped.
    Exception,
    /// Handling an exception failed too; nothing more will run.
    FatalError,
}

impl TaskState {
    const ALL: [TaskState; 7] = [
        TaskState::Init,
        TaskState::PreOperational,
        TaskState::Stopped,
        TaskState::Running,
        TaskState::RunTimeError,
        TaskState::Exception,
        TaskState::FatalError,
    ];

    fn from_u8(v: u8) -> TaskState {
        Self::ALL
            .get(usize::from(v))
            .copied()
            .unwrap_or(TaskState::FatalError)
    }

    fn as_u8(self) -> u8 {
        Self::ALL.iter().position(|s| *s == self).unwrap_or(6) as u8
    }
}

impl fmt::Display for TaskState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self, f)
    }
}

/// Why a hook failed: a message (any error converts into one).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HookError(pub String);

impl fmt::Display for HookError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl<E: std::error::Error> From<E> for HookError {
    fn from(e: E) -> Self {
        HookError(e.to_string())
    }
}

impl HookError {
    /// A hook error with `message`.
    pub fn new(message: impl Into<String>) -> Self {
        HookError(message.into())
    }
}

/// What a hook returns.
pub type HookResult = Result<(), HookError>;

/// The hooks a component implements; every one has a default that does nothing.
///
/// `update_hook` runs on the component's activity thread and must keep the real-time
/// contract: no blocking, no allocation.
pub trait Component: Send + 'static {
    /// PreOperational/Stopped → Stopped. An error keeps the state.
    fn configure_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let _ = ctx;
        Ok(())
    }
    /// Stopped → Running. An error keeps the state.
    fn start_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let _ = ctx;
        Ok(())
    }
    /// One step while Running. An error puts the component in Exception; call
    /// [`Context::error`] instead to go to RunTimeError and keep stepping.
    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let _ = ctx;
        Ok(())
    }
    /// One step while in RunTimeError (instead of `update_hook`); call
    /// [`Context::recover`] when the condition is gone.
    fn error_hook(&mut self, ctx: &mut Context<'_>) {
        let _ = ctx;
    }
    /// Running/RunTimeError → Stopped, and on the way into Exception.
    fn stop_hook(&mut self, ctx: &mut Context<'_>) {
        let _ = ctx;
    }
    /// Stopped → PreOperational.
    fn cleanup_hook(&mut self, ctx: &mut Context<'_>) {
        let _ = ctx;
    }
    /// On entering Exception.
    fn exception_hook(&mut self, ctx: &mut Context<'_>) {
        let _ = ctx;
    }
}

trait ErasedComponent: Component {
    fn as_any_mut(&mut self) -> &mut dyn Any;
}

impl<C: Component> ErasedComponent for C {
    fn as_any_mut(&mut self) -> &mut dyn Any {
        self
    }
}

/// What a hook can see and ask for.
pub struct Context<'a> {
    core: &'a TaskCore,
    events: &'a FdEvents,
    timing: StepTiming,
    error_requested: bool,
    recover_requested: bool,
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
        self.error_requested = true;
    }

    /// From `error_hook`: return to Running after this step.
    pub fn recover(&mut self) {
        self.recover_requested = true;
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

    /// Another component of the same runtime, by name (for configure-time wiring, as RTT
    /// peers: a reporter connecting to the ports it records). Not for real-time paths.
    pub fn peer(&self, name: &str) -> Result<TaskContext, IntrospectError> {
        let peers = self.core.peers.upgrade();
        let list = peers.as_ref().map(|p| lock(p).clone()).unwrap_or_default();
        list.iter()
            .find(|t| t.name() == name)
            .cloned()
            .ok_or_else(|| IntrospectError::NotFound {
                component: self.core.name.clone(),
                kind: "peer",
                name: name.to_string(),
                known: list.iter().map(|t| t.name().to_string()).collect(),
            })
    }
}

/// Why a lifecycle command was refused.
#[derive(Debug, Clone, thiserror::Error)]
#[non_exhaustive]
pub enum LifecycleError {
    /// The command is not allowed in the current state.
    #[error("component {component:?}: cannot {command} in state {state}")]
    Illegal {
        /// The component.
        component: String,
        /// The command.
        command: &'static str,
        /// The state it is in.
        state: TaskState,
    },
    /// The hook returned an error; the state did not change.
    #[error("component {component:?}: {hook} failed: {message}")]
    HookFailed {
        /// The component.
        component: String,
        /// The hook.
        hook: &'static str,
        /// Its error.
        message: String,
    },
    /// The hook panicked; the component went to Exception (or FatalError).
    #[error("component {component:?}: {hook} panicked: {message}; now in {state}")]
    HookPanicked {
        /// The component.
        component: String,
        /// The hook.
        hook: &'static str,
        /// The panic message.
        message: String,
        /// The state it ended in.
        state: TaskState,
    },
    /// The activity could not start.
    #[error("component {component:?}: {source}")]
    Activity {
        /// The component.
        component: String,
        /// The activity error.
        #[source]
        source: Arc<ActivityError>,
    },
}

/// Why something was not found or did not fit in a component's interface.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum IntrospectError {
    /// No such port, operation or component.
    #[error("{component:?} has no {kind} {name:?}; it has: {}", if .known.is_empty() { "none".to_string() } else { .known.join(", ") })]
    NotFound {
        /// The component (or "runtime").
        component: String,
        /// "port", "operation", "component".
        kind: &'static str,
        /// The name asked for.
        name: String,
        /// The names that exist.
        known: Vec<String>,
    },
    /// A name used twice in one interface.
    #[error("{component:?} already has a {kind} named {name:?}")]
    Duplicate {
        /// The component.
        component: String,
        /// "port", "operation".
        kind: &'static str,
        /// The name.
        name: String,
    },
    /// A typed lookup with the wrong types.
    #[error("{what} is {actual}, not {asked}")]
    WrongType {
        /// What was looked up.
        what: String,
        /// Its actual type.
        actual: String,
        /// The type asked for.
        asked: String,
    },
    /// A dynamically typed value that does not fit.
    #[error("{what}: expected {expected}: {detail}")]
    BadValue {
        /// What was written.
        what: String,
        /// The expected type.
        expected: String,
        /// What was wrong.
        detail: String,
    },
    /// An operation on a port of the wrong direction.
    #[error("port {port:?} is an {actual} port; {what} needs an {needed} port")]
    Direction {
        /// The port.
        port: String,
        /// Its direction.
        actual: Direction,
        /// The direction needed.
        needed: Direction,
        /// What was attempted.
        what: &'static str,
    },
    /// Connecting failed.
    #[error(transparent)]
    Connect(#[from] ConnectError),
    /// A property could not be added, found or set.
    #[error(transparent)]
    Property(#[from] crate::property::PropertyError),
}

/// Data direction of a port.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Direction {
    /// An input port.
    Input,
    /// An output port.
    Output,
}

impl fmt::Display for Direction {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Direction::Input => "input",
            Direction::Output => "output",
        })
    }
}

/// What a port can carry: clonable, sendable, serde (for the dynamic interface).
pub trait PortData: Clone + Send + Sync + Serialize + DeserializeOwned + 'static {}
impl<T: Clone + Send + Sync + Serialize + DeserializeOwned + 'static> PortData for T {}

/// A port, as listed.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct PortInfo {
    /// Name.
    pub name: String,
    /// What it carries.
    pub doc: String,
    /// Direction.
    pub direction: Direction,
    /// Rust type of the data.
    pub type_name: String,
    /// True for an input port that wakes its component.
    pub event: bool,
}

/// Reads a port's data as dynamically typed values (made by [`DynPort::reader`]).
pub trait DynReader: Send {
    /// The next sample, as [`InputPort::read`] gives it, serialised.
    fn read(&mut self) -> (FlowStatus, Option<Value>);
}

/// Writes dynamically typed values into an input port (made by [`DynPort::writer`]).
pub trait DynWriter: Send {
    /// Converts `value` to the port's type and writes it.
    fn write(&mut self, value: Value) -> Result<(), IntrospectError>;
}

/// A port of any type and direction, reachable by name.
pub trait DynPort: Send + Sync {
    /// Name, doc, direction, type.
    fn info(&self) -> PortInfo;
    /// Live connections and their counters.
    fn connections(&self) -> Vec<ConnectionInfo>;
    /// An output port's last written value (`None` before the first write).
    fn last_value(&self) -> Result<Option<Value>, IntrospectError>;
    /// A new connection from this output port to a reader of serialised values.
    fn reader(&self, policy: ConnPolicy) -> Result<Box<dyn DynReader>, IntrospectError>;
    /// A new connection from a writer of serialised values to this input port.
    fn writer(&self, policy: ConnPolicy) -> Result<Box<dyn DynWriter>, IntrospectError>;
    /// Connects this output port to `input`.
    fn connect_to(
        &self,
        input: &dyn DynPort,
        policy: ConnPolicy,
    ) -> Result<ConnectionInfo, IntrospectError>;
    /// Closes connection `id`, or all with `None`; returns how many.
    fn disconnect(&self, id: Option<u64>) -> usize;
    /// For typed downcasts.
    fn as_any(&self) -> &dyn Any;
}

struct OutEntry<T: Send> {
    shared: Arc<OutputShared<T>>,
    doc: String,
}

struct InEntry<T: Send> {
    shared: Arc<InputShared<T>>,
    doc: String,
    sample: T,
    event: bool,
}

fn direction_error(port: &str, actual: Direction, what: &'static str) -> IntrospectError {
    let needed = match actual {
        Direction::Input => Direction::Output,
        Direction::Output => Direction::Input,
    };
    IntrospectError::Direction {
        port: port.to_string(),
        actual,
        needed,
        what,
    }
}

struct ValueReader<T: Send> {
    port: InputPort<T>,
    sample: T,
}

impl<T: PortData> DynReader for ValueReader<T> {
    fn read(&mut self) -> (FlowStatus, Option<Value>) {
        match self.port.read(&mut self.sample) {
            FlowStatus::NoData => (FlowStatus::NoData, None),
            s => (s, serde_json::to_value(&self.sample).ok()),
        }
    }
}

struct ValueWriter<T: Send> {
    port: OutputPort<T>,
    what: String,
}

impl<T: PortData> DynWriter for ValueWriter<T> {
    fn write(&mut self, value: Value) -> Result<(), IntrospectError> {
        let v: T = serde_json::from_value(value).map_err(|e| IntrospectError::BadValue {
            what: self.what.clone(),
            expected: std::any::type_name::<T>().to_string(),
            detail: e.to_string(),
        })?;
        self.port.write(&v);
        Ok(())
    }
}

impl<T: PortData> DynPort for OutEntry<T> {
    fn info(&self) -> PortInfo {
        PortInfo {
            name: self.shared.name.to_string(),
            doc: self.doc.clone(),
            direction: Direction::Output,
            type_name: std::any::type_name::<T>().to_string(),
            event: false,
        }
    }

    fn connections(&self) -> Vec<ConnectionInfo> {
        self.shared.connections()
    }

    fn last_value(&self) -> Result<Option<Value>, IntrospectError> {
        Ok(self
            .shared
            .last_written()
            .and_then(|v| serde_json::to_value(&v).ok()))
    }

    fn reader(&self, policy: ConnPolicy) -> Result<Box<dyn DynReader>, IntrospectError> {
        let sample = match self.shared.last_written() {
            Some(v) => v,
            None => self.shared.sample_clone(),
        };
        let port = InputPort::with_sample(&format!("{}.reader", self.shared.name), sample.clone());
        connect_shared(&self.shared, port.shared(), policy)?;
        Ok(Box::new(ValueReader { port, sample }))
    }

    fn writer(&self, _policy: ConnPolicy) -> Result<Box<dyn DynWriter>, IntrospectError> {
        Err(direction_error(
            &self.shared.name,
            Direction::Output,
            "writing",
        ))
    }

    fn connect_to(
        &self,
        input: &dyn DynPort,
        policy: ConnPolicy,
    ) -> Result<ConnectionInfo, IntrospectError> {
        match input.as_any().downcast_ref::<InEntry<T>>() {
            Some(inp) => Ok(connect_shared(&self.shared, &inp.shared, policy)?),
            None => {
                let info = input.info();
                if info.direction == Direction::Output {
                    return Err(ConnectError::Direction {
                        from: self.shared.name.to_string(),
                        to: info.name,
                    }
                    .into());
                }
                Err(ConnectError::TypeMismatch {
                    output: self.shared.name.to_string(),
                    output_type: std::any::type_name::<T>().to_string(),
                    input: info.name,
                    input_type: info.type_name,
                }
                .into())
            }
        }
    }

    fn disconnect(&self, id: Option<u64>) -> usize {
        self.shared.disconnect(id)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

impl<T: PortData> DynPort for InEntry<T> {
    fn info(&self) -> PortInfo {
        PortInfo {
            name: self.shared.name.to_string(),
            doc: self.doc.clone(),
            direction: Direction::Input,
            type_name: std::any::type_name::<T>().to_string(),
            event: self.event,
        }
    }

    fn connections(&self) -> Vec<ConnectionInfo> {
        self.shared.connections()
    }

    fn last_value(&self) -> Result<Option<Value>, IntrospectError> {
        Err(direction_error(
            &self.shared.name,
            Direction::Input,
            "reading a last value",
        ))
    }

    fn reader(&self, _policy: ConnPolicy) -> Result<Box<dyn DynReader>, IntrospectError> {
        Err(direction_error(
            &self.shared.name,
            Direction::Input,
            "watching",
        ))
    }

    fn writer(&self, policy: ConnPolicy) -> Result<Box<dyn DynWriter>, IntrospectError> {
        let port =
            OutputPort::with_sample(&format!("{}.writer", self.shared.name), self.sample.clone());
        connect_shared(port.shared(), &self.shared, policy)?;
        Ok(Box::new(ValueWriter {
            port,
            what: format!("port {:?}", self.shared.name),
        }))
    }

    fn connect_to(
        &self,
        input: &dyn DynPort,
        _policy: ConnPolicy,
    ) -> Result<ConnectionInfo, IntrospectError> {
        Err(ConnectError::Direction {
            from: self.shared.name.to_string(),
            to: input.info().name,
        }
        .into())
    }

    fn disconnect(&self, id: Option<u64>) -> usize {
        self.shared.disconnect(id)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// Builds a component's interface: handed to the component's constructor.
pub struct Interface<C> {
    name: String,
    engine: Weak<dyn Engine>,
    waker: Arc<dyn Waker>,
    ports: Vec<Arc<dyn DynPort>>,
    operations: Vec<Arc<dyn DynOperation>>,
    properties: PropertyBag,
    attributes: PropertyBag,
    registry: Arc<Registry>,
    _component: std::marker::PhantomData<fn(&mut C)>,
}

impl<C: Component> Interface<C> {
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
        let port = OutputPort::with_sample(name, sample);
        self.ports.push(Arc::new(OutEntry {
            shared: port.shared().clone(),
            doc: doc.to_string(),
        }));
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

    /// Adds an input port keeping its sample in a copy of `sample`.
    pub fn input_with_sample<T: PortData>(
        &mut self,
        name: &str,
        doc: &str,
        sample: T,
        event: bool,
    ) -> Result<InputPort<T>, IntrospectError> {
        self.check_port_name(name)?;
        let port = InputPort::with_sample(name, sample.clone());
        if event {
            let _ = port.shared().waker.set(self.waker.clone());
        }
        self.ports.push(Arc::new(InEntry {
            shared: port.shared().clone(),
            doc: doc.to_string(),
            sample,
            event,
        }));
        Ok(port)
    }

    fn add_operation<A: Args, R: Serialize + 'static>(
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
                        type_name: t.to_string(),
                    }
                })
                .collect(),
            result: std::any::type_name::<R>().to_string(),
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
    pub fn client_operation<A: Args, R: Serialize + 'static>(
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
        let inner: Arc<dyn crate::operation::Invoke<A, R>> = Arc::new(OwnOp {
            name: Arc::from(name),
            f: Arc::new(f),
            engine: self.engine.clone(),
            _component: std::marker::PhantomData,
        });
        self.add_operation(name, doc, args, ExecutionThread::OwnThread, inner)
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

/// Error and step counters of a component.
#[derive(Debug, Clone, Default, Serialize)]
pub struct TaskCounters {
    /// Times it went to RunTimeError.
    pub runtime_errors: u64,
    /// Times it went to Exception.
    pub exceptions: u64,
    /// Hooks that returned an error or panicked.
    pub failed_hooks: u64,
    /// The last failure message.
    pub last_error: Option<String>,
}

pub(crate) struct TaskCore {
    name: String,
    state: AtomicU8,
    component: Mutex<Box<dyn ErasedComponent>>,
    queue: SegQueue<Message>,
    activity: Activity,
    ports: Vec<Arc<dyn DynPort>>,
    operations: Vec<Arc<dyn DynOperation>>,
    properties: PropertyBag,
    attributes: PropertyBag,
    registry: Arc<Registry>,
    clock: Arc<dyn Clock>,
    runtime_errors: AtomicU64,
    exceptions: AtomicU64,
    failed_hooks: AtomicU64,
    last_error: Mutex<Option<String>>,
    engine_thread: Mutex<Option<std::thread::ThreadId>>,
    peers: Weak<Mutex<Vec<TaskContext>>>,
}

impl TaskCore {
    fn state(&self) -> TaskState {
        TaskState::from_u8(self.state.load(Ordering::Acquire))
    }

    fn set_state(&self, s: TaskState) {
        self.state.store(s.as_u8(), Ordering::Release);
    }

    fn record_failure(&self, message: String) {
        self.failed_hooks.fetch_add(1, Ordering::Relaxed);
        *lock(&self.last_error) = Some(message);
    }

    /// Runs a hook with panics caught. `Ok(r)` or the panic message.
    fn run_hook<R>(
        &self,
        comp: &mut dyn ErasedComponent,
        events: &FdEvents,
        timing: StepTiming,
        f: impl FnOnce(&mut dyn ErasedComponent, &mut Context<'_>) -> R,
    ) -> (Result<R, String>, bool, bool) {
        let mut ctx = Context {
            core: self,
            events,
            timing,
            error_requested: false,
            recover_requested: false,
        };
        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| f(comp, &mut ctx)))
            .map_err(|p| {
                p.downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| p.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "(no message)".into())
            });
        (r, ctx.error_requested, ctx.recover_requested)
    }

    /// Enters Exception from any state: exception hook, then the stop hook if it was
    /// running. A panic in either goes to FatalError.
    fn enter_exception(&self, comp: &mut dyn ErasedComponent, reason: String) -> TaskState {
        let was_running = matches!(self.state(), TaskState::Running | TaskState::RunTimeError);
        tracing::error!(component = %self.name, "entering Exception: {reason}");
        self.record_failure(reason);
        self.exceptions.fetch_add(1, Ordering::Relaxed);
        self.set_state(TaskState::Exception);
        self.activity.stop();
        let events = FdEvents::default();
        let timing = StepTiming::default();
        let (r, _, _) = self.run_hook(comp, &events, timing, |c, ctx| c.exception_hook(ctx));
        let r = r.and_then(|()| {
            if was_running {
                self.run_hook(comp, &events, timing, |c, ctx| c.stop_hook(ctx))
                    .0
            } else {
                Ok(())
            }
        });
        if let Err(msg) = r {
            tracing::error!(component = %self.name, "handling the exception panicked: {msg}; FatalError");
            self.record_failure(msg);
            self.set_state(TaskState::FatalError);
        }
        self.drain_queue();
        self.state()
    }

    /// Drops queued OwnThread calls: their callers get `Cancelled`.
    fn drain_queue(&self) {
        while self.queue.pop().is_some() {}
    }

    fn step(&self, events: &FdEvents, timing: StepTiming) {
        let mut guard = lock(&self.component);
        let comp: &mut dyn ErasedComponent = &mut **guard;
        while let Some(msg) = self.queue.pop() {
            msg(comp.as_any_mut());
        }
        match self.state() {
            TaskState::Running => {
                let (r, error, _) =
                    self.run_hook(comp, events, timing, |c, ctx| c.update_hook(ctx));
                match r {
                    Ok(Ok(())) if error => {
                        self.runtime_errors.fetch_add(1, Ordering::Relaxed);
                        self.set_state(TaskState::RunTimeError);
                    }
                    Ok(Ok(())) => {}
                    Ok(Err(e)) => {
                        self.enter_exception(comp, format!("update failed: {e}"));
                    }
                    Err(panic) => {
                        self.enter_exception(comp, format!("update panicked: {panic}"));
                    }
                }
            }
            TaskState::RunTimeError => {
                let (r, _, recover) =
                    self.run_hook(comp, events, timing, |c, ctx| c.error_hook(ctx));
                match r {
                    Ok(()) if recover => self.set_state(TaskState::Running),
                    Ok(()) => {}
                    Err(panic) => {
                        self.enter_exception(comp, format!("error hook panicked: {panic}"));
                    }
                }
            }
            _ => {}
        }
    }
}

impl Engine for TaskCore {
    fn submit(&self, operation: &str, msg: Message) -> Result<(), CallError> {
        let state = self.state();
        if !self.activity.is_running()
            || !matches!(state, TaskState::Running | TaskState::RunTimeError)
        {
            return Err(CallError::NotRunning {
                operation: operation.to_string(),
                component: self.name.clone(),
                state: state.to_string(),
            });
        }
        if *lock(&self.engine_thread) == Some(std::thread::current().id()) {
            return Err(CallError::Reentrant {
                operation: operation.to_string(),
            });
        }
        self.queue.push(msg);
        self.activity.trigger();
        Ok(())
    }
}

/// Steps a component's engine. An activity's runner notes its thread at the first step,
/// so an OwnThread call from that thread is refused, not dead-locked; a slave's runner
/// (stepped from whatever thread calls `step`) notes nothing.
struct EngineRunner {
    core: Weak<TaskCore>,
    /// True until the engine thread is noted (activity runners only).
    note_thread: AtomicBool,
}

impl EngineRunner {
    fn new(core: &Arc<TaskCore>, note_thread: bool) -> Self {
        EngineRunner {
            core: Arc::downgrade(core),
            note_thread: AtomicBool::new(note_thread),
        }
    }
}

impl Runner for EngineRunner {
    fn step(&self, events: &FdEvents, timing: StepTiming) {
        let Some(core) = self.core.upgrade() else {
            return;
        };
        if self.note_thread.swap(false, Ordering::Relaxed) {
            *lock(&core.engine_thread) = Some(std::thread::current().id());
        }
        core.step(events, timing);
    }
}

/// A component in the runtime: its lifecycle, activity and interface. Cheap to clone;
/// every clone is the same component.
#[derive(Clone)]
pub struct TaskContext {
    core: Arc<TaskCore>,
}

impl fmt::Debug for TaskContext {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "TaskContext({:?}, {})",
            self.core.name,
            self.core.state()
        )
    }
}

/// Everything needed to build a [`TaskContext`] besides the component.
pub(crate) struct TaskSetup {
    pub(crate) registry: Arc<Registry>,
    pub(crate) clock: Arc<dyn Clock>,
    pub(crate) scope: Arc<ThreadScope>,
    pub(crate) thread_number: Box<dyn FnOnce() -> u32>,
    /// The runtime's components, weakly: a component must not keep its runtime alive.
    pub(crate) peers: Weak<Mutex<Vec<TaskContext>>>,
}

impl TaskContext {
    pub(crate) fn build<C: Component>(
        name: &str,
        spec: ActivitySpec,
        needs_configure: bool,
        setup: TaskSetup,
        build: impl FnOnce(&mut Interface<C>) -> Result<C, IntrospectError>,
    ) -> Result<TaskContext, crate::RuntimeError> {
        let activity =
            Activity::new(spec, name, setup.scope, setup.thread_number).map_err(|e| {
                crate::RuntimeError::Activity {
                    component: name.to_string(),
                    source: Arc::new(e),
                }
            })?;
        let waker = activity.waker();
        let mut build_result = None;
        let core = Arc::new_cyclic(|weak: &Weak<TaskCore>| {
            let engine: Weak<dyn Engine> = weak.clone();
            let mut iface = Interface {
                name: name.to_string(),
                engine,
                waker,
                ports: Vec::new(),
                operations: Vec::new(),
                properties: PropertyBag::new("properties"),
                attributes: PropertyBag::new("attributes"),
                registry: setup.registry.clone(),
                _component: std::marker::PhantomData,
            };
            let component: Box<dyn ErasedComponent> = match build(&mut iface) {
                Ok(c) => Box::new(c),
                Err(e) => {
                    build_result = Some(e);
                    Box::new(Placeholder)
                }
            };
            TaskCore {
                name: name.to_string(),
                state: AtomicU8::new(TaskState::Init.as_u8()),
                component: Mutex::new(component),
                queue: SegQueue::new(),
                activity,
                ports: iface.ports,
                operations: iface.operations,
                properties: iface.properties,
                attributes: iface.attributes,
                registry: setup.registry,
                clock: setup.clock,
                runtime_errors: AtomicU64::new(0),
                exceptions: AtomicU64::new(0),
                failed_hooks: AtomicU64::new(0),
                last_error: Mutex::new(None),
                engine_thread: Mutex::new(None),
                peers: setup.peers,
            }
        });
        if let Some(e) = build_result {
            return Err(crate::RuntimeError::Build {
                component: name.to_string(),
                source: e,
            });
        }
        core.set_state(if needs_configure {
            TaskState::PreOperational
        } else {
            TaskState::Stopped
        });
        Ok(TaskContext { core })
    }

    /// The component's name.
    pub fn name(&self) -> &str {
        &self.core.name
    }

    /// The lifecycle state.
    pub fn state(&self) -> TaskState {
        self.core.state()
    }

    fn illegal(&self, command: &'static str) -> LifecycleError {
        LifecycleError::Illegal {
            component: self.core.name.clone(),
            command,
            state: self.state(),
        }
    }

    /// Runs a transition hook under the component lock; a panic enters Exception.
    fn hook(
        &self,
        command: &'static str,
        allowed: &[TaskState],
        hook: &'static str,
        f: impl FnOnce(&mut dyn ErasedComponent, &mut Context<'_>) -> HookResult,
        success: TaskState,
    ) -> Result<(), LifecycleError> {
        let mut guard = lock(&self.core.component);
        if !allowed.contains(&self.state()) {
            return Err(self.illegal(command));
        }
        let comp: &mut dyn ErasedComponent = &mut **guard;
        match self
            .core
            .run_hook(comp, &FdEvents::default(), StepTiming::default(), f)
            .0
        {
            Ok(Ok(())) => {
                self.core.set_state(success);
                Ok(())
            }
            Ok(Err(e)) => {
                self.core.record_failure(format!("{hook} failed: {e}"));
                Err(LifecycleError::HookFailed {
                    component: self.core.name.clone(),
                    hook,
                    message: e.0,
                })
            }
            Err(panic) => {
                let state = self
                    .core
                    .enter_exception(comp, format!("{hook} panicked: {panic}"));
                Err(LifecycleError::HookPanicked {
                    component: self.core.name.clone(),
                    hook,
                    message: panic,
                    state,
                })
            }
        }
    }

    /// PreOperational or Stopped → Stopped, via the configure hook.
    pub fn configure(&self) -> Result<(), LifecycleError> {
        self.hook(
            "configure",
            &[TaskState::PreOperational, TaskState::Stopped],
            "configure_hook",
            |c, ctx| c.configure_hook(ctx),
            TaskState::Stopped,
        )
    }

    /// Stopped → Running: the start hook, then the activity starts.
    pub fn start(&self) -> Result<(), LifecycleError> {
        self.hook(
            "start",
            &[TaskState::Stopped],
            "start_hook",
            |c, ctx| c.start_hook(ctx),
            TaskState::Running,
        )?;
        let runner: Arc<dyn Runner> = Arc::new(EngineRunner::new(&self.core, true));
        if let Err(e) = self.core.activity.start(runner) {
            self.core.set_state(TaskState::Stopped);
            return Err(LifecycleError::Activity {
                component: self.core.name.clone(),
                source: Arc::new(e),
            });
        }
        Ok(())
    }

    /// Running or RunTimeError → Stopped: the activity stops (pending OwnThread calls are
    /// cancelled), then the stop hook runs.
    pub fn stop(&self) -> Result<(), LifecycleError> {
        if !matches!(self.state(), TaskState::Running | TaskState::RunTimeError) {
            return Err(self.illegal("stop"));
        }
        // Stop the thread first, without holding the component: its step needs it.
        self.core.activity.stop();
        *lock(&self.core.engine_thread) = None;
        self.core.drain_queue();
        self.hook(
            "stop",
            &[TaskState::Running, TaskState::RunTimeError],
            "stop_hook",
            |c, ctx| {
                c.stop_hook(ctx);
                Ok(())
            },
            TaskState::Stopped,
        )
    }

    /// Stopped → PreOperational, via the cleanup hook.
    pub fn cleanup(&self) -> Result<(), LifecycleError> {
        self.hook(
            "cleanup",
            &[TaskState::Stopped],
            "cleanup_hook",
            |c, ctx| {
                c.cleanup_hook(ctx);
                Ok(())
            },
            TaskState::PreOperational,
        )
    }

    /// RunTimeError → Running; Exception → Stopped.
    pub fn recover(&self) -> Result<(), LifecycleError> {
        let _guard = lock(&self.core.component);
        match self.state() {
            TaskState::RunTimeError => self.core.set_state(TaskState::Running),
            TaskState::Exception => self.core.set_state(TaskState::Stopped),
            _ => return Err(self.illegal("recover")),
        }
        Ok(())
    }

    /// Running → RunTimeError, from outside the component.
    pub fn error(&self) -> Result<(), LifecycleError> {
        let _guard = lock(&self.core.component);
        if self.state() != TaskState::Running {
            return Err(self.illegal("error"));
        }
        self.core.runtime_errors.fetch_add(1, Ordering::Relaxed);
        self.core.set_state(TaskState::RunTimeError);
        Ok(())
    }

    /// Asks a non-periodic or file-descriptor activity for a step.
    pub fn trigger(&self) {
        self.core.activity.trigger();
    }

    /// One step on the calling thread: queued OwnThread calls, then update (or error).
    /// Slave activities only; stepping a stopped component runs only the queue.
    pub fn step(&self) -> Result<(), ActivityError> {
        let runner = EngineRunner::new(&self.core, false);
        self.core.activity.step_slave(&runner)
    }

    /// The activity.
    pub fn activity(&self) -> &Activity {
        &self.core.activity
    }

    /// The activity's statistics.
    pub fn stats(&self) -> ActivityStats {
        self.core.activity.stats()
    }

    /// Error counters and the last error.
    pub fn counters(&self) -> TaskCounters {
        TaskCounters {
            runtime_errors: self.core.runtime_errors.load(Ordering::Relaxed),
            exceptions: self.core.exceptions.load(Ordering::Relaxed),
            failed_hooks: self.core.failed_hooks.load(Ordering::Relaxed),
            last_error: lock(&self.core.last_error).clone(),
        }
    }

    /// Every port.
    pub fn ports(&self) -> Vec<PortInfo> {
        self.core.ports.iter().map(|p| p.info()).collect()
    }

    /// The port `name`, or an error listing the ports.
    pub fn port(&self, name: &str) -> Result<Arc<dyn DynPort>, IntrospectError> {
        self.core
            .ports
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
            None => {
                let info = op.info();
                let arg_types: Vec<&str> = info.args.iter().map(|a| a.type_name.as_str()).collect();
                Err(IntrospectError::WrongType {
                    what: format!("operation {name:?}"),
                    actual: format!("fn({}) -> {}", arg_types.join(", "), info.result),
                    asked: format!(
                        "fn({}) -> {}",
                        A::type_names().join(", "),
                        std::any::type_name::<R>()
                    ),
                })
            }
        }
    }

    /// Calls operation `name` with dynamically typed arguments.
    pub fn call_value(&self, name: &str, args: Vec<Value>) -> Result<Value, CallOrIntrospect> {
        let op = self.find_operation(name)?;
        Ok(op.call_value(args)?)
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

/// Either a lookup or a call failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CallOrIntrospect {
    /// The lookup failed.
    #[error(transparent)]
    Introspect(#[from] IntrospectError),
    /// The call failed.
    #[error(transparent)]
    Call(#[from] CallError),
}

/// Stands in for a component whose constructor failed (never runs).
struct Placeholder;
impl Component for Placeholder {}
