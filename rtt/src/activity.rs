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

use crate::scope::{ThreadScope, set_thread_number};
use arc_swap::ArcSwapOption;
use device_interface::time::{Clock, MonotonicClock, Timestamp};
use nix::sys::epoll::{Epoll, EpollCreateFlags, EpollEvent, EpollFlags, EpollTimeout};
use nix::sys::eventfd::{EfdFlags, EventFd};
use nix::sys::timerfd::{ClockId, Expiration, TimerFd, TimerFlags, TimerSetTimeFlags};
use serde::{Deserialize, Serialize};
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, OwnedFd, RawFd};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::{JoinHandle, Thread};
use std::time::Duration;

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
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
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

impl ThreadOptions {
    /// Checks the options against what the system can do: a SCHED_FIFO priority of 1 to
    /// 99, CPUs this machine has.
    pub fn check(&self) -> Result<(), String> {
        if self.policy == SchedPolicy::Fifo && !(1..=99).contains(&self.priority) {
            return Err(format!(
                "priority {}: SCHED_FIFO takes 1 to 99",
                self.priority
            ));
        }
        let configured = cpus_configured();
        for &c in &self.cpus {
            if c >= configured {
                return Err(format!(
                    "cpu {c} does not exist (this machine has {configured}: 0..={})",
                    configured.saturating_sub(1)
                ));
            }
        }
        Ok(())
    }
}

/// CPUs this machine has configured (online or not).
fn cpus_configured() -> usize {
    match nix::unistd::sysconf(nix::unistd::SysconfVar::_NPROCESSORS_CONF) {
        Ok(Some(n)) if n > 0 => usize::try_from(n).unwrap_or(1),
        _ => std::thread::available_parallelism().map_or(1, usize::from),
    }
}

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
    #[error("{0}")]
    Thread(String),
    /// `wake_at` on an activity that is not a file-descriptor activity.
    #[error("only a file-descriptor activity wakes at a deadline")]
    NoDeadline,
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

/// Number of lateness histogram buckets: bucket `i` holds lateness in `[2^i, 2^(i+1))` ns.
pub const HISTOGRAM_BUCKETS: usize = 40;

/// A snapshot of an activity's statistics.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ActivityStats {
    /// Steps run.
    pub steps: u64,
    /// Wake-ups that came after the next one was due (periodic only).
    pub overruns: u64,
    /// Overruns in a row, now.
    pub consecutive_overruns: u64,
    /// False while consecutive overruns exceed the configured maximum.
    pub healthy: bool,
    /// Times it became unhealthy (so a watcher that looks now and then sees a spell that
    /// was over before it looked).
    #[serde(default)]
    pub unhealthy_spells: u64,
    /// Lateness histogram: bucket `i` counts wake-ups `2^i..2^(i+1)` ns late.
    pub lateness_histogram: Vec<u64>,
    /// Largest lateness seen, ns.
    pub lateness_max_ns: u64,
    /// Longest step, ns.
    pub step_max_ns: u64,
    /// Total time in steps, ns.
    pub step_total_ns: u64,
    /// True when the thread got the real-time class it asked for.
    pub realtime: bool,
}

impl ActivityStats {
    /// Mean step duration.
    pub fn step_mean(&self) -> Duration {
        Duration::from_nanos(self.step_total_ns.checked_div(self.steps).unwrap_or(0))
    }

    /// Upper bound of the lateness below which fraction `q` (0..=1) of the wake-ups fell.
    pub fn lateness_quantile(&self, q: f64) -> Duration {
        let total: u64 = self.lateness_histogram.iter().sum();
        if total == 0 {
            return Duration::ZERO;
        }
        let want = (q.clamp(0.0, 1.0) * total as f64).ceil() as u64;
        let mut seen = 0;
        for (i, n) in self.lateness_histogram.iter().enumerate() {
            seen += n;
            if seen >= want {
                return Duration::from_nanos((1u64 << (i + 1)).min(self.lateness_max_ns.max(1)));
            }
        }
        Duration::from_nanos(self.lateness_max_ns)
    }
}

