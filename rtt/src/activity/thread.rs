//! The loop of an activity's own thread, per kind: the periodic grid slept on with
//! `clock_nanosleep`, the non-periodic wait for a trigger, the file-descriptor epoll wait;
//! and the signal that wakes a non-periodic thread.

use super::deadline::{ASK_EVENT, DEADLINE_EVENT};
use super::realtime::{apply_thread_options, prepare_periodic};
use super::{
    ActivityError, ActivitySpec, FdEvents, FdState, Runner, Shared, StepTiming, Timing, WAKE_EVENT,
    run_step,
};
use crate::scope::set_thread_number;
use arc_swap::ArcSwapOption;
use device_interface::time::{Clock, MonotonicClock, Timestamp};
use nix::sys::epoll::EpollEvent;
use std::os::fd::RawFd;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::Thread;
use std::time::Duration;

/// Wakes a parked thread: a flag, a bounded spin, then park/unpark.
pub(super) struct Signal {
    pending: AtomicBool,
    woken_at: AtomicU64,
    pub(super) thread: ArcSwapOption<Thread>,
    parked: AtomicBool,
}

impl Signal {
    pub(super) fn new() -> Self {
        Signal {
            pending: AtomicBool::new(false),
            woken_at: AtomicU64::new(0),
            thread: ArcSwapOption::empty(),
            parked: AtomicBool::new(false),
        }
    }

    /// Waits for a notify: spins for `spin` (a trigger within it is seen at once, no
    /// scheduler wake-up), then parks. Returns when the notify was sent (0: unknown).
    fn wait(&self, spin: Duration) -> u64 {
        loop {
            if self.pending.swap(false, Ordering::AcqRel) {
                return self.woken_at.swap(0, Ordering::AcqRel);
            }
            // A thread this one just woke may be scheduled on this CPU: no spin then.
            let spin = if crate::spin::take_woke_another() {
                Duration::ZERO
            } else {
                spin
            };
            if crate::spin::spin_until(spin, || self.pending.load(Ordering::Relaxed)) {
                continue;
            }
            self.parked.store(true, Ordering::SeqCst);
            if !self.pending.load(Ordering::SeqCst) {
                std::thread::park();
            }
            self.parked.store(false, Ordering::SeqCst);
        }
    }

    /// Wakes the thread: at once when it is stepping or spinning, through the scheduler
    /// when it has parked.
    pub(super) fn notify(&self, now_ns: u64) {
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

pub(super) fn thread_main(shared: Arc<Shared>, runner: Arc<dyn Runner>) {
    if let Some(n) = shared.thread_number {
        set_thread_number(n);
    }
    let clock = MonotonicClock;
    let stats = &shared.stats;
    // A restart left by a step that unwound is not this thread's.
    shared.restarted.store(0, Ordering::Relaxed);
    stats.taps.warm();
    let changed = crate::lock::lock(&shared.changed).clone();
    match changed.as_ref().unwrap_or(&shared.spec) {
        ActivitySpec::Periodic {
            period,
            thread,
            timing,
            max_overruns,
        } => {
            let realtime = apply_thread_options(&shared.name, thread);
            stats.realtime.store(realtime, Ordering::Relaxed);
            stats
                .memory_locked
                .store(prepare_periodic(&shared.name, realtime), Ordering::Relaxed);
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
                let end = run_step(&shared, runner.as_ref(), &events, step_timing);
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
                        stats.spells.unhealthy(end);
                        if !unhealthy_logged {
                            unhealthy_logged = true;
                            crate::rt_log!(
                                shared.log,
                                Error,
                                "{} overruns in a row: activity unhealthy",
                                run
                            );
                        }
                    }
                } else {
                    stats.consecutive.store(0, Ordering::Relaxed);
                    if stats.spells.healthy_again(end) {
                        unhealthy_logged = false;
                        crate::rt_log!(shared.log, Info, "on time again: activity healthy");
                    }
                }
            }
            // A stopped activity is not overrunning: a spell on at the stop ends there (its
            // time would else run on until the next start's first step on time).
            stats.spells.healthy_again(clock.now().as_nanos());
        }
        ActivitySpec::NonPeriodic { thread } => {
            stats.realtime.store(
                apply_thread_options(&shared.name, thread),
                Ordering::Relaxed,
            );
            let events = FdEvents::default();
            let spin = Duration::from_micros(u64::from(thread.spin_us));
            let spin_ns = u64::try_from(spin.as_nanos()).unwrap_or(u64::MAX);
            // Adaptive: the thread spins after a step only while triggers come within the
            // spin of the step before ending (calls back to back); a trigger after a longer
            // gap found it parked, and it parks at once after that step (a thread it wakes
            // then, such as a parked caller, may need this CPU).
            let mut hot = false;
            let mut last_end = 0u64;
            loop {
                let woken_at = shared.signal.wait(if hot { spin } else { Duration::ZERO });
                if !shared.running.load(Ordering::Acquire) {
                    break;
                }
                let start = clock.now().as_nanos();
                if woken_at != 0 {
                    stats.lateness(start.saturating_sub(woken_at));
                }
                hot = woken_at != 0 && woken_at.saturating_sub(last_end) < spin_ns;
                let timing = StepTiming {
                    scheduled: Timestamp::from_nanos(if woken_at == 0 { start } else { woken_at }),
                    started: Timestamp::from_nanos(start),
                };
                last_end = run_step(&shared, runner.as_ref(), &events, timing);
            }
        }
        ActivitySpec::FileDescriptor { timeout, thread } => {
            stats.realtime.store(
                apply_thread_options(&shared.name, thread),
                Ordering::Relaxed,
            );
            let Some(fd) = &shared.fd else { return };
            let timeout = timeout.map(|t| u64::try_from(t.as_nanos()).unwrap_or(u64::MAX));
            fd_loop(&shared, runner.as_ref(), fd, timeout);
        }
        ActivitySpec::Slave => {}
    }
}

