//! A file-descriptor activity's deadline ([`Activity::wake_at`](super::Activity::wake_at)):
//! a one-shot `timerfd` in the activity's epoll set, armed only when a wait needs it.
//!
//! A deadline asked for from another thread arms the timer at once (one system call). One
//! asked for from the activity's own step — a bus line scheduling its next poll — is noted
//! and applied by the thread when the step ends:
//!
//! - a time already past: the next step follows at once, after an `epoll_wait` that does
//!   not wait (to take up descriptors that became ready). No timer is armed, fired and read:
//!   one system call where there were three, so a line polling back to back costs what its
//!   own I/O costs. A timer still armed for a later time is disarmed first, as "replaces any
//!   deadline set before" says.
//! - a time to come: the timer is armed unless it is armed for that time already (a step
//!   woken by a descriptor or a trigger that asks for the same next poll costs no call).

use super::ActivityError;
use nix::sys::time::TimeSpec;
use nix::sys::timerfd::{ClockId, Expiration, TimerFd, TimerFlags, TimerSetTimeFlags};
use std::cell::Cell;
use std::sync::atomic::{AtomicU64, Ordering};

thread_local! {
    /// The deadline of the activity whose thread this is (its address; 0: none).
    static OWN: Cell<usize> = const { Cell::new(0) };
}

pub(super) struct Deadline {
    pub(super) timer: TimerFd,
    /// The time the timer is armed for (monotonic ns; 0: not armed).
    armed: AtomicU64,
    /// The deadline the activity's own step asked for, applied when the step ends (ns; 0:
    /// none). Only the activity's thread touches it.
    noted: AtomicU64,
}

impl Deadline {
    pub(super) fn new() -> Result<Self, ActivityError> {
        let timer = TimerFd::new(
            ClockId::CLOCK_MONOTONIC,
            TimerFlags::TFD_NONBLOCK | TimerFlags::TFD_CLOEXEC,
        )
        .map_err(|source| ActivityError::Fd {
            what: "timerfd_create",
            source,
        })?;
        Ok(Deadline {
            timer,
            armed: AtomicU64::new(0),
            noted: AtomicU64::new(0),
        })
    }

    fn key(&self) -> usize {
        self as *const Self as usize
    }

    /// Marks the calling thread as the activity's own: its `wake_at` calls are noted.
    pub(super) fn enter_thread(&self) {
        OWN.with(|o| o.set(self.key()));
    }

    /// Asks for a step at `ns` (monotonic), replacing any deadline set before.
    pub(super) fn wake_at(&self, ns: u64) -> Result<(), ActivityError> {
        // A zero it_value would disarm the timer: the earliest deadline is 1 ns.
        let ns = ns.max(1);
        if OWN.with(Cell::get) == self.key() {
            self.noted.store(ns, Ordering::Relaxed);
            return Ok(());
        }
        self.arm(ns)
    }

    fn arm(&self, ns: u64) -> Result<(), ActivityError> {
        let ts = TimeSpec::new(
            (ns / 1_000_000_000) as libc::time_t,
            (ns % 1_000_000_000) as libc::c_long,
        );
        self.timer
            .set(
                Expiration::OneShot(ts),
                TimerSetTimeFlags::TFD_TIMER_ABSTIME,
            )
            .map_err(|source| ActivityError::Fd {
                what: "timerfd_settime",
                source,
            })?;
        self.armed.store(ns, Ordering::Relaxed);
        Ok(())
    }

    /// After a step that ended at `now` (monotonic ns): applies the deadline the step asked
    /// for. True when the next step is due at once.
    pub(super) fn after_step(&self, now: u64) -> Result<bool, ActivityError> {
        let ns = self.noted.swap(0, Ordering::Relaxed);
        if ns == 0 {
            return Ok(false);
        }
        if ns <= now {
            if self.armed.swap(0, Ordering::Relaxed) != 0 {
                self.timer.unset().map_err(|source| ActivityError::Fd {
                    what: "timerfd_settime(disarm)",
                    source,
                })?;
            }
            return Ok(true);
        }
        if self.armed.load(Ordering::Relaxed) != ns {
            self.arm(ns)?;
        }
        Ok(false)
    }

    /// The timer fired: takes its expiry (a timer re-armed meanwhile may already be unread).
    pub(super) fn fired(&self) {
        let _ = self.timer.wait();
        self.armed.store(0, Ordering::Relaxed);
    }
}
