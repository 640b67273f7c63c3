//! An activity's steps as they happen, for recorders: each step's due time, start and
//! end, pushed by the activity's thread into the bounded queue of every [`StepTap`] taken
//! with [`Activity::tap_steps`](super::Activity::tap_steps).
//!
//! Real-time contract: with no tap, a step costs one relaxed load; with taps, one
//! lock-free load of the tap list and one bounded queue push per tap. A full queue drops
//! the step and counts it ([`StepTap::dropped`]); the activity's thread never waits for a
//! reader and never allocates.

use crate::lock::lock;
use arc_swap::ArcSwap;
use crossbeam_queue::ArrayQueue;
use device_interface::time::{Clock, MonotonicClock};
use std::cell::Cell;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// One step of an activity, in ns on the monotonic clock.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct StepRecord {
    /// When it was due (the periodic grid point, the wake-up request; for file-descriptor
    /// and slave activities its start).
    pub scheduled: u64,
    /// When it began.
    pub started: u64,
    /// When it ended.
    pub ended: u64,
}

impl StepRecord {
    /// How late it began, ns.
    pub fn lateness_ns(&self) -> u64 {
        self.started.saturating_sub(self.scheduled)
    }

    /// How long it took, ns.
    pub fn duration_ns(&self) -> u64 {
        self.ended.saturating_sub(self.started)
    }
}

thread_local! {
    /// The start of the step this thread is running (monotonic ns), 0 outside a step.
    static STEP_START: Cell<u64> = const { Cell::new(0) };
    /// The activity whose step this thread is running (its key), 0 outside a step.
    static STEP_OWNER: Cell<u64> = const { Cell::new(0) };
}

/// Runs `f` as the step of activity `owner` (a key no other live activity has, never 0)
/// that began at `started` (monotonic ns): what it writes to stamped connections takes
/// that time, and what it appends to a journal goes to its activity's lane. A step run
/// inside another (a slave stepped from a hook) gives the outer step its time and owner
/// back after.
#[inline]
pub(crate) fn in_step<R>(started: u64, owner: u64, f: impl FnOnce() -> R) -> R {
    let outer = STEP_START.replace(started.max(1));
    let outer_owner = STEP_OWNER.replace(owner);
    let r = f();
    STEP_START.set(outer);
    STEP_OWNER.set(outer_owner);
    r
}

/// The step this thread is running counts from `at` (monotonic ns, not 0) from now on:
/// what it writes to stamped connections takes that time (see
/// [`Activity::restart_step`](super::Activity::restart_step)).
pub(crate) fn restart_step_clock(at: u64) {
    if STEP_START.get() != 0 {
        STEP_START.set(at);
    }
}

/// The activity whose step this thread is running (see [`in_step`]), 0 outside a step. An
/// activity's steps never overlap, whatever thread runs them: a journal lane keyed by it
/// has one writer at a time, across restarts too.
#[inline]
pub(crate) fn step_owner() -> u64 {
    STEP_OWNER.get()
}

/// The time a sample written now is stamped with (monotonic ns): the start of the step
/// this thread is running — the one clock read the step made, so a step's samples share
/// their step's time and a write costs no clock read — or, outside any step (a control
/// client's write), the monotonic clock now.
#[inline]
pub fn stamp_now() -> u64 {
    match STEP_START.get() {
        0 => MonotonicClock.now().as_nanos(),
        t => t,
    }
}

/// The most steps one tap holds (each 24 bytes, allocated when the tap is taken).
pub const MAX_TAP: usize = 1 << 20;

struct Log {
    queue: ArrayQueue<StepRecord>,
    dropped: AtomicU64,
}

/// The taps of one activity.
pub(crate) struct StepTaps {
    any: AtomicBool,
    logs: ArcSwap<Vec<Arc<Log>>>,
    /// Serialises taking and dropping taps (never touched by the activity's thread), and
    /// holds the lists replaced, each freed at a later edit once no reader holds it: the
    /// activity's thread never frees a list or a tap's queue.
    edit: Mutex<Vec<Arc<Vec<Arc<Log>>>>>,
}

impl StepTaps {
    pub(crate) fn new() -> Self {
        StepTaps {
            any: AtomicBool::new(false),
            logs: ArcSwap::from_pointee(Vec::new()),
            edit: Mutex::new(Vec::new()),
        }
    }

    /// The activity's thread, before its first step: what loading the list first costs
    /// (arc-swap's per-thread slot) is paid here, not in a step.
    pub(crate) fn warm(&self) {
        drop(self.logs.load());
    }

    /// The activity's thread, after each step.
    #[inline]
    pub(crate) fn push(&self, record: StepRecord) {
        if !self.any.load(Ordering::Relaxed) {
            return;
        }
        for log in self.logs.load().iter() {
            if log.queue.push(record).is_err() {
                log.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    fn edit(&self, f: impl FnOnce(&mut Vec<Arc<Log>>)) {
        let mut retired = lock(&self.edit);
        let mut logs = self.logs.load().as_ref().clone();
        f(&mut logs);
        self.any.store(!logs.is_empty(), Ordering::Relaxed);
        retired.push(self.logs.swap(Arc::new(logs)));
        retired.retain(|old| Arc::strong_count(old) > 1);
    }
}

/// Receives an activity's steps from when it was taken until it is dropped.
pub struct StepTap {
    log: Arc<Log>,
    taps: Arc<StepTaps>,
}

impl StepTap {
    pub(crate) fn new(taps: &Arc<StepTaps>, capacity: usize) -> StepTap {
        let log = Arc::new(Log {
            queue: ArrayQueue::new(capacity.clamp(1, MAX_TAP)),
            dropped: AtomicU64::new(0),
        });
        taps.edit(|logs| logs.push(log.clone()));
        StepTap {
            log,
            taps: taps.clone(),
        }
    }

    /// Moves the steps received since the last call into `out`, oldest first.
    pub fn drain(&self, out: &mut Vec<StepRecord>) {
        while let Some(r) = self.log.queue.pop() {
            out.push(r);
        }
    }

    /// Steps lost so far because the tap was full.
    pub fn dropped(&self) -> u64 {
        self.log.dropped.load(Ordering::Relaxed)
    }
}

impl Drop for StepTap {
    fn drop(&mut self) {
        let log = self.log.clone();
        self.taps
            .edit(|logs| logs.retain(|l| !Arc::ptr_eq(l, &log)));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tap_receives_steps_until_dropped_and_counts_what_did_not_fit() {
        let taps = Arc::new(StepTaps::new());
        let step = |n| StepRecord {
            scheduled: n,
            started: n + 1,
            ended: n + 3,
        };
        taps.push(step(0));
        let tap = StepTap::new(&taps, 2);
        for n in 1..=3 {
            taps.push(step(n * 10));
        }
        let mut got = Vec::new();
        tap.drain(&mut got);
        assert_eq!(got, vec![step(10), step(20)]);
        assert_eq!(tap.dropped(), 1);
        assert_eq!((got[0].lateness_ns(), got[0].duration_ns()), (1, 2));
        drop(tap);
        assert!(!taps.any.load(Ordering::Relaxed));
        assert!(taps.logs.load().is_empty());
    }
}