struct StatsCell {
    steps: AtomicU64,
    overruns: AtomicU64,
    consecutive: AtomicU64,
    healthy: AtomicBool,
    spells: AtomicU64,
    histogram: [AtomicU64; HISTOGRAM_BUCKETS],
    lateness_max: AtomicU64,
    step_max: AtomicU64,
    step_total: AtomicU64,
    realtime: AtomicBool,
}

impl StatsCell {
    fn new() -> Self {
        StatsCell {
            steps: AtomicU64::new(0),
            overruns: AtomicU64::new(0),
            consecutive: AtomicU64::new(0),
            healthy: AtomicBool::new(true),
            spells: AtomicU64::new(0),
            histogram: std::array::from_fn(|_| AtomicU64::new(0)),
            lateness_max: AtomicU64::new(0),
            step_max: AtomicU64::new(0),
            step_total: AtomicU64::new(0),
            realtime: AtomicBool::new(false),
        }
    }

    fn lateness(&self, ns: u64) {
        let bucket = (63 - ns.max(1).leading_zeros() as usize).min(HISTOGRAM_BUCKETS - 1);
        self.histogram[bucket].fetch_add(1, Ordering::Relaxed);
        self.lateness_max.fetch_max(ns, Ordering::Relaxed);
    }

    fn step(&self, ns: u64) {
        self.steps.fetch_add(1, Ordering::Relaxed);
        self.step_total.fetch_add(ns, Ordering::Relaxed);
        self.step_max.fetch_max(ns, Ordering::Relaxed);
    }

