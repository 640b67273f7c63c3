//! Activities: what makes a component step, and on which thread.
//!
//! - **Periodic**: a thread of its own wakes on an absolute grid of the monotonic clock
//!   (`clock_nanosleep(TIMER_ABSTIME)`, as cyclictest does), with a priority,
//!   SCHED_FIFO or SCHED_OTHER, a CPU affinity and an overrun policy.
//! - **Non-periodic**: a thread of its own sleeps until woken — by an event port receiving
//!   data, an OwnThread operation being queued, or `trigger()`.
//! - **File descriptor**: a thread of its own waits in epoll on watched descriptors (CAN
//!   sockets, serial ports, GPIO line events) with a timeout, and for a deadline the
//!   component sets with [`Activity::wake_at`] (the next poll of a bus); the step sees which
//!   descriptors are ready, that the deadline came, or that the timeout passed.
//! - **Slave**: no thread; stepped explicitly. Every deterministic test uses it.
//!
//! Each keeps statistics: steps, a histogram of wake-up lateness, step duration, overruns.
//! When the process may not use SCHED_FIFO the activity says so once, with the reason, and
//! runs SCHED_OTHER.

mod deadline;
mod realtime;
mod spells;
mod stats;
pub mod steps;
mod thread;

pub use realtime::ThreadError;
pub use stats::{ActivityStats, HISTOGRAM_BUCKETS};
use steps::in_step;
pub(crate) use steps::step_owner;
pub use steps::{StepRecord, StepTap, stamp_now};

use crate::scope::ThreadScope;
use deadline::Deadline;
#[doc(hidden)]
pub use deadline::{use_precise_deadlines_for_every_thread, use_timer_deadlines};
use device_interface::time::{Clock, MonotonicClock, Timestamp};
use nix::sys::epoll::{Epoll, EpollCreateFlags, EpollEvent, EpollFlags};
use nix::sys::eventfd::{EfdFlags, EventFd};
use serde::{Deserialize, Serialize};
use stats::StatsCell;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, OwnedFd, RawFd};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;
use thread::{Signal, thread_main};

/// Something that makes an activity step soon. Never blocks, never allocates.
pub trait Waker: Send + Sync {
    /// Asks for a step.
    fn wake(&self);
}

/// Linux scheduling class of an activity's thread.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SchedPolicy {
    /// The normal time-sharing class.
    #[default]
    Other,
    /// Real-time, first in first out, at a priority 1..=99.
    Fifo,
}

/// Where and how an activity's thread runs.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ThreadOptions {
    /// Scheduling class.
    #[serde(default)]
    pub policy: SchedPolicy,
    /// Priority within the class (1..=99 for SCHED_FIFO; ignored for SCHED_OTHER).
    #[serde(default)]
    pub priority: i32,
    /// CPUs the thread may run on; empty: any.
    #[serde(default)]
    pub cpus: Vec<usize>,
    /// How long a non-periodic activity's thread spins for its next trigger before it
    /// parks, and a caller of its OwnThread operations for the result, µs (default
    /// [`DEFAULT_SPIN_US`]; 0: park at once; at most [`MAX_SPIN_US`]). A call or trigger
    /// within the spin is seen in nanoseconds instead of a scheduler wake-up; the cost is
    /// at most this much busy time after each step.
    #[serde(default = "default_spin_us")]
    pub spin_us: u32,
}

/// The default spin of a non-periodic activity and its callers, µs.
pub const DEFAULT_SPIN_US: u32 = 20;
/// The longest spin an activity may be given, µs.
pub const MAX_SPIN_US: u32 = 10_000;

fn default_spin_us() -> u32 {
    DEFAULT_SPIN_US
}

impl Default for ThreadOptions {
    fn default() -> Self {
        ThreadOptions {
            policy: SchedPolicy::Other,
            priority: 0,
            cpus: Vec::new(),
            spin_us: DEFAULT_SPIN_US,
        }
    }
}

/// What a periodic activity does after a step that ran past its next wake-up.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Timing {
    /// Keep the absolute grid `start + k * period`: missed wake-ups are skipped and counted.
    #[default]
    Absolute,
    /// Wake one period after the last wake-up: no skipping, the grid drifts by the overrun.
    Relative,
}

