//! The two descriptors a CAN bus side waits on beside its socket: a timerfd armed at the
//! next deadline (a cyclic frame, a SYNC, a timeout, a link check) and an eventfd that
//! another thread writes when an output changed. An rtt file-descriptor activity watches
//! them with the socket; the bus side calls [`Wakeups::clear`] at each service and
//! [`Wakeups::arm`] at its end, which cost a system call only when something fired or the
//! deadline moved.
//!
//! A bus side that waits in its socket instead ([`Wakeups::wait_in_socket`]) has its
//! deadlines kept by the [`Waiter`]'s timer, and its wake-ups end that wait with a signal
//! (see [`crate::blocking`]); the eventfd is still written, so a side without a socket
//! waits for it with `poll`.

use crate::blocking::Waiter;
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
    /// What waits in the socket (see [`wait_in_socket`](Self::wait_in_socket)); boxed, as
    /// most sides never use it.
    waiter: Box<Waiter>,
    /// The side waits in its socket: deadlines go to the waiter's timer.
    in_socket: bool,
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
        let waiter = Waiter::new().map_err(|e| {
            (
                "sigaction",
                nix::Error::from_raw(e.raw_os_error().unwrap_or(0)),
            )
        })?;
        Ok(Wakeups {
            timer,
            wake: Arc::new(wake),
            woken: Arc::new(AtomicBool::new(false)),
            armed: 0,
            waiter: Box::new(waiter),
            in_socket: false,
        })
    }

    /// From now on the side waits in its socket ([`Waiter`]), or (false) in an epoll set
    /// with the timer's and the wake-up's descriptors.
    pub fn wait_in_socket(&mut self, yes: bool) {
        self.in_socket = yes;
        self.armed = 0;
    }

    /// Waits in `poll` on the wake-up, and on `socket` if given, until `deadline`
    /// (monotonic ns) at the latest: for a side that waits in its socket while it has none
    /// (its interface is missing), or while it cannot (a signal's timer would not arm).
    pub fn wait_in_poll(&mut self, deadline: u64, socket: Option<BorrowedFd<'_>>) {
        use nix::poll::{PollFd, PollFlags, PollTimeout, poll};
        let ms = deadline
            .saturating_sub(crate::blocking::now_ns())
            .div_ceil(1_000_000);
        let timeout = PollTimeout::try_from(ms.min(60_000) as i32).unwrap_or(PollTimeout::MAX);
        let wake = PollFd::new(self.wake.as_fd(), PollFlags::POLLIN);
        // Interrupted or failed: the caller looks at what is due, as after a wake-up.
        let _ = match socket {
            Some(s) => poll(&mut [wake, PollFd::new(s, PollFlags::POLLIN)], timeout),
            None => poll(&mut [wake], timeout),
        };
    }

    /// The waiter, for the side's thread.
    pub fn waiter(&mut self) -> &mut Waiter {
        &mut self.waiter
    }

    /// What another thread calls to wake the bus side.
    pub fn waker(&self) -> Box<dyn Fn() + Send + Sync> {
        let (wake, woken) = (self.wake.clone(), self.woken.clone());
        let interrupter = self.waiter.interrupter();
        // The write first, then the flag: a flag seen set means the count is there (or a
        // read took it already), so the eventfd is never left readable with the flag
        // clear for longer than between these two lines. Last, the signal that ends a
        // wait in the socket (nothing when the side does not wait there).
        Box::new(move || {
            let _ = wake.write(1);
            woken.store(true, Ordering::Release);
            interrupter.interrupt();
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
        if !self.in_socket && self.armed != 0 && now >= self.armed {
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
        if self.in_socket {
            // A failed arm is tried again before the next wait (the waiter keeps the time).
            let _ = self.waiter.arm(next);
            return;
        }
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
