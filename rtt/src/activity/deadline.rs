//! A file-descriptor activity's deadline ([`Activity::wake_at`](super::Activity::wake_at)):
//! a one-shot `timerfd` in the activity's epoll set, armed only when a wait needs it, and
//! touched only by the activity's own thread (so no other thread can race it between the
//! timer and the record of what it is armed for).
//!
//! A deadline asked for from the activity's own step — a bus line scheduling its next
//! poll — is noted and applied by the thread when the step ends:
//!
//! - a time already past: the next step follows at once, after an `epoll_wait` that does
//!   not wait (to take up descriptors that became ready). No timer is armed, fired and read:
//!   one system call where there were three, so a line polling back to back costs what its
//!   own I/O costs. A timer still armed for a later time is disarmed first, as "replaces any
//!   deadline set before" says.
//! - a time to come: the timer is armed unless it is armed for that time already (a step
//!   woken by a descriptor or a trigger that asks for the same next poll costs no call).
//!
//! A deadline asked for from another thread is left for the activity's thread with a write
//! to an eventfd of its own (one system call), and applied, the same way, at the wake-up
//! that write causes: a time to come arms the timer without a step; a time past steps. The
//! thread applies requests in the order it sees them, so the later replaces the earlier.
//! A request made while the activity is stopped waits for its start.

use super::ActivityError;
use nix::sys::epoll::{Epoll, EpollEvent, EpollFlags};
use nix::sys::eventfd::EventFd;
use nix::sys::time::TimeSpec;
use nix::sys::timerfd::{ClockId, Expiration, TimerFd, TimerFlags, TimerSetTimeFlags};
use std::cell::Cell;
use std::os::fd::AsFd;
use std::sync::atomic::{AtomicU64, Ordering};

thread_local! {
    /// The deadline of the activity whose thread this is (its address; 0: none).
    static OWN: Cell<usize> = const { Cell::new(0) };
}

/// epoll data of the deadline timer.
pub(super) const DEADLINE_EVENT: u64 = u64::MAX - 1;
/// epoll data of another thread's request.
pub(super) const ASK_EVENT: u64 = u64::MAX - 2;

pub(super) struct Deadline {
    timer: TimerFd,
    /// Another thread's request: written before `ask` is (ns; 0: none).
    asked: AtomicU64,
    ask: EventFd,
    /// The time the timer is armed for (monotonic ns; 0: not armed). Only the activity's
    /// thread touches it and the timer.
    armed: AtomicU64,
    /// The deadline the activity's own step asked for, applied when the step ends (ns; 0:
    /// none). Only the activity's thread touches it.
    noted: AtomicU64,
}

impl Deadline {
    /// A deadline whose timer and request eventfd are registered with `epoll`.
    pub(super) fn new(epoll: &Epoll) -> Result<Self, ActivityError> {
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
        let ask = super::eventfd_in(epoll, ASK_EVENT)?;
        Ok(Deadline {
            timer,
            asked: AtomicU64::new(0),
            ask,
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
        self.asked.store(ns, Ordering::Release);
        self.ask.write(1).map_err(|source| ActivityError::Fd {
            what: "eventfd write",
            source,
        })?;
        Ok(())
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
        match self.noted.swap(0, Ordering::Relaxed) {
            0 => Ok(false),
            ns => self.apply(ns, now),
        }
    }

    /// At a wake-up by another thread's request: applies it. True when a step is due at
    /// once.
    pub(super) fn take_asked(&self, now: u64) -> Result<bool, ActivityError> {
        let _ = self.ask.read();
        match self.asked.swap(0, Ordering::Acquire) {
            0 => Ok(false),
            ns => self.apply(ns, now),
        }
    }

    /// The thread's loop ends with a step due at once: leaves the timer fired, so that
    /// step comes at the next start.
    pub(super) fn keep_for_restart(&self) -> Result<(), ActivityError> {
        self.arm(1)
    }

    fn apply(&self, ns: u64, now: u64) -> Result<bool, ActivityError> {
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