/// What kind of activity steps a component.
#[derive(Debug, Clone, PartialEq)]
pub enum ActivitySpec {
    /// A thread waking every `period`.
    Periodic {
        /// The period.
        period: Duration,
        /// Thread options.
        thread: ThreadOptions,
        /// Overrun handling.
        timing: Timing,
        /// After this many consecutive overruns the activity reports itself unhealthy
        /// (the service's watchdog stops being fed); `None`: never.
        max_overruns: Option<u32>,
    },
    /// A thread stepping when woken.
    NonPeriodic {
        /// Thread options.
        thread: ThreadOptions,
    },
    /// A thread stepping when a watched file descriptor is ready, or after `timeout`.
    FileDescriptor {
        /// Step anyway after this long without events; `None`: wait forever.
        timeout: Option<Duration>,
        /// Thread options.
        thread: ThreadOptions,
    },
    /// No thread: stepped by hand.
    Slave,
}

/// The longest period a periodic activity takes.
pub const MAX_PERIOD: Duration = Duration::from_secs(86_400);

impl ActivitySpec {
    /// A periodic activity at `period`, SCHED_OTHER, absolute timing.
    pub fn periodic(period: Duration) -> Self {
        ActivitySpec::Periodic {
            period,
            thread: ThreadOptions::default(),
            timing: Timing::Absolute,
            max_overruns: None,
        }
    }

    /// A non-periodic activity, SCHED_OTHER.
    pub fn non_periodic() -> Self {
        ActivitySpec::NonPeriodic {
            thread: ThreadOptions::default(),
        }
    }

    /// A file-descriptor activity with `timeout`, SCHED_OTHER.
    pub fn file_descriptor(timeout: Option<Duration>) -> Self {
        ActivitySpec::FileDescriptor {
            timeout,
            thread: ThreadOptions::default(),
        }
    }

    fn has_thread(&self) -> bool {
        !matches!(self, ActivitySpec::Slave)
    }
}

/// Why an activity could not start or watch.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ActivityError {
    /// The thread could not be spawned.
    #[error("could not start the activity thread: {0}")]
    Spawn(#[source] std::io::Error),
    /// An epoll or eventfd call failed.
    #[error("file-descriptor activity: {what}: {source}")]
    Fd {
        /// What was being done.
        what: &'static str,
        /// The error.
        #[source]
        source: nix::Error,
    },
    /// `watch` on an activity that is not a file-descriptor activity.
    #[error("only a file-descriptor activity watches file descriptors")]
    NotFileDescriptor,
    /// `step` on an activity that is not a slave.
    #[error("only a slave activity is stepped by hand; this one has its own thread")]
    NotSlave,
    /// A period of zero.
    #[error("a periodic activity needs a period above zero")]
    ZeroPeriod,
    /// A period longer than a day.
    #[error("a period of {0:?} is too long (at most a day)")]
    PeriodTooLong(Duration),
    /// Thread options that cannot be had.
    #[error(transparent)]
    Thread(#[from] ThreadError),
    /// `wake_at` on an activity that is not a file-descriptor activity.
    #[error("only a file-descriptor activity wakes at a deadline")]
    NoDeadline,
    /// `set_period` on an activity that is not periodic.
    #[error("only a periodic activity has a period")]
    NotPeriodic,
    /// `set_thread` on a slave activity.
    #[error("a slave activity has no thread of its own")]
    NoThread,
    /// A change of a running activity.
    #[error("the activity is running: stop its component first")]
    Running,
}

impl ActivityError {
    /// The error of the system call `what` that failed (for `map_err`).
    fn fd(what: &'static str) -> impl FnOnce(nix::Error) -> ActivityError {
        move |source| ActivityError::Fd { what, source }
    }
}

/// The descriptors that were ready for one step of a file-descriptor activity.
#[derive(Debug, Clone, Copy)]
pub struct FdEvents {
    ready: [RawFd; FdEvents::MAX],
    count: usize,
    timeout: bool,
    deadline: bool,
}

impl Default for FdEvents {
    fn default() -> Self {
        FdEvents {
            ready: [-1; FdEvents::MAX],
            count: 0,
            timeout: false,
            deadline: false,
        }
    }
}

impl FdEvents {
    /// How many ready descriptors one step reports at most.
    pub const MAX: usize = 32;

    /// True when `fd` (as given to `watch`) was ready.
    pub fn is_updated(&self, fd: RawFd) -> bool {
        self.ready[..self.count].contains(&fd)
    }

    /// True when the step came from the timeout, not from a descriptor.
    pub fn has_timeout(&self) -> bool {
        self.timeout
    }

    /// True when the deadline set with [`Activity::wake_at`] came.
    pub fn deadline_passed(&self) -> bool {
        self.deadline
    }

    /// The ready descriptors.
    pub fn ready(&self) -> &[RawFd] {
        &self.ready[..self.count]
    }
}

/// When a step was due and when it began, on the monotonic clock.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StepTiming {
    /// When the step was due: the periodic grid point, the wake-up request, or (file
    /// descriptor and slave activities) the start of the step.
    pub scheduled: Timestamp,
    /// When the step began.
    pub started: Timestamp,
}

