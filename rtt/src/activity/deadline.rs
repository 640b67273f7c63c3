//! A file-descriptor activity's deadline ([`Activity::wake_at`](super::Activity::wake_at)):
//! a one-shot `timerfd` in the activity's epoll set, armed only when a wait needs it, and
//! touched only by the activity's own thread (so no other thread can race it between the
//! timer and the record of what it is armed for).
//!
//! A deadline asked for from the activity's own step — a bus line scheduling its next
//! poll — is noted and applied by the thread when the step ends:
//!
//! - a time already past: the next step follows at once, after an `epoll_wait` that does
//!   not wait (to take up descriptors that became ready) — or with no call at all when
//!   nothing in the epoll set can be ready: the activity watches no descriptor of its user,
//!   and no wake-up or request from another thread was written since the last look (each
//!   writer raises a flag after its write; see [`Deadline::nudge`]). No timer is armed,
//!   fired and read, so a line polling back to back costs what its own I/O costs. A
//!   timer still armed for a later time is disarmed first, as "replaces any deadline set
//!   before" says.
//! - a time to come: the timer is armed unless it is armed for that time already (a step
//!   woken by a descriptor or a trigger that asks for the same next poll costs no call).
//!
//! A deadline asked for from another thread is left for the activity's thread with a write
//! to an eventfd of its own (one system call), and applied, the same way, at the wake-up
//! that write causes: a time to come arms the timer without a step; a time past steps. The
//! thread applies requests in the order it sees them, so the later replaces the earlier.
//! A request made while the activity is stopped waits for its start.
//!
//! **How the thread waits for it.** Where the kernel has `epoll_pwait2` (Linux 5.11), the
//! deadline is no timer at all: the thread's wait itself ends at it, with a timeout to the
//! nanosecond, so a line polling every period makes one system call for its wait, where a
//! timer cost three (arm it, wake through it, read its expiry). A kernel without the call
//! (`ENOSYS`), or a seccomp filter that refuses it (`EPERM`, as systemd's
//! `SystemCallErrorNumber=EPERM` does for calls it does not know), turns the process over
//! to the timer for good at the first wait that meets it; the timer is armed for the
//! deadline then, so nothing asked for is lost. Only a real-time thread (SCHED_FIFO or
//! SCHED_RR) waits this way: the kernel gives any other thread's timed wait a slack (its
//! timer slack, 50 µs by default, or 0.1 % of the wait if more: 1 ms late on a 1 s poll),
//! where a timer's expiry has none. Other threads keep the timer.

use super::ActivityError;
use device_interface::time::{Clock, MonotonicClock};
use nix::errno::Errno;
use nix::sys::epoll::{Epoll, EpollEvent, EpollFlags, EpollTimeout};
use nix::sys::eventfd::EventFd;
use nix::sys::time::TimeSpec;
use nix::sys::timerfd::{ClockId, Expiration, TimerFd, TimerFlags, TimerSetTimeFlags};
use std::cell::Cell;
use std::os::fd::{AsFd, AsRawFd};
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU64, Ordering};

thread_local! {
    /// The deadline of the activity whose thread this is (its address; 0: none).
    static OWN: Cell<usize> = const { Cell::new(0) };
}

/// How deadlines are waited for, for the whole process: not known yet, by the wait's own
/// timeout (`epoll_pwait2`), or by a timer (the kernel or a filter refused the call).
static HOW: AtomicU8 = AtomicU8::new(UNKNOWN);
const UNKNOWN: u8 = 0;
const PRECISE_WAIT: u8 = 1;
const TIMER: u8 = 2;

/// Makes every deadline from now on a timer's, as on a kernel without `epoll_pwait2`: for
/// the tests of that path.
#[doc(hidden)]
pub fn use_timer_deadlines() {
    HOW.store(TIMER, Ordering::Relaxed);
}

/// Threads entering their loop from now on wait for their deadlines with `epoll_pwait2`
/// whatever their scheduling class (where the kernel has it): for the tests of that path,
/// which run on SCHED_OTHER threads.
#[doc(hidden)]
pub fn use_precise_deadlines_for_every_thread() {
    FOR_EVERY_THREAD.store(true, Ordering::Relaxed);
}

static FOR_EVERY_THREAD: AtomicBool = AtomicBool::new(false);

/// What ended a wait.
pub(super) struct Waited {
    /// Events in the buffer.
    pub(super) n: usize,
    /// The deadline came (without a timer's event to say so).
    pub(super) deadline: bool,
    /// The activity's timeout passed with nothing ready.
    pub(super) timeout: bool,
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
    /// The deadline in force (monotonic ns; 0: none): what the thread's wait ends at, or
    /// what the timer is armed for. Only the activity's thread touches it and the timer.
    armed: AtomicU64,
    /// Its thread waits for it with `epoll_pwait2` (a real-time thread; see the module).
    precise: AtomicBool,
    /// The deadline in force is on the timer (not left to the wait). Per deadline: another
    /// activity's thread may turn the process over to the timer while this one's deadline
    /// waits to be waited for.
    timed: AtomicBool,
    /// The deadline the activity's own step asked for, applied when the step ends (ns; 0:
    /// none). Only the activity's thread touches it.
    noted: AtomicU64,
    /// Raised by another thread after it wrote to an eventfd in the epoll set (a wake-up, a
    /// request): a step due at once looks at the set first.
    nudged: AtomicBool,
}

