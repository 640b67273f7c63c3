//! An activity's unhealthy spells and the time they took, kept by its thread at each change
//! of health and read by any thread.
//!
//! The thread writes only at a spell's start and end, under a sequence number (odd while
//! it writes: plain stores, no read-modify-write but the spell count), so a reader takes the
//! health, the spell's start and the time of the spells that are over as one consistent
//! set, and counts a spell neither twice nor not at all. A reader that finds the thread in
//! the middle of a change [`TRIES`] times running (the thread preempted there) reports what
//! readers reported last. What is reported never goes down (a Prometheus counter): a
//! reader's clock read can fall after the thread took a spell's end but before it wrote it.

use crossbeam_utils::CachePadded;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering, fence};

/// Looks a reader makes before it reports what was reported last.
const TRIES: usize = 64;

pub(crate) struct Spells {
    /// Odd while the activity's thread changes the fields below.
    seq: AtomicU64,
    healthy: AtomicBool,
    /// When the current spell began (ns, monotonic clock), valid while unhealthy.
    since: AtomicU64,
    /// The spells that are over, ns.
    total: AtomicU64,
    count: AtomicU64,
    /// The most any reader reported (readers write it: a line of its own).
    reported: CachePadded<AtomicU64>,
}

/// What a reader sees.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct SpellsNow {
    pub(crate) healthy: bool,
    pub(crate) count: u64,
    /// Time spent unhealthy up to the read, ns.
    pub(crate) unhealthy_ns: u64,
}

impl Spells {
    pub(crate) fn new() -> Self {
        Spells {
            seq: AtomicU64::new(0),
            healthy: AtomicBool::new(true),
            since: AtomicU64::new(0),
            total: AtomicU64::new(0),
            count: AtomicU64::new(0),
            reported: CachePadded::new(AtomicU64::new(0)),
        }
    }

    /// The activity's thread (the only writer) changes the fields in `f`.
    fn write(&self, f: impl FnOnce()) {
        let s = self.seq.load(Ordering::Relaxed);
        self.seq.store(s.wrapping_add(1), Ordering::Relaxed);
        fence(Ordering::Release);
        f();
        self.seq.store(s.wrapping_add(2), Ordering::Release);
    }

    /// The activity's thread found it unhealthy at `at` (ns, monotonic clock): a spell
    /// begins unless one is on (true when it does).
    pub(crate) fn unhealthy(&self, at: u64) -> bool {
        if !self.healthy.load(Ordering::Relaxed) {
            return false;
        }
        self.write(|| {
            self.since.store(at, Ordering::Relaxed);
            self.healthy.store(false, Ordering::Relaxed);
            self.count
                .store(self.count.load(Ordering::Relaxed) + 1, Ordering::Relaxed);
        });
        true
    }

    /// The activity's thread found it healthy at `at` (on time again, or stopping): the
    /// spell on, if any, ends (true when one did).
    pub(crate) fn healthy_again(&self, at: u64) -> bool {
        if self.healthy.load(Ordering::Relaxed) {
            return false;
        }
        self.write(|| {
            let took = at.saturating_sub(self.since.load(Ordering::Relaxed));
            let total = self.total.load(Ordering::Relaxed).saturating_add(took);
            self.total.store(total, Ordering::Relaxed);
            self.healthy.store(true, Ordering::Relaxed);
        });
        true
    }

    /// The spells up to `now` (ns, monotonic clock), from any thread.
    pub(crate) fn read(&self, now: u64) -> SpellsNow {
        for _ in 0..TRIES {
            let s1 = self.seq.load(Ordering::Acquire);
            if s1 % 2 == 1 {
                std::hint::spin_loop();
                continue;
            }
            let healthy = self.healthy.load(Ordering::Relaxed);
            let since = self.since.load(Ordering::Relaxed);
            let total = self.total.load(Ordering::Relaxed);
            let count = self.count.load(Ordering::Relaxed);
            fence(Ordering::Acquire);
            if self.seq.load(Ordering::Relaxed) != s1 {
                continue;
            }
            let time = if healthy {
                total
            } else {
                total.saturating_add(now.saturating_sub(since))
            };
            let before = self.reported.fetch_max(time, Ordering::Relaxed);
            return SpellsNow {
                healthy,
                count,
                unhealthy_ns: time.max(before),
            };
        }
        SpellsNow {
            healthy: self.healthy.load(Ordering::Relaxed),
            count: self.count.load(Ordering::Relaxed),
            unhealthy_ns: self.reported.load(Ordering::Relaxed),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_spell_counts_while_on_and_once_over() {
        let s = Spells::new();
        assert_eq!(s.read(5).unhealthy_ns, 0);
        assert!(s.unhealthy(10));
        assert!(!s.unhealthy(12), "one spell at a time");
        let on = s.read(25);
        assert_eq!((on.healthy, on.count, on.unhealthy_ns), (false, 1, 15));
        assert!(s.healthy_again(30));
        assert!(!s.healthy_again(31));
        let over = s.read(100);
        assert_eq!((over.healthy, over.count, over.unhealthy_ns), (true, 1, 20));
        assert!(s.unhealthy(200));
        assert_eq!(s.read(205).unhealthy_ns, 25);
        assert_eq!(s.read(205).count, 2);
    }

    #[test]
    fn what_is_reported_never_goes_down() {
        let s = Spells::new();
        s.unhealthy(10);
        // A reader whose clock read came after the spell's end the thread took (40).
        assert_eq!(s.read(50).unhealthy_ns, 40);
        s.healthy_again(40);
        assert_eq!(s.read(60).unhealthy_ns, 40);
    }
}