impl StepTiming {
    fn now() -> Self {
        let t = MonotonicClock.now();
        StepTiming {
            scheduled: t,
            started: t,
        }
    }

    /// How late the step began.
    pub fn lateness(&self) -> Duration {
        self.started.duration_since(self.scheduled)
    }
}

/// One step, as every kind of activity runs it: ThreadScope's pulse around it, its start as
/// the time of what it writes to stamped connections, then its statistics and step taps.
/// Returns when it ended (monotonic ns).
#[inline]
fn run_step(shared: &Shared, runner: &dyn Runner, events: &FdEvents, timing: StepTiming) -> u64 {
    let started = timing.started.as_nanos();
    // The activity's address: its own while it lives, and never 0.
    let owner = shared as *const Shared as u64;
    shared
        .scope
        .pulse(|| in_step(started, owner, || runner.step(events, timing)));
    let ended = MonotonicClock.now().as_nanos();
    // A step that waited in its component's own code counts from the end of the wait
    // (see `Activity::restart_step`); only this thread writes the cell.
    let (scheduled, started) = match shared.restarted.load(Ordering::Relaxed) {
        0 => (timing.scheduled.as_nanos(), started),
        at => {
            shared.restarted.store(0, Ordering::Relaxed);
            (at, at)
        }
    };
    shared.stats.step(scheduled, started, ended);
    ended
}

/// What an activity steps.
pub(crate) trait Runner: Send + Sync {
    fn step(&self, events: &FdEvents, timing: StepTiming);
}

struct FdState {
    epoll: Epoll,
    wake: EventFd,
    /// The deadline set by `wake_at`.
    deadline: Deadline,
    /// (fd as the user knows it, our duplicate registered with epoll)
    watched: Mutex<Vec<(RawFd, OwnedFd)>>,
    /// How many are watched (for the thread, without the lock).
    watching: AtomicUsize,
}

struct Shared {
    /// As built: its kind never changes.
    spec: ActivitySpec,
    /// As changed since ([`Activity::set_period`], [`Activity::set_thread`]): taken by the
    /// thread when it starts.
    changed: Mutex<Option<ActivitySpec>>,
    name: String,
    /// Where its thread logs (the component's name).
    log: crate::log::Area,
    thread_number: Option<u32>,
    running: AtomicBool,
    signal: Signal,
    fd: Option<FdState>,
    stats: StatsCell,
    scope: Arc<ThreadScope>,
    /// When the step under way restarted its clock (monotonic ns; 0: it did not).
    restarted: AtomicU64,
    /// Called at every wake-up, after the activity's own (see [`Activity::on_wake`]).
    wake_hook: std::sync::OnceLock<Box<dyn Fn() + Send + Sync>>,
}

impl Waker for Shared {
    fn wake(&self) {
        match &self.spec {
            ActivitySpec::NonPeriodic { .. } => self.signal.notify(MonotonicClock.now().as_nanos()),
            ActivitySpec::FileDescriptor { .. } => {
                if let Some(fd) = &self.fd {
                    let _ = fd.wake.write(1);
                    fd.deadline.nudge();
                }
                if let Some(hook) = self.wake_hook.get() {
                    hook();
                }
            }
            // A periodic activity processes its queue at the next period; a slave when stepped.
            ActivitySpec::Periodic { .. } | ActivitySpec::Slave => {}
        }
    }
}

/// An activity: the thread (or not) that steps one component.
pub struct Activity {
    shared: Arc<Shared>,
    handle: Mutex<Option<JoinHandle<()>>>,
}

