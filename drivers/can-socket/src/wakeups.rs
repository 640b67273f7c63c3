//! The two descriptors a CAN bus side waits on beside its socket: a timerfd armed at the
//! next deadline (a cyclic frame, a SYNC, a timeout, a link check) and an eventfd that
//! another thread writes when an output changed. An rtt file-descriptor activity watches
//! them with the socket; the bus side calls [`Wakeups::clear`] at each service and
//! [`Wakeups::arm`] at its end, which cost a system call only when something fired or the
//! deadline moved.

use nix::sys::eventfd::{EfdFlags, EventFd};
use nix::sys::time::TimeSpec;
use nix::sys::timerfd::{ClockId, Expiration, TimerFd, TimerFlags, TimerSetTimeFlags};
use std::os::fd::{AsFd, BorrowedFd};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// A bus side's timer and wake-up.
pub struct Wakeups {
    timer: TimerFd,
    wake: Arc<EventFd>,
    /// Set after each wake-up written (so the eventfd is read only when written).
    woken: Arc<AtomicBool>,
    /// The deadline the timer is armed for (CLOCK_MONOTONIC ns; 0: none).
    armed: u64,
}

impl Wakeups {
    /// A timer (CLOCK_MONOTONIC) and a wake-up, both non-blocking.
    pub fn new() -> Result<Wakeups, (&'static str, nix::Error)> {
        let timer = TimerFd::new(
            ClockId::CLOCK_MONOTONIC,
            TimerFlags::TFD_NONBLOCK | TimerFlags::TFD_CLOEXEC,
        )
        .map_err(|e| ("timerfd_create", e))?;
        let wake = EventFd::from_value_and_flags(0, EfdFlags::EFD_NONBLOCK | EfdFlags::EFD_CLOEXEC)
            .map_err(|e| ("eventfd", e))?;
        Ok(Wakeups {
            timer,
            wake: Arc::new(wake),
            woken: Arc::new(AtomicBool::new(false)),
            armed: 0,
        })
    }

    /// What another thread calls to wake the bus side.
    pub fn waker(&self) -> Box<dyn Fn() + Send + Sync> {
        let (wake, woken) = (self.wake.clone(), self.woken.clone());
        // The write first, then the flag: a flag seen set means the count is there (or a
        // read took it already), so the eventfd is never left readable with the flag
        // clear for longer than between these two lines.
        Box::new(move || {
            let _ = wake.write(1);
            woken.store(true, Ordering::Release);
        })
    }

    /// The timer's and the wake-up's descriptors.
    pub fn fds(&self) -> [BorrowedFd<'_>; 2] {
        [self.timer.as_fd(), self.wake.as_fd()]
    }

    /// Takes what fired by `now` (CLOCK_MONOTONIC ns): the wake-up if it was written, the
    /// timer if its deadline passed.
    pub fn clear(&mut self, now: u64) {
        if self.woken.swap(false, Ordering::AcqRel) {
            // Empties the count (EAGAIN when an earlier read took this write's too).
            let _ = self.wake.read();
        }
        if self.armed != 0 && now >= self.armed {
            // Clears the expiry (EAGAIN if the kernel has not quite fired it: the re-arm
            // replaces it).
            let _ = self.timer.wait();
            self.armed = 0;
        }
    }

    /// Arms the timer for `next` (CLOCK_MONOTONIC ns, at least 1), unless it is armed for
    /// that already. Only a timer that took the deadline counts as armed for it (else the
    /// next call tries again).
    pub fn arm(&mut self, next: u64) {
        let next = next.max(1);
        if next == self.armed {
            return;
        }
        let ts = TimeSpec::from_duration(Duration::from_nanos(next));
        self.armed = match self.timer.set(
            Expiration::OneShot(ts),
            TimerSetTimeFlags::TFD_TIMER_ABSTIME,
        ) {
            Ok(()) => next,
            Err(_) => 0,
        };
    }
}
