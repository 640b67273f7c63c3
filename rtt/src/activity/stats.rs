//! An activity's timing statistics: steps, a histogram of wake-up lateness, step
//! durations and overruns, kept in atomics by the activity's thread and read as a snapshot.

use super::steps::{StepRecord, StepTaps};
use serde::{Deserialize, Serialize};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

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
    /// Time spent unhealthy, ns: the spells that are over and the current one up to the
    /// snapshot; never less than an earlier snapshot's. A watcher's share of unhealthy
    /// time between two looks.
    #[serde(default)]
    pub unhealthy_ns: u64,
    /// Lateness histogram: bucket `i` counts wake-ups `2^i..2^(i+1)` ns late.
    pub lateness_histogram: Vec<u64>,
    /// Largest lateness seen, ns.
    pub lateness_max_ns: u64,
    /// Sum of every wake-up's lateness, ns (with the histogram's count, its mean).
    #[serde(default)]
    pub lateness_total_ns: u64,
    /// Step duration histogram: bucket `i` counts steps that took `2^i..2^(i+1)` ns.
    #[serde(default)]
    pub step_histogram: Vec<u64>,
    /// Longest step, ns.
    pub step_max_ns: u64,
    /// Total time in steps, ns.
    pub step_total_ns: u64,
    /// True when the thread got the real-time class it asked for.
    pub realtime: bool,
    /// True when the process's memory is locked (a periodic SCHED_FIFO activity locks it;
    /// see the activity module).
    #[serde(default)]
    pub memory_locked: bool,
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

/// The histogram bucket of `ns`: `i` with `2^i <= ns < 2^(i+1)` (0 and 1 in bucket 0),
/// the last bucket taking everything beyond.
fn bucket(ns: u64) -> usize {
    (63 - ns.max(1).leading_zeros() as usize).min(HISTOGRAM_BUCKETS - 1)
}

pub(crate) struct StatsCell {
    pub(crate) steps: AtomicU64,
    pub(crate) overruns: AtomicU64,
    pub(crate) consecutive: AtomicU64,
    /// Health, its unhealthy spells and their time.
    pub(crate) spells: super::spells::Spells,
    pub(crate) histogram: [AtomicU64; HISTOGRAM_BUCKETS],
    pub(crate) lateness_max: AtomicU64,
    pub(crate) lateness_total: AtomicU64,
    pub(crate) step_histogram: [AtomicU64; HISTOGRAM_BUCKETS],
    pub(crate) step_max: AtomicU64,
    pub(crate) step_total: AtomicU64,
    pub(crate) realtime: AtomicBool,
    pub(crate) memory_locked: AtomicBool,
    pub(crate) taps: Arc<StepTaps>,
}

impl StatsCell {
    pub(crate) fn new() -> Self {
        StatsCell {
            steps: AtomicU64::new(0),
            overruns: AtomicU64::new(0),
            consecutive: AtomicU64::new(0),
            spells: super::spells::Spells::new(),
            histogram: std::array::from_fn(|_| AtomicU64::new(0)),
            lateness_max: AtomicU64::new(0),
            lateness_total: AtomicU64::new(0),
            step_histogram: std::array::from_fn(|_| AtomicU64::new(0)),
            step_max: AtomicU64::new(0),
            step_total: AtomicU64::new(0),
            realtime: AtomicBool::new(false),
            memory_locked: AtomicBool::new(false),
            taps: Arc::new(StepTaps::new()),
        }
    }

    pub(crate) fn lateness(&self, ns: u64) {
        self.histogram[bucket(ns)].fetch_add(1, Ordering::Relaxed);
        self.lateness_max.fetch_max(ns, Ordering::Relaxed);
        self.lateness_total.fetch_add(ns, Ordering::Relaxed);
    }

    /// A step that was due at `scheduled`, began at `started` and ended at `ended` (ns on
    /// the monotonic clock): counted, and given to the step taps.
    pub(crate) fn step(&self, scheduled: u64, started: u64, ended: u64) {
        let ns = ended.saturating_sub(started);
        self.taps.push(StepRecord {
            scheduled,
            started,
            ended,
        });
        self.steps.fetch_add(1, Ordering::Relaxed);
        self.step_total.fetch_add(ns, Ordering::Relaxed);
        self.step_max.fetch_max(ns, Ordering::Relaxed);
        self.step_histogram[bucket(ns)].fetch_add(1, Ordering::Relaxed);
    }

    pub(crate) fn snapshot(&self) -> ActivityStats {
        use device_interface::time::{Clock, MonotonicClock};
        let spells = self.spells.read(MonotonicClock.now().as_nanos());
        ActivityStats {
            steps: self.steps.load(Ordering::Relaxed),
            overruns: self.overruns.load(Ordering::Relaxed),
            consecutive_overruns: self.consecutive.load(Ordering::Relaxed),
            healthy: spells.healthy,
            unhealthy_spells: spells.count,
            unhealthy_ns: spells.unhealthy_ns,
            lateness_histogram: self
                .histogram
                .iter()
                .map(|a| a.load(Ordering::Relaxed))
                .collect(),
            lateness_max_ns: self.lateness_max.load(Ordering::Relaxed),
            lateness_total_ns: self.lateness_total.load(Ordering::Relaxed),
            step_histogram: self
                .step_histogram
                .iter()
                .map(|a| a.load(Ordering::Relaxed))
                .collect(),
            step_max_ns: self.step_max.load(Ordering::Relaxed),
            step_total_ns: self.step_total.load(Ordering::Relaxed),
            realtime: self.realtime.load(Ordering::Relaxed),
            memory_locked: self.memory_locked.load(Ordering::Relaxed),
        }
    }
}