impl Activity {
    pub(crate) fn new(
        spec: ActivitySpec,
        name: &str,
        scope: Arc<ThreadScope>,
        thread_number: impl FnOnce() -> u32,
    ) -> Result<Self, ActivityError> {
        if let ActivitySpec::Periodic { period, .. } = &spec {
            if period.is_zero() {
                return Err(ActivityError::ZeroPeriod);
            }
            if *period > MAX_PERIOD {
                return Err(ActivityError::PeriodTooLong(*period));
            }
        }
        let thread = match &spec {
            ActivitySpec::Periodic { thread, .. }
            | ActivitySpec::NonPeriodic { thread }
            | ActivitySpec::FileDescriptor { thread, .. } => Some(thread),
            ActivitySpec::Slave => None,
        };
        if let Some(t) = thread {
            t.check().map_err(ActivityError::Thread)?;
        }
        let fd = match &spec {
            ActivitySpec::FileDescriptor { .. } => {
                let epoll = Epoll::new(EpollCreateFlags::EPOLL_CLOEXEC)
                    .map_err(ActivityError::fd("epoll_create"))?;
                let wake = eventfd_in(&epoll, WAKE_EVENT)?;
                let deadline = Deadline::new(&epoll)?;
                Some(FdState {
                    epoll,
                    wake,
                    deadline,
                    watched: Mutex::new(Vec::new()),
                    watching: AtomicUsize::new(0),
                })
            }
            _ => None,
        };
        let thread_number = spec.has_thread().then(thread_number);
        if let Some(n) = thread_number {
            scope.name_thread(n, name);
        }
        if let (Some(n), true) = (thread_number, scope.is_on()) {
            tracing::info!(
                activity = name,
                bit = n,
                "ThreadScope: thread {name} is bit {n}"
            );
        }
        Ok(Activity {
            shared: Arc::new(Shared {
                spec,
                changed: Mutex::new(None),
                name: name.to_string(),
                log: crate::log::Area::named(name),
                thread_number,
                running: AtomicBool::new(false),
                signal: Signal::new(),
                fd,
                stats: StatsCell::new(),
                scope,
                restarted: AtomicU64::new(0),
                wake_hook: std::sync::OnceLock::new(),
            }),
            handle: Mutex::new(None),
        })
    }

    /// A tap on this activity's steps from now on, holding at most `capacity` steps not yet
    /// drained (clamped to 1..=[`steps::MAX_TAP`]); see [`steps`].
    pub fn tap_steps(&self, capacity: usize) -> StepTap {
        StepTap::new(&self.shared.stats.taps, capacity)
    }

    /// The activity's kind and parameters as built (see [`current`](Self::current) for
    /// what it runs with after a change).
    pub fn spec(&self) -> &ActivitySpec {
        &self.shared.spec
    }

    /// The activity's kind and parameters as it runs (or will, at its next start): as
    /// built, with the changes of [`set_period`](Self::set_period) and
    /// [`set_thread`](Self::set_thread).
    pub fn current(&self) -> ActivitySpec {
        crate::lock::lock(&self.shared.changed)
            .clone()
            .unwrap_or_else(|| self.shared.spec.clone())
    }

    /// A new period for a periodic activity that is not running (RTT's `setPeriod`): taken
    /// at its next start.
    pub fn set_period(&self, new: Duration) -> Result<(), ActivityError> {
        if new.is_zero() {
            return Err(ActivityError::ZeroPeriod);
        }
        if new > MAX_PERIOD {
            return Err(ActivityError::PeriodTooLong(new));
        }
        self.change(|spec| match spec {
            ActivitySpec::Periodic { period, .. } => {
                *period = new;
                Ok(())
            }
            _ => Err(ActivityError::NotPeriodic),
        })
    }

    /// New thread options (policy, priority, CPUs) for an activity with a thread that is not
    /// running (RTT's `setPriority`/`setScheduler`): taken at its next start.
    pub fn set_thread(&self, options: ThreadOptions) -> Result<(), ActivityError> {
        options.check()?;
        self.change(|spec| match spec {
            ActivitySpec::Periodic { thread, .. }
            | ActivitySpec::NonPeriodic { thread }
            | ActivitySpec::FileDescriptor { thread, .. } => {
                *thread = options;
                Ok(())
            }
            ActivitySpec::Slave => Err(ActivityError::NoThread),
        })
    }