impl Deadline {
    /// A deadline whose timer and request eventfd are registered with `epoll`.
    pub(super) fn new(epoll: &Epoll) -> Result<Self, ActivityError> {
        let timer = TimerFd::new(
            ClockId::CLOCK_MONOTONIC,
            TimerFlags::TFD_NONBLOCK | TimerFlags::TFD_CLOEXEC,
        )
        .map_err(ActivityError::fd("timerfd_create"))?;
        epoll
            .add(
                timer.as_fd(),
                EpollEvent::new(EpollFlags::EPOLLIN, DEADLINE_EVENT),
            )
            .map_err(ActivityError::fd("epoll_ctl(timerfd)"))?;
        let ask = super::eventfd_in(epoll, ASK_EVENT)?;
        Ok(Deadline {
            timer,
            asked: AtomicU64::new(0),
            ask,
            armed: AtomicU64::new(0),
            precise: AtomicBool::new(false),
            timed: AtomicBool::new(false),
            noted: AtomicU64::new(0),
            nudged: AtomicBool::new(false),
        })
    }

    fn key(&self) -> usize {
        self as *const Self as usize
    }

    /// Marks the calling thread as the activity's own: its `wake_at` calls are noted, and
    /// its timed waits end when asked (no timer slack).
    /// A `realtime` thread waits for its deadlines itself (see the module).
    pub(super) fn enter_thread(&self, realtime: bool) {
        OWN.with(|o| o.set(self.key()));
        self.precise.store(
            realtime || FOR_EVERY_THREAD.load(Ordering::Relaxed),
            Ordering::Relaxed,
        );
    }

    /// Its deadlines are the timer's: the process's kernel refused the wait, or its thread
    /// is not a real-time one.
    fn by_timer(&self) -> bool {
        HOW.load(Ordering::Relaxed) == TIMER || !self.precise.load(Ordering::Relaxed)
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
        self.ask
            .write(1)
            .map_err(ActivityError::fd("eventfd write"))?;
        self.nudge();
        Ok(())
    }

    /// Says that an eventfd in the epoll set was written (called after the write, so a
    /// thread that sees the flag sees the descriptor ready): a step due at once looks at
    /// the set before it runs.
    pub(super) fn nudge(&self) {
        self.nudged.store(true, Ordering::Release);
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
            .map_err(ActivityError::fd("timerfd_settime"))?;
        self.armed.store(ns, Ordering::Relaxed);
        self.timed.store(true, Ordering::Relaxed);
        Ok(())
    }

    /// Makes `ns` the deadline in force, left to the thread's wait (no system call).
    fn leave_to_wait(&self, ns: u64) -> Result<(), ActivityError> {
        if self.timed.swap(false, Ordering::Relaxed) {
            // Armed before the thread waited for itself (a restart as a real-time thread):
            // it must not fire for the deadline this one replaces.
            self.timer
                .unset()
                .map_err(ActivityError::fd("timerfd_settime(disarm)"))?;
        }
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
        if self.by_timer() {
            self.arm(1)
        } else {
            self.leave_to_wait(1)
        }
    }

    fn apply(&self, ns: u64, now: u64) -> Result<bool, ActivityError> {
        if ns <= now {
            if self.armed.swap(0, Ordering::Relaxed) != 0
                && self.timed.swap(false, Ordering::Relaxed)
            {
                self.timer
                    .unset()
                    .map_err(ActivityError::fd("timerfd_settime(disarm)"))?;
            }
            return Ok(true);
        }
        if self.armed.load(Ordering::Relaxed) != ns {
            if self.by_timer() {
                self.arm(ns)?;
            } else {
                self.leave_to_wait(ns)?;
            }
        }
        Ok(false)
    }

