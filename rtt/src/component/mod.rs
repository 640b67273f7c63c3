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

mod builder;
mod context;
mod dynport;
mod hook_error;
mod lookup;
mod services;
mod settings;

pub use crate::error::{CallOrIntrospect, IntrospectError, LifecycleError, RuntimeError};
pub use crate::info::{Direction, NamedValue, PortData, PortInfo};
pub use crate::state::{InitialState, TaskState};
pub use builder::InterfaceBuilder;
use context::Asked;
pub use context::{Context, SelfRef};
pub use dynport::{DynPort, DynReader, DynWriter, WordValue};
pub use hook_error::{HookError, HookResult};
pub use services::{Provides, Requires};

use crate::activity::{
    Activity, ActivityError, ActivitySpec, ActivityStats, FdEvents, Runner, StepTiming,
};
use crate::bounded::Bounded;
use crate::lock::lock;
use crate::log::Arg;
use crate::operation::{CallError, DynOperation, Engine, QUEUE_CAPACITY, Queued};
use crate::property::PropertyBag;
use crate::scope::ThreadScope;
use crate::state::StateCell;
use device_interface::Registry;
use device_interface::time::Clock;
use serde::Serialize;
use std::any::Any;
use std::fmt;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;

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
    /// `recover` from Exception: put things right. Ok → Stopped (start again); an error →
    /// PreOperational (configure again).
    fn reset_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let _ = ctx;
        Ok(())
    }
    /// Before a step: required `service` (a service or devices, by the name it was
    /// required under) stopped being ready — its provider left Running, a device went
    /// offline. Its operations refuse calls until [`service_back`](Self::service_back).
    fn service_lost(&mut self, ctx: &mut Context<'_>, service: &str) {
        let _ = (ctx, service);
    }
    /// Before a step: required `service` is ready again.
    fn service_back(&mut self, ctx: &mut Context<'_>, service: &str) {
        let _ = (ctx, service);
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

/// Error and step counters of a component.
#[derive(Debug, Clone, Default, Serialize, serde::Deserialize)]
pub struct TaskCounters {
    /// Times it went to RunTimeError.
    pub runtime_errors: u64,
    /// Times it went to Exception.
    pub exceptions: u64,
    /// Hooks that returned an error or panicked.
    pub failed_hooks: u64,
    /// The last failure message.
    pub last_error: Option<String>,
    /// The warning flag is up ([`Context::warning`]); the component still runs.
    #[serde(default)]
    pub warning: bool,
    /// Times the warning flag was raised.
    #[serde(default)]
    pub warnings: u64,
    /// Times a required service or device stopped being ready while it ran.
    #[serde(default)]
    pub services_lost: u64,
    /// Times one was ready again.
    #[serde(default)]
    pub services_back: u64,
    /// OwnThread calls refused because its queue was full ([`QUEUE_CAPACITY`]).
    #[serde(default)]
    pub calls_refused: u64,
    /// OwnThread calls that needed a call slot made on the heap: more calls to one
    /// operation were outstanding at once than its pool holds (4).
    #[serde(default)]
    pub call_slots_allocated: u64,
}

pub(crate) struct TaskCore {
    name: String,
    /// Where its engine logs.
    log: crate::log::Area,
    /// Itself, for what a component keeps of itself ([`SelfRef`]).
    me: Weak<TaskCore>,
    state: Arc<StateCell>,
    component: Mutex<Box<dyn ErasedComponent>>,
    /// OwnThread calls to run before the next step: bounded, never waiting for another
    /// thread ([`crate::bounded`]).
    queue: Bounded<Queued>,
    /// Calls refused because the queue was full.
    calls_refused: AtomicU64,
    /// Call slots made on the heap because an operation's pool was in use.
    call_slots_allocated: AtomicU64,
    activity: Activity,
    /// Swapped whole when a component adds a port while it configures.
    ports: arc_swap::ArcSwap<Vec<Arc<dyn DynPort>>>,
    operations: Vec<Arc<dyn DynOperation>>,
    properties: PropertyBag,
    attributes: PropertyBag,
    provided: Vec<crate::service::ProvidedInfo>,
    required: Vec<Arc<crate::service::Requirement>>,
    registry: Arc<Registry>,
    clock: Arc<dyn Clock>,
    runtime_errors: AtomicU64,
    exceptions: AtomicU64,
    failed_hooks: AtomicU64,
    warning: AtomicBool,
    warnings: AtomicU64,
    last_error: Mutex<Option<String>>,
    /// The engine's thread ([`this_thread`]) once it has stepped, 0 before and after: an
    /// own-thread call from it is refused rather than queued behind itself. An atomic, so
    /// that a caller never takes a lock the engine thread could need.
    engine_thread: AtomicU64,
    /// The thread holding `component` ([`this_thread`]), 0 when none: a lifecycle command
    /// or own-thread call from it is refused rather than dead-locked.
    holder: AtomicU64,
    /// Threads outside the component waiting to take it between steps (`error`,
    /// `recover`): while any waits, its activity's steps are skipped, so a step that waits
    /// in the component's own code cannot take it back before them.
    outside: AtomicU32,
    peers: Weak<Mutex<Vec<TaskContext>>>,
    /// Slave components stepped after each of this one's steps, in order.
    slaves: arc_swap::ArcSwap<Vec<TaskContext>>,
    /// Names this component knows its peers by (`device` → `press_io`).
    peer_aliases: Mutex<Vec<(String, String)>>,
    /// Interrupts the component's own blocking code at a stop (its break hook).
    breaker: Option<Box<dyn Fn() + Send + Sync>>,
}

impl TaskCore {
    fn state(&self) -> TaskState {
        self.state.get()
    }

    fn set_state(&self, s: TaskState) {
        self.state.set(s);
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
    ) -> (Result<R, String>, Asked) {
        let mut ctx = Context {
            core: self,
            events,
            timing,
            asked: Asked::default(),
        };
        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| f(comp, &mut ctx)))
            .map_err(|p| {
                p.downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| p.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "(no message)".into())
            });
        (r, ctx.asked)
    }

    /// Enters Exception from any state: exception hook, then the stop hook if it was
    /// running. A panic in either goes to FatalError.
    fn enter_exception(&self, comp: &mut dyn ErasedComponent, reason: String) -> TaskState {
        self.enter_exception_from(comp, reason, None)
    }

    /// [`enter_exception`](Self::enter_exception) from lifecycle hook `hook`: the stop
    /// hook is not run again when it was the hook that failed.
    fn enter_exception_from(
        &self,
        comp: &mut dyn ErasedComponent,
        reason: String,
        hook: Option<&str>,
    ) -> TaskState {
        let was_running = matches!(self.state(), TaskState::Running | TaskState::RunTimeError)
            && hook != Some("stop_hook");
        let [a, b, c, d] = Arg::chunks(&reason);
        crate::rt_log!(self.log, Error, "entering Exception: {}{}{}{}", a, b, c, d);
        self.record_failure(reason);
        self.exceptions.fetch_add(1, Ordering::Relaxed);
        self.set_state(TaskState::Exception);
        self.activity.stop();
        let events = FdEvents::default();
        let timing = StepTiming::default();
        let (r, _) = self.run_hook(comp, &events, timing, |c, ctx| c.exception_hook(ctx));
        let r = r.and_then(|()| {
            if was_running {
                self.run_hook(comp, &events, timing, |c, ctx| c.stop_hook(ctx))
                    .0
            } else {
                Ok(())
            }
        });
        if let Err(msg) = r {
            let [a, b, c] = Arg::chunks(&msg);
            crate::rt_log!(
                self.log,
                Error,
                "handling the exception panicked: {}{}{}; FatalError",
                a,
                b,
                c
            );
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

    /// The component, noted as held by this thread while the guard lives; `None` when
    /// this thread holds it already (a hook that reached its own component).
    fn lock_component(&self) -> Option<Held<'_>> {
        let me = this_thread();
        if self.holder.load(Ordering::Acquire) == me {
            return None;
        }
        let guard = lock(&self.component);
        self.holder.store(me, Ordering::Release);
        Some(Held {
            guard,
            holder: &self.holder,
        })
    }

    /// The component, for a thread outside it while its activity runs (`error`,
    /// `recover`): the activity's steps are skipped until this thread has it, a step under
    /// way is woken (its activity's wake hook ends a wait in the component's own code), and
    /// the activity is asked for a step when the guard goes.
    fn lock_from_outside(&self) -> Option<Outside<'_>> {
        self.outside.fetch_add(1, Ordering::AcqRel);
        self.activity.trigger();
        let held = self.lock_component();
        self.outside.fetch_sub(1, Ordering::AcqRel);
        Some(Outside {
            held: Some(held?),
            activity: &self.activity,
        })
    }

    /// Whether this thread is inside the component's hook or step.
    fn held_here(&self) -> bool {
        self.holder.load(Ordering::Acquire) == this_thread()
    }

    fn step(&self, events: &FdEvents, timing: StepTiming) {
        // A thread outside waits for the component: it goes first (it asks for a step
        // when done).
        if self.outside.load(Ordering::Acquire) > 0 {
            return;
        }
        // A step from within the component's own hook (a script stepping itself) is none.
        let Some(mut guard) = self.lock_component() else {
            return;
        };
        let comp: &mut dyn ErasedComponent = &mut **guard;
        while let Some(call) = self.queue.pop() {
            call.run(comp.as_any_mut());
        }
        if matches!(self.state(), TaskState::Running | TaskState::RunTimeError) {
            self.look_at_requirements(comp, events, timing);
        }
        match self.state() {
            TaskState::Running => {
                let (r, asked) = self.run_hook(comp, events, timing, |c, ctx| c.update_hook(ctx));
                match r {
                    Ok(Ok(())) if asked.exception.is_some() => {
                        let reason = asked.exception.unwrap_or_default();
                        self.enter_exception(comp, format!("update raised an exception: {reason}"));
                    }
                    Ok(Ok(())) if asked.error => {
                        self.runtime_errors.fetch_add(1, Ordering::Relaxed);
                        self.set_state(TaskState::RunTimeError);
                    }
                    Ok(Ok(())) => {}
                    // The gateway is stopping and holds its outputs: no failure of the
                    // component's (the stop reaches it next).
                    Ok(Err(e)) if e.is_held() => {
                        crate::rt_log!(self.log, Debug, "update skipped: {}", Arg::display(&e));
                    }
                    Ok(Err(e)) => {
                        self.enter_exception(comp, format!("update failed: {e}"));
                    }
                    Err(panic) => {
                        self.enter_exception(comp, format!("update panicked: {panic}"));
                    }
                }
            }
            TaskState::RunTimeError => {
                let (r, asked) = self.run_hook(comp, events, timing, |c, ctx| c.error_hook(ctx));
                match r {
                    Ok(()) if asked.exception.is_some() => {
                        let reason = asked.exception.unwrap_or_default();
                        self.enter_exception(
                            comp,
                            format!("error hook raised an exception: {reason}"),
                        );
                    }
                    Ok(()) if asked.recover => self.set_state(TaskState::Running),
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
    fn submit(&self, operation: &str, call: Queued) -> Result<Duration, (CallError, Queued)> {
        let state = self.state();
        if !self.activity.is_running()
            || !matches!(state, TaskState::Running | TaskState::RunTimeError)
        {
            let e = CallError::NotRunning {
                operation: operation.to_string(),
                component: self.name.clone(),
                state: state.to_string(),
            };
            return Err((e, call));
        }
        if self.engine_thread.load(Ordering::Acquire) == this_thread() || self.held_here() {
            let e = CallError::Reentrant {
                operation: operation.to_string(),
            };
            return Err((e, call));
        }
        if let Err(call) = self.queue.push(call) {
            self.calls_refused.fetch_add(1, Ordering::Relaxed);
            let e = CallError::QueueFull {
                operation: operation.to_string(),
                component: self.name.clone(),
                capacity: QUEUE_CAPACITY,
            };
            return Err((e, call));
        }
        self.activity.trigger();
        // A stop that drained the queue after the look above and before the push would
        // leave this call queued until the next start: look again, and cancel what is
        // queued once the engine is stopped.
        if !self.activity.is_running() {
            self.drain_queue();
        }
        // A non-periodic engine answers at once (a caller spinning, yielding after 2 µs,
        // takes the result without a wake-up); the others step on their own schedule.
        Ok(match self.activity.spec() {
            ActivitySpec::NonPeriodic { thread } => {
                Duration::from_micros(u64::from(thread.spin_us))
            }
            _ => Duration::ZERO,
        })
    }

    fn note_slot_allocated(&self) {
        self.call_slots_allocated.fetch_add(1, Ordering::Relaxed);
    }
}

/// A number for the calling thread (`ThreadId` has no stable integer form); never 0.
fn this_thread() -> u64 {
    static NEXT: AtomicU64 = AtomicU64::new(1);
    thread_local!(static ID: u64 = NEXT.fetch_add(1, Ordering::Relaxed));
    ID.with(|id| *id)
}

/// The component's lock, with its holder noted until it is let go.
struct Held<'a> {
    guard: std::sync::MutexGuard<'a, Box<dyn ErasedComponent>>,
    holder: &'a AtomicU64,
}

impl Drop for Held<'_> {
    fn drop(&mut self) {
        // Before the guard lets go (fields drop after this): no other thread can have
        // noted itself meanwhile.
        self.holder.store(0, Ordering::Release);
    }
}

/// The component held by a thread outside it (see `TaskCore::lock_from_outside`): when
/// it goes, the component is let go and its activity asked for the step it skipped.
struct Outside<'a> {
    held: Option<Held<'a>>,
    activity: &'a Activity,
}