    fn change(
        &self,
        f: impl FnOnce(&mut ActivitySpec) -> Result<(), ActivityError>,
    ) -> Result<(), ActivityError> {
        let mut changed = crate::lock::lock(&self.shared.changed);
        if self.shared.running.load(Ordering::Acquire) {
            return Err(ActivityError::Running);
        }
        let mut spec = changed.clone().unwrap_or_else(|| self.shared.spec.clone());
        f(&mut spec)?;
        *changed = Some(spec);
        Ok(())
    }

    /// The thread number (ThreadScope bit) of the activity's thread; `None` for a slave.
    pub fn thread_number(&self) -> Option<u32> {
        self.shared.thread_number
    }

    /// True while the activity's thread runs (a slave: between start and stop).
    pub fn is_running(&self) -> bool {
        self.shared.running.load(Ordering::Acquire)
    }

    /// The statistics so far.
    pub fn stats(&self) -> ActivityStats {
        self.shared.stats.snapshot()
    }

    /// From the activity's own step, which waited in its component's own code for what it
    /// now handles (a bus reading a frame in a blocking call): the step counts from now —
    /// its duration, the lateness and the stamp of what it writes to stamped connections —
    /// so the time it waited is not taken for time it worked. Returns the time it took (the
    /// monotonic clock's now, read once, for the caller to use too). Changes nothing from
    /// any other thread, or outside a step. The step's `Context::timing`, given before the
    /// step began, still says when the step was woken; the statistics and stamps count
    /// from the time returned here.
    pub fn restart_step(&self) -> Timestamp {
        let now = MonotonicClock.now().as_nanos().max(1);
        let owner = Arc::as_ptr(&self.shared) as u64;
        if steps::step_owner() == owner {
            steps::restart_step_clock(now);
            self.shared.restarted.store(now, Ordering::Relaxed);
        }
        Timestamp::from_nanos(now)
    }

    /// Adds `hook` to every wake-up of a file-descriptor activity (a trigger, an event
    /// port, an OwnThread call, another thread's `wake_at`, a stop), called after the
    /// activity's own: for a component whose step waits in its own code (a bus blocked
    /// in `recvmsg`), to end that wait. The first hook given stays; it must not block.
    pub fn on_wake(&self, hook: impl Fn() + Send + Sync + 'static) {
        let _ = self.shared.wake_hook.set(Box::new(hook));
    }

    /// Asks for a step soon (non-periodic and file-descriptor activities; a no-op for the
    /// others, which step on their own schedule or by hand).
    pub fn trigger(&self) {
        self.shared.wake();
    }

    /// A handle that asks this activity for a step from any thread, as [`trigger`](Self::trigger)
    /// does, holding nothing of its component: for a device's write path to wake the bus
    /// side that sends it. Waking is one `eventfd` write (file-descriptor activities) or a
    /// notify (non-periodic); never blocks, never allocates.
    pub fn waker(&self) -> Arc<dyn Waker> {
        self.shared.clone()
    }

    /// Watches `fd` for readability (file-descriptor activities). The activity keeps a
    /// duplicate of the descriptor until [`unwatch`](Self::unwatch); `FdEvents::is_updated`
    /// reports it by the number given here.
    pub fn watch(&self, fd: BorrowedFd<'_>) -> Result<(), ActivityError> {
        let state = self
            .shared
            .fd
            .as_ref()
            .ok_or(ActivityError::NotFileDescriptor)?;
        let dup = fd.try_clone_to_owned().map_err(|e| ActivityError::Fd {
            what: "dup",
            source: nix::Error::from_raw(e.raw_os_error().unwrap_or(0)),
        })?;
        let user = fd.as_raw_fd();
        state
            .epoll
            .add(
                dup.as_fd(),
                EpollEvent::new(EpollFlags::EPOLLIN, user as u64),
            )
            .map_err(ActivityError::fd("epoll_ctl(add)"))?;
        let mut watched = crate::lock::lock(&state.watched);
        watched.push((user, dup));
        state.watching.store(watched.len(), Ordering::Release);
        Ok(())
    }