    /// Waits in `epoll` for ready descriptors (into `ready`), the deadline in force, or
    /// `timeout` (ns; `None`: for ever) with nothing ready; with `at_once`, does not wait
    /// (the step before asked for a time already past, which is the deadline that came),
    /// and does not look either unless `watching` (descriptors of the user's are in the set)
    /// or a [`nudge`](Self::nudge) came since it last looked.
    pub(super) fn wait(
        &self,
        epoll: &Epoll,
        ready: &mut [EpollEvent],
        timeout: Option<u64>,
        at_once: bool,
        watching: bool,
    ) -> Result<Waited, ActivityError> {
        if at_once {
            // Nothing can be ready: no descriptor of the user's, no eventfd written.
            let n = if !watching && !self.nudged.swap(false, Ordering::Acquire) {
                0
            } else {
                epoll
                    .wait(ready, EpollTimeout::ZERO)
                    .map_err(ActivityError::fd("epoll_wait"))?
            };
            return Ok(Waited {
                n,
                deadline: true,
                timeout: false,
            });
        }
        // This wait looks at the set: what a nudge taken here said is seen by it (the swap
        // synchronises with the nudge's release, which follows its write).
        self.nudged.swap(false, Ordering::AcqRel);
        let due = self.armed.load(Ordering::Relaxed);
        if due != 0 && !self.timed.load(Ordering::Relaxed) {
            if self.by_timer() {
                // Left to the wait when the thread waited itself (before a restart as a
                // thread that does not, or before the process turned to the timer).
                self.arm(due)?;
            } else {
                match self.wait_precisely(epoll, ready, timeout, due) {
                    Err(ActivityError::Fd {
                        what: EPOLL_PWAIT2,
                        source: Errno::ENOSYS | Errno::EPERM,
                    }) => {
                        HOW.store(TIMER, Ordering::Relaxed);
                        self.arm(due)?;
                    }
                    waited => return waited,
                }
            }
        }
        let n = epoll
            .wait(ready, epoll_timeout(timeout))
            .map_err(ActivityError::fd("epoll_wait"))?;
        Ok(Waited {
            n,
            deadline: false,
            timeout: n == 0,
        })
    }

    /// Waits with `epoll_pwait2` for at most the time to `due` or `timeout`, whichever
    /// comes first.
    fn wait_precisely(
        &self,
        epoll: &Epoll,
        ready: &mut [EpollEvent],
        timeout: Option<u64>,
        due: u64,
    ) -> Result<Waited, ActivityError> {
        let now = MonotonicClock.now().as_nanos();
        let n = if due <= now {
            epoll
                .wait(ready, EpollTimeout::ZERO)
                .map_err(ActivityError::fd("epoll_wait"))?
        } else {
            let ns = (due - now).min(timeout.unwrap_or(u64::MAX));
            let n = epoll_pwait2(epoll, ready, ns).map_err(ActivityError::fd(EPOLL_PWAIT2))?;
            // Once: a refusal seen meanwhile on another thread stays the process's.
            let _ =
                HOW.compare_exchange(UNKNOWN, PRECISE_WAIT, Ordering::Relaxed, Ordering::Relaxed);
            n
        };
        let deadline = due <= now || MonotonicClock.now().as_nanos() >= due;
        if deadline {
            self.armed.store(0, Ordering::Relaxed);
        }
        Ok(Waited {
            n,
            deadline,
            timeout: n == 0 && !deadline,
        })
    }

    /// The timer fired: takes its expiry (a timer re-armed meanwhile may already be unread).
    pub(super) fn fired(&self) {
        let _ = self.timer.wait();
        self.armed.store(0, Ordering::Relaxed);
        self.timed.store(false, Ordering::Relaxed);
    }
}

/// What a failed `epoll_pwait2` is called in its error: the name its refusal (ENOSYS,
/// EPERM) is known by, which turns the process over to the timer.
const EPOLL_PWAIT2: &str = "epoll_pwait2";

/// An `epoll_wait` whose timeout is in ms (rounded up, so a timeout never ends a wait
/// early), from one in ns (`None`: for ever).
fn epoll_timeout(ns: Option<u64>) -> EpollTimeout {
    match ns {
        None => EpollTimeout::NONE,
        Some(ns) => EpollTimeout::try_from(std::time::Duration::from_nanos(
            ns.div_ceil(1_000_000).saturating_mul(1_000_000),
        ))
        .unwrap_or(EpollTimeout::MAX),
    }
}

/// `epoll_pwait2` on `epoll` with a relative timeout of `ns` and no signal mask: the
/// events ready, at most `ready.len()` of them.
#[allow(
    unsafe_code,
    reason = "no wrapper for epoll_pwait2 in nix or libc: a raw system call with a buffer we own"
)]
fn epoll_pwait2(epoll: &Epoll, ready: &mut [EpollEvent], ns: u64) -> Result<usize, Errno> {
    if cfg!(not(target_pointer_width = "64")) {
        // The call takes a 64-bit timespec, which `libc::timespec` is not everywhere here:
        // such a target keeps the timer.
        return Err(Errno::ENOSYS);
    }
    let ts = libc::timespec {
        tv_sec: (ns / 1_000_000_000).min(i64::MAX as u64) as libc::time_t,
        tv_nsec: (ns % 1_000_000_000) as libc::c_long,
    };
    let max = libc::c_int::try_from(ready.len()).unwrap_or(libc::c_int::MAX);
    // SAFETY: `EpollEvent` is `repr(transparent)` over `libc::epoll_event`, so `ready` is
    // `max` writable events the kernel may fill; `ts` lives across the call; a null
    // signal mask (size 0) leaves the mask alone.
    let n = unsafe {
        libc::syscall(
            libc::SYS_epoll_pwait2,
            epoll.0.as_raw_fd(),
            ready.as_mut_ptr().cast::<libc::epoll_event>(),
            max,
            &ts as *const libc::timespec,
            std::ptr::null::<libc::sigset_t>(),
            0usize,
        )
    };
    Errno::result(n).map(|n| usize::try_from(n).unwrap_or(0))
}