    fn snapshot(&self) -> ActivityStats {
        ActivityStats {
            steps: self.steps.load(Ordering::Relaxed),
            overruns: self.overruns.load(Ordering::Relaxed),
            consecutive_overruns: self.consecutive.load(Ordering::Relaxed),
            healthy: self.healthy.load(Ordering::Relaxed),
            unhealthy_spells: self.spells.load(Ordering::Relaxed),
            lateness_histogram: self
                .histogram
                .iter()
                .map(|a| a.load(Ordering::Relaxed))
                .collect(),
            lateness_max_ns: self.lateness_max.load(Ordering::Relaxed),
            step_max_ns: self.step_max.load(Ordering::Relaxed),
            step_total_ns: self.step_total.load(Ordering::Relaxed),
            realtime: self.realtime.load(Ordering::Relaxed),
        }
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

/// What an activity steps.
pub(crate) trait Runner: Send + Sync {
    fn step(&self, events: &FdEvents, timing: StepTiming);
}

/// Wakes a parked thread: a flag, a short spin, then park/unpark.
struct Signal {
    pending: AtomicBool,
    woken_at: AtomicU64,
    thread: ArcSwapOption<Thread>,
    parked: AtomicBool,
}

impl Signal {
    fn new() -> Self {
        Signal {
            pending: AtomicBool::new(false),
            woken_at: AtomicU64::new(0),
            thread: ArcSwapOption::empty(),
            parked: AtomicBool::new(false),
        }
    }

    fn wait(&self) -> u64 {
        let backoff = crossbeam_utils::Backoff::new();
        loop {
            if self.pending.swap(false, Ordering::AcqRel) {
                return self.woken_at.swap(0, Ordering::AcqRel);
            }
            if backoff.is_completed() {
                self.parked.store(true, Ordering::SeqCst);
                if !self.pending.load(Ordering::SeqCst) {
                    std::thread::park();
                }
                self.parked.store(false, Ordering::SeqCst);
            } else {
                backoff.snooze();
            }
        }
    }

    fn notify(&self, now_ns: u64) {
        let _ =
            self.woken_at
                .compare_exchange(0, now_ns.max(1), Ordering::AcqRel, Ordering::Relaxed);
        self.pending.store(true, Ordering::SeqCst);
        if self.parked.load(Ordering::SeqCst)
            && let Some(t) = self.thread.load().as_deref()
        {
            t.unpark();
        }
    }
}

struct FdState {
    epoll: Epoll,
    wake: EventFd,
    /// One-shot deadline set by `wake_at` (absolute CLOCK_MONOTONIC).
    timer: TimerFd,
    /// (fd as the user knows it, our duplicate registered with epoll)
    watched: Mutex<Vec<(RawFd, OwnedFd)>>,
}

struct Shared {
    spec: ActivitySpec,
    name: String,
    thread_number: Option<u32>,
    running: AtomicBool,
    signal: Signal,
    fd: Option<FdState>,
    stats: StatsCell,
    scope: Arc<ThreadScope>,
}

impl Waker for Shared {
    fn wake(&self) {
        match &self.spec {
            ActivitySpec::NonPeriodic { .. } => self.signal.notify(MonotonicClock.now().as_nanos()),
            ActivitySpec::FileDescriptor { .. } => {
                if let Some(fd) = &self.fd {
                    let _ = fd.wake.write(1);
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
                let epoll = Epoll::new(EpollCreateFlags::EPOLL_CLOEXEC).map_err(|source| {
                    ActivityError::Fd {
                        what: "epoll_create",
                        source,
                    }
                })?;
                let wake = EventFd::from_flags(EfdFlags::EFD_CLOEXEC | EfdFlags::EFD_NONBLOCK)
                    .map_err(|source| ActivityError::Fd {
                        what: "eventfd",
                        source,
                    })?;
                epoll
                    .add(
                        wake.as_fd(),
                        EpollEvent::new(EpollFlags::EPOLLIN, WAKE_EVENT),
                    )
                    .map_err(|source| ActivityError::Fd {
                        what: "epoll_ctl(eventfd)",
                        source,
                    })?;
                let timer = TimerFd::new(
                    ClockId::CLOCK_MONOTONIC,
                    TimerFlags::TFD_NONBLOCK | TimerFlags::TFD_CLOEXEC,
                )
                .map_err(|source| ActivityError::Fd {
                    what: "timerfd_create",
                    source,
                })?;
                epoll
                    .add(
                        timer.as_fd(),
                        EpollEvent::new(EpollFlags::EPOLLIN, DEADLINE_EVENT),
                    )
                    .map_err(|source| ActivityError::Fd {
                        what: "epoll_ctl(timerfd)",
                        source,
                    })?;
                Some(FdState {
                    epoll,
                    wake,
                    timer,
                    watched: Mutex::new(Vec::new()),
                })
            }
            _ => None,
        };
        let thread_number = spec.has_thread().then(thread_number);
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
                name: name.to_string(),
                thread_number,
                running: AtomicBool::new(false),
                signal: Signal::new(),
                fd,
                stats: StatsCell::new(),
                scope,
            }),
            handle: Mutex::new(None),
        })
    }

    /// The activity's kind and parameters.
    pub fn spec(&self) -> &ActivitySpec {
        &self.shared.spec
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
            .map_err(|source| ActivityError::Fd {
                what: "epoll_ctl(add)",
                source,
            })?;
        crate::lock::lock(&state.watched).push((user, dup));
        Ok(())
    }

    /// Asks a file-descriptor activity for a step at `at` (the monotonic clock), replacing
    /// any deadline set before; a time already past steps at once. The step reports it with
    /// [`FdEvents::deadline_passed`]. One system call; callable from the activity's own step.
    pub fn wake_at(&self, at: Timestamp) -> Result<(), ActivityError> {
        let state = self.shared.fd.as_ref().ok_or(ActivityError::NoDeadline)?;
        // A zero it_value would disarm the timer: the earliest deadline is 1 ns.
        let ns = at.as_nanos().max(1);
        let ts = nix::sys::time::TimeSpec::new(
            (ns / 1_000_000_000) as libc::time_t,
            (ns % 1_000_000_000) as libc::c_long,
        );
        state
            .timer
            .set(
                Expiration::OneShot(ts),
                TimerSetTimeFlags::TFD_TIMER_ABSTIME,
            )
            .map_err(|source| ActivityError::Fd {
                what: "timerfd_settime",
                source,
            })
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
        if !self.shared.running.swap(false, Ordering::AcqRel) {
            return;
        }
        self.shared.wake();
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
        let clock = MonotonicClock;
        let t0 = clock.now();
        let timing = StepTiming {
            scheduled: t0,
            started: t0,
        };
        self.shared
            .scope
            .pulse(|| runner.step(&FdEvents::default(), timing));
        self.shared
            .stats
            .step(clock.now().duration_since(t0).as_nanos() as u64);
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
/// epoll data of the activity's deadline timer (`wake_at`).
const DEADLINE_EVENT: u64 = u64::MAX - 1;

static RT_WARNED: AtomicBool = AtomicBool::new(false);

/// Applies the thread options to the calling thread; true when SCHED_FIFO was granted.
fn apply_thread_options(name: &str, opts: &ThreadOptions) -> bool {
    if !opts.cpus.is_empty() {
        let mut set = nix::sched::CpuSet::new();
        for &c in &opts.cpus {
            if set.set(c).is_err() {
                tracing::warn!(
                    activity = name,
                    cpu = c,
                    "CPU {c} is beyond what this system can address; ignored"
                );
            }
        }
        if let Err(e) = nix::sched::sched_setaffinity(nix::unistd::Pid::from_raw(0), &set) {
            tracing::warn!(activity = name, cpus = ?opts.cpus, "could not pin the thread to CPUs {:?}: {e}", opts.cpus);
        }
    }
    if opts.policy != SchedPolicy::Fifo {
        return false;
    }
    match set_fifo(opts.priority) {
        Ok(()) => true,
        Err(e) => {
            if !RT_WARNED.swap(true, Ordering::Relaxed) {
                tracing::warn!(
                    activity = name,
                    priority = opts.priority,
                    "SCHED_FIFO at priority {} is not available ({e}); running SCHED_OTHER. \
                     Real-time scheduling needs CAP_SYS_NICE or an RLIMIT_RTPRIO of at least \
                     the priority (systemd: LimitRTPRIO=, AmbientCapabilities=CAP_SYS_NICE).",
                    opts.priority
                );
            }
            false
        }
    }
}

#[allow(unsafe_code)]
fn set_fifo(priority: i32) -> std::io::Result<()> {
    let param = libc::sched_param {
        sched_priority: priority,
    };
    // SAFETY: pthread_self() is the calling thread, and `param` is a valid sched_param
    // that outlives the call.
    let rc = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &param) };
    if rc == 0 {
        Ok(())
    } else {
        Err(std::io::Error::from_raw_os_error(rc))
    }
}