impl Drop for Outside<'_> {
    fn drop(&mut self) {
        self.held = None;
        self.activity.trigger();
    }
}

impl std::ops::Deref for Held<'_> {
    type Target = Box<dyn ErasedComponent>;
    fn deref(&self) -> &Self::Target {
        &self.guard
    }
}

impl std::ops::DerefMut for Held<'_> {
    fn deref_mut(&mut self) -> &mut Self::Target {
        &mut self.guard
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
            core.engine_thread.store(this_thread(), Ordering::Release);
        }
        core.step(events, timing);
        // Its slaves, after its own step and on its thread (the component's lock let go).
        for slave in core.slaves.load().iter() {
            let _ = slave.step();
        }
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
        initial: InitialState,
        setup: TaskSetup,
        build: impl FnOnce(&mut InterfaceBuilder<C>) -> Result<C, IntrospectError>,
    ) -> Result<TaskContext, RuntimeError> {
        let activity =
            Activity::new(spec, name, setup.scope, setup.thread_number).map_err(|e| {
                RuntimeError::Activity {
                    component: name.to_string(),
                    source: Arc::new(e),
                }
            })?;
        let waker = activity.waker();
        let mut build_result = None;
        let core = Arc::new_cyclic(|weak: &Weak<TaskCore>| {
            let engine: Weak<dyn Engine> = weak.clone();
            let mut iface = InterfaceBuilder::new(name, engine, waker, setup.registry.clone());
            let component: Box<dyn ErasedComponent> = match build(&mut iface) {
                Ok(c) => Box::new(c),
                Err(e) => {
                    build_result = Some(e);
                    Box::new(Placeholder)
                }
            };
            let iface = iface.into_parts();
            TaskCore {
                name: name.to_string(),
                log: crate::log::Area::named(name),
                me: weak.clone(),
                state: Arc::new(StateCell::new(TaskState::Init)),
                component: Mutex::new(component),
                queue: Bounded::new(QUEUE_CAPACITY),
                calls_refused: AtomicU64::new(0),
                call_slots_allocated: AtomicU64::new(0),
                activity,
                ports: arc_swap::ArcSwap::from_pointee(iface.ports),
                operations: iface.operations,
                properties: iface.properties,
                attributes: iface.attributes,
                provided: iface.provided,
                required: iface.required,
                registry: setup.registry,
                clock: setup.clock,
                runtime_errors: AtomicU64::new(0),
                exceptions: AtomicU64::new(0),
                failed_hooks: AtomicU64::new(0),
                warning: AtomicBool::new(false),
                warnings: AtomicU64::new(0),
                last_error: Mutex::new(None),
                engine_thread: AtomicU64::new(0),
                holder: AtomicU64::new(0),
                outside: AtomicU32::new(0),
                peers: setup.peers,
                slaves: arc_swap::ArcSwap::from_pointee(Vec::new()),
                peer_aliases: Mutex::new(Vec::new()),
                breaker: iface.breaker,
            }
        });
        if let Some(e) = build_result {
            return Err(RuntimeError::Build {
                component: name.to_string(),
                source: e,
            });
        }
        core.set_state(initial.into());
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

    fn reentrant(&self, command: &'static str) -> LifecycleError {
        LifecycleError::Reentrant {
            component: self.core.name.clone(),
            command,
        }
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
        let Some(mut guard) = self.core.lock_component() else {
            return Err(self.reentrant(command));
        };
        if !allowed.contains(&self.state()) {
            return Err(self.illegal(command));
        }
        let comp: &mut dyn ErasedComponent = &mut **guard;
        let (r, asked) = self
            .core
            .run_hook(comp, &FdEvents::default(), StepTiming::default(), f);
        match r {
            Ok(Ok(())) if asked.exception.is_some() => {
                let message = asked.exception.unwrap_or_default();
                let state = self.core.enter_exception_from(
                    comp,
                    format!("{hook} raised an exception: {message}"),
                    Some(hook),
                );
                Err(LifecycleError::Exception {
                    component: self.core.name.clone(),
                    hook,
                    message,
                    state,
                })
            }
            Ok(Ok(())) => {
                self.core.set_state(success);
                Ok(())
            }
            Ok(Err(e)) => {
                self.core.record_failure(format!("{hook} failed: {e}"));
                if hook == "reset_hook" {
                    // What a reset could not put right is configured again (set under
                    // the component's lock: no second recover runs the reset meanwhile).
                    self.core.set_state(TaskState::PreOperational);
                }
                Err(LifecycleError::HookFailed {
                    component: self.core.name.clone(),
                    hook,
                    message: e.message().to_string(),
                })
            }
            Err(panic) => {
                let state = self.core.enter_exception_from(
                    comp,
                    format!("{hook} panicked: {panic}"),
                    Some(hook),
                );
                Err(LifecycleError::HookPanicked {
                    component: self.core.name.clone(),
                    hook,
                    message: panic,
                    state,
                })
            }
        }
    }

    /// PreOperational or Stopped → Stopped, via the configure hook; refused while a
    /// requirement that is not optional is unbound.
    pub fn configure(&self) -> Result<(), LifecycleError> {
        self.core.unbound()?;
        self.hook(
            "configure",
            &[TaskState::PreOperational, TaskState::Stopped],
            "configure_hook",
            |c, ctx| c.configure_hook(ctx),
            TaskState::Stopped,
        )
    }

    /// Stopped → Running: the start hook, then the activity starts; refused while a
    /// requirement that is not optional is unbound.
    pub fn start(&self) -> Result<(), LifecycleError> {
        self.core.unbound()?;
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
        if self.core.held_here() {
            return Err(self.reentrant("stop"));
        }
        if !matches!(self.state(), TaskState::Running | TaskState::RunTimeError) {
            return Err(self.illegal("stop"));
        }
        // Stop the thread first, without holding the component: its step needs it. Its
        // break hook once the thread is told: a step blocked in the component's own code
        // returns, and the thread, seeing the stop, can be joined.
        self.core
            .activity
            .stop_breaking(self.core.breaker.as_deref());
        self.core.engine_thread.store(0, Ordering::Release);
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

    /// Stopped → PreOperational, via the cleanup hook; the warning flag and the warning
    /// and error counters start again from zero (manual L832–884).
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
        )?;
        let core = &self.core;
        for counter in [
            &core.runtime_errors,
            &core.exceptions,
            &core.failed_hooks,
            &core.warnings,
        ] {
            counter.store(0, Ordering::Relaxed);
        }
        core.warning.store(false, Ordering::Relaxed);
        *lock(&core.last_error) = None;
        for r in &core.required {
            r.reset_counts();
        }
        Ok(())
    }

    /// RunTimeError → Running; Exception → the reset hook, then Stopped when it
    /// succeeds, PreOperational (configure again) when it fails (manual L886–953).
    pub fn recover(&self) -> Result<(), LifecycleError> {
        match self.state() {
            TaskState::RunTimeError => {
                let Some(_guard) = self.core.lock_from_outside() else {
                    return Err(self.reentrant("recover"));
                };
                if self.state() != TaskState::RunTimeError {
                    return Err(self.illegal("recover"));
                }
                self.core.set_state(TaskState::Running);
                Ok(())
            }
            TaskState::Exception => self.hook(
                "recover",
                &[TaskState::Exception],
                "reset_hook",
                |c, ctx| c.reset_hook(ctx),
                TaskState::Stopped,
            ),
            _ => Err(self.illegal("recover")),
        }
    }

    /// Running → RunTimeError, from outside the component.
    pub fn error(&self) -> Result<(), LifecycleError> {
        let Some(_guard) = self.core.lock_from_outside() else {
            return Err(self.reentrant("error"));
        };
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
            warning: self.core.warning.load(Ordering::Relaxed),
            warnings: self.core.warnings.load(Ordering::Relaxed),
            services_lost: self.core.required.iter().map(|r| r.counts().0).sum(),
            services_back: self.core.required.iter().map(|r| r.counts().1).sum(),
            calls_refused: self.core.calls_refused.load(Ordering::Relaxed),
            call_slots_allocated: self.core.call_slots_allocated.load(Ordering::Relaxed),
        }
    }
}

/// Stands in for a component whose constructor failed (never runs).
struct Placeholder;
impl Component for Placeholder {}