    /// Asks a file-descriptor activity for a step at `at` (the monotonic clock), replacing
    /// any deadline set before; a time already past steps at once. The step reports it with
    /// [`FdEvents::deadline_passed`]. From the activity's own step: no system call; the
    /// thread applies it when the step ends, and a time already past then costs no timer at
    /// all. From another thread: one (an eventfd write); the thread applies it when that
    /// wakes it, or at its start (see the `deadline` module).
    pub fn wake_at(&self, at: Timestamp) -> Result<(), ActivityError> {
        let state = self.shared.fd.as_ref().ok_or(ActivityError::NoDeadline)?;
        state.deadline.wake_at(at.as_nanos())
    }

    /// Stops watching `fd`; true if it was watched.
    pub fn unwatch(&self, fd: RawFd) -> bool {
        let Some(state) = &self.shared.fd else {
            return false;
        };
        let mut w = crate::lock::lock(&state.watched);
        let Some(i) = w.iter().position(|(u, _)| *u == fd) else {
            return false;
        };
        let (_, dup) = w.swap_remove(i);
        state.watching.store(w.len(), Ordering::Release);
        let _ = state.epoll.delete(dup.as_fd());
        true
    }

    pub(crate) fn start(&self, runner: Arc<dyn Runner>) -> Result<(), ActivityError> {
        if self.shared.running.swap(true, Ordering::AcqRel) {
            return Ok(());
        }
        if !self.shared.spec.has_thread() {
            return Ok(());
        }
        let shared = self.shared.clone();
        let spawned = std::thread::Builder::new()
            .name(self.shared.name.chars().take(15).collect())
            .spawn(move || thread_main(shared, runner));
        match spawned {
            Ok(h) => {
                if matches!(self.shared.spec, ActivitySpec::NonPeriodic { .. }) {
                    self.shared
                        .signal
                        .thread
                        .store(Some(Arc::new(h.thread().clone())));
                }
                *crate::lock::lock(&self.handle) = Some(h);
                Ok(())
            }
            Err(e) => {
                self.shared.running.store(false, Ordering::Release);
                Err(ActivityError::Spawn(e))
            }
        }
    }

    /// Stops the thread and waits for it: the step under way finishes; a periodic activity's
    /// sleep is cut short (within 50 ms, whatever its period).
    pub(crate) fn stop(&self) {
        self.stop_breaking(None);
    }

    /// Stops the thread as [`stop`](Self::stop) does, calling `brk` (the component's break
    /// hook) once the thread is told to stop and before it is joined: a step blocked in the
    /// component's own code returns, and the thread, looking at its flag, ends.
    pub(crate) fn stop_breaking(&self, brk: Option<&(dyn Fn() + Send + Sync)>) {
        if !self.shared.running.swap(false, Ordering::AcqRel) {
            return;
        }
        self.shared.wake();
        if let Some(b) = brk {
            b();
        }
        if let Some(t) = self.shared.signal.thread.load().as_deref() {
            t.unpark();
        }
        let handle = crate::lock::lock(&self.handle).take();
        if let Some(h) = handle
            && h.thread().id() != std::thread::current().id()
        {
            let _ = h.join();
        }
    }

    /// One step on the calling thread (slave activities only).
    pub(crate) fn step_slave(&self, runner: &dyn Runner) -> Result<(), ActivityError> {
        if self.shared.spec.has_thread() {
            return Err(ActivityError::NotSlave);
        }
        run_step(
            &self.shared,
            runner,
            &FdEvents::default(),
            StepTiming::now(),
        );
        Ok(())
    }
}

impl Drop for Activity {
    fn drop(&mut self) {
        self.stop();
    }
}

/// epoll data of the activity's own eventfd (`trigger`, stop).
const WAKE_EVENT: u64 = u64::MAX;

/// A non-blocking eventfd, registered with `epoll` as `data`.
fn eventfd_in(epoll: &Epoll, data: u64) -> Result<EventFd, ActivityError> {
    let fd = EventFd::from_flags(EfdFlags::EFD_CLOEXEC | EfdFlags::EFD_NONBLOCK)
        .map_err(ActivityError::fd("eventfd"))?;
    epoll
        .add(fd.as_fd(), EpollEvent::new(EpollFlags::EPOLLIN, data))
        .map_err(ActivityError::fd("epoll_ctl(eventfd)"))?;
    Ok(fd)
}