fn thread_main(shared: Arc<Shared>, runner: Arc<dyn Runner>) {
    if let Some(n) = shared.thread_number {
        set_thread_number(n);
    }
    let clock = MonotonicClock;
    let stats = &shared.stats;
    match &shared.spec {
        ActivitySpec::Periodic {
            period,
            thread,
            timing,
            max_overruns,
        } => {
            stats.realtime.store(
                apply_thread_options(&shared.name, thread),
                Ordering::Relaxed,
            );
            let period_ns = u64::try_from(period.as_nanos()).unwrap_or(u64::MAX);
            let mut next = clock.now().as_nanos();
            let events = FdEvents::default();
            let mut unhealthy_logged = false;
            while shared.running.load(Ordering::Acquire) {
                sleep_until_or_stopped(next, &shared.running);
                if !shared.running.load(Ordering::Acquire) {
                    break;
                }
                let woke = clock.now().as_nanos();
                stats.lateness(woke.saturating_sub(next));
                let step_timing = StepTiming {
                    scheduled: Timestamp::from_nanos(next),
                    started: Timestamp::from_nanos(woke),
                };
                shared.scope.pulse(|| runner.step(&events, step_timing));
                let end = clock.now().as_nanos();
                stats.step(end.saturating_sub(woke));
                next = match timing {
                    Timing::Absolute => next.saturating_add(period_ns),
                    Timing::Relative => woke.saturating_add(period_ns),
                };
                if end > next {
                    stats.overruns.fetch_add(1, Ordering::Relaxed);
                    let run = stats.consecutive.fetch_add(1, Ordering::Relaxed) + 1;
                    if let Timing::Absolute = timing {
                        // Skip the wake-ups already missed, keeping the grid.
                        let missed = (end - next) / period_ns + 1;
                        next = next.saturating_add(missed.saturating_mul(period_ns));
                    }
                    if max_overruns.is_some_and(|m| run > u64::from(m)) {
                        if stats.healthy.swap(false, Ordering::Relaxed) {
                            stats.spells.fetch_add(1, Ordering::Relaxed);
                        }
                        if !unhealthy_logged {
                            unhealthy_logged = true;
                            tracing::error!(activity = %shared.name, overruns = run, "{} overruns in a row: activity unhealthy", run);
                        }
                    }
                } else {
                    stats.consecutive.store(0, Ordering::Relaxed);
                    if !stats.healthy.swap(true, Ordering::Relaxed) {
                        unhealthy_logged = false;
                        tracing::info!(activity = %shared.name, "on time again: activity healthy");
                    }
                }
            }
        }
        ActivitySpec::NonPeriodic { thread } => {
            stats.realtime.store(
                apply_thread_options(&shared.name, thread),
                Ordering::Relaxed,
            );
            let events = FdEvents::default();
            loop {
                let woken_at = shared.signal.wait();
                if !shared.running.load(Ordering::Acquire) {
                    break;
                }
                let start = clock.now().as_nanos();
                if woken_at != 0 {
                    stats.lateness(start.saturating_sub(woken_at));
                }
                let timing = StepTiming {
                    scheduled: Timestamp::from_nanos(if woken_at == 0 { start } else { woken_at }),
                    started: Timestamp::from_nanos(start),
                };
                shared.scope.pulse(|| runner.step(&events, timing));
                stats.step(clock.now().as_nanos().saturating_sub(start));
            }
        }
        ActivitySpec::FileDescriptor { timeout, thread } => {
            stats.realtime.store(
                apply_thread_options(&shared.name, thread),
                Ordering::Relaxed,
            );
            let Some(fd) = &shared.fd else { return };
            let epoll_timeout = match timeout {
                None => EpollTimeout::NONE,
                Some(t) => EpollTimeout::try_from(*t).unwrap_or(EpollTimeout::MAX),
            };
            let mut ready = [EpollEvent::empty(); FdEvents::MAX];
            while shared.running.load(Ordering::Acquire) {
                let n = match fd.epoll.wait(&mut ready, epoll_timeout) {
                    Ok(n) => n,
                    Err(nix::Error::EINTR) => continue,
                    Err(e) => {
                        tracing::error!(activity = %shared.name, "epoll_wait failed: {e}; activity stops");
                        break;
                    }
                };
                if !shared.running.load(Ordering::Acquire) {
                    break;
                }
                let mut events = FdEvents {
                    timeout: n == 0,
                    ..FdEvents::default()
                };
                for ev in &ready[..n] {
                    if ev.data() == WAKE_EVENT {
                        let _ = fd.wake.read();
                    } else if ev.data() == DEADLINE_EVENT {
                        // Reading clears the expiry; a re-armed timer may already be unread.
                        let _ = fd.timer.wait();
                        events.deadline = true;
                    } else if events.count < FdEvents::MAX {
                        events.ready[events.count] = ev.data() as RawFd;
                        events.count += 1;
                    }
                }
                let start = clock.now().as_nanos();
                let timing = StepTiming::now();
                shared.scope.pulse(|| runner.step(&events, timing));
                stats.step(clock.now().as_nanos().saturating_sub(start));
            }
        }
        ActivitySpec::Slave => {}
    }
}