/// The loop of a file-descriptor activity's thread: wait in epoll (not at all when the
/// step before asked for a time already past), step, apply the deadline the step asked
/// for (see the `deadline` module).
fn fd_loop(shared: &Shared, runner: &dyn Runner, fd: &FdState, timeout: Option<u64>) {
    let failed = |e: &ActivityError| {
        crate::rt_log!(
            shared.log,
            Error,
            "the activity's deadline could not be set: {}; activity stops",
            crate::log::Arg::display(e)
        );
    };
    let mut ready = [EpollEvent::empty(); FdEvents::MAX];
    fd.deadline
        .enter_thread(shared.stats.realtime.load(Ordering::Relaxed));
    let mut at_once = false;
    while shared.running.load(Ordering::Acquire) {
        let watching = fd.watching.load(Ordering::Acquire) > 0;
        let waited = match fd
            .deadline
            .wait(&fd.epoll, &mut ready, timeout, at_once, watching)
        {
            Ok(w) => w,
            Err(ActivityError::Fd {
                source: nix::Error::EINTR,
                ..
            }) => continue,
            Err(e) => {
                crate::rt_log!(
                    shared.log,
                    Error,
                    "the activity's wait failed: {}; activity stops",
                    crate::log::Arg::display(&e)
                );
                break;
            }
        };
        if !shared.running.load(Ordering::Acquire) {
            break;
        }
        let n = waited.n;
        let mut events = FdEvents {
            timeout: waited.timeout,
            deadline: waited.deadline,
            ..FdEvents::default()
        };
        // A wake-up that only brought another thread's deadline for later is no step.
        let mut step = waited.timeout || waited.deadline;
        for ev in &ready[..n] {
            match ev.data() {
                WAKE_EVENT => {
                    let _ = fd.wake.read();
                    step = true;
                }
                DEADLINE_EVENT => {
                    fd.deadline.fired();
                    events.deadline = true;
                    step = true;
                }
                ASK_EVENT => match fd.deadline.take_asked(MonotonicClock.now().as_nanos()) {
                    Ok(due) => {
                        events.deadline |= due;
                        step |= due;
                    }
                    Err(e) => return failed(&e),
                },
                user => {
                    if events.count < FdEvents::MAX {
                        events.ready[events.count] = user as RawFd;
                        events.count += 1;
                    }
                    step = true;
                }
            }
        }
        if !step {
            continue;
        }
        // One clock read for the step's start and its timing.
        let ended = run_step(shared, runner, &events, StepTiming::now());
        at_once = match fd.deadline.after_step(ended) {
            Ok(at_once) => at_once,
            Err(e) => return failed(&e),
        };
    }
    if at_once && let Err(e) = fd.deadline.keep_for_restart() {
        failed(&e);
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