/// Longest uninterrupted sleep of a periodic activity: a stop is seen within this long
/// whatever the period (a period of a day must not make a stop wait a day).
const STOP_SLICE_NS: u64 = 50_000_000;

/// Sleeps until `ns` on the monotonic clock, in slices of at most [`STOP_SLICE_NS`],
/// returning early once `running` is cleared. A wake-up within a slice of `ns` is the same
/// single absolute sleep as ever.
fn sleep_until_or_stopped(ns: u64, running: &AtomicBool) {
    loop {
        let now = MonotonicClock.now().as_nanos();
        if now >= ns {
            return;
        }
        let until = ns.min(now.saturating_add(STOP_SLICE_NS));
        sleep_until(until);
        if until == ns || !running.load(Ordering::Acquire) {
            return;
        }
    }
}

fn sleep_until(ns: u64) {
    let ts = nix::sys::time::TimeSpec::new(
        (ns / 1_000_000_000) as libc::time_t,
        (ns % 1_000_000_000) as libc::c_long,
    );
    loop {
        match nix::time::clock_nanosleep(
            nix::time::ClockId::CLOCK_MONOTONIC,
            nix::time::ClockNanosleepFlags::TIMER_ABSTIME,
            &ts,
        ) {
            Err(nix::Error::EINTR) => continue,
            _ => return,
        }
    }
}
