//! Waiting for a frame in the socket itself: a bus thread blocked in `recvmsg`, as a bare
//! blocking reader is, rather than in `epoll_wait` followed by a second call for the frame.
//!
//! What else the thread waits for reaches it as a signal, [`signal()`], sent to that thread
//! alone: a POSIX timer aimed at it fires at the next deadline (a cyclic frame, a link
//! check), and [`Interrupter::interrupt`] — an output that changed, a stop — sends it from
//! any thread. The handler makes the waiting socket non-blocking (`fcntl`, which is
//! async-signal-safe), so no signal is lost in the moment between the thread's last look at
//! what is pending and its entry into `recvmsg`: a signal in that moment makes the call
//! return at once (`EAGAIN`), one during it ends it (`EINTR`). The thread makes the socket
//! blocking again before its next wait, only when a signal came ([`Waiter::prepare`]).
//!
//! The handler is installed once per process with `SA_RESTART`, so any other call the
//! thread makes (a netlink query) is restarted rather than failed; a restarted `recvmsg` on
//! the socket sees it non-blocking and returns. Sends on such a socket must not block: they
//! pass `MSG_DONTWAIT` ([`crate::socket::RawSocket::send`]).

use std::cell::Cell;
use std::os::fd::RawFd;
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::sync::{Arc, OnceLock};

/// The signal that interrupts a bus thread's wait: the sixth real-time signal above the
/// C library's reserved ones, which nothing else in hwgw uses.
pub fn signal() -> libc::c_int {
    libc::SIGRTMIN() + 5
}

thread_local! {
    /// The socket this thread waits on (-1: none): what the handler makes non-blocking.
    /// Atomics, as the handler touches them between any two instructions of the thread.
    static WAITING_FD: AtomicI32 = const { AtomicI32::new(-1) };
    /// Set by the handler when it made the socket non-blocking.
    static UNBLOCKED: AtomicBool = const { AtomicBool::new(false) };
    /// This thread's kernel id, once asked (0: not yet).
    static TID: Cell<libc::pid_t> = const { Cell::new(0) };
}

/// The calling thread's kernel id (one system call per thread).
fn this_thread() -> libc::pid_t {
    match TID.get() {
        0 => {
            #[allow(
                unsafe_code,
                reason = "gettid has no safe wrapper in the C library crate"
            )]
            // SAFETY: a plain system call without arguments.
            let tid = unsafe { libc::gettid() };
            TID.set(tid);
            tid
        }
        tid => tid,
    }
}

extern "C" fn on_signal(_: libc::c_int) {
    #[allow(
        unsafe_code,
        reason = "a signal handler keeps the thread's errno, which only a raw pointer reaches"
    )]
    // SAFETY: `__errno_location` returns this thread's errno, valid for its life; `fcntl`
    // is async-signal-safe; the thread-locals are const-initialised cells without drop,
    // plain thread-local storage.
    unsafe {
        let errno = libc::__errno_location();
        let saved = *errno;
        let fd = WAITING_FD.with(|w| w.load(Ordering::Relaxed));
        if fd >= 0 {
            let flags = libc::fcntl(fd, libc::F_GETFL);
            if flags >= 0 && libc::fcntl(fd, libc::F_SETFL, flags | libc::O_NONBLOCK) == 0 {
                UNBLOCKED.with(|u| u.store(true, Ordering::Relaxed));
            }
        }
        *errno = saved;
    }
}

/// The handler's installation: done once; its failure (an errno) kept for every waiter.
static INSTALLED: OnceLock<Result<(), i32>> = OnceLock::new();

/// Installs the handler of [`signal()`] (once per process; a failure is every caller's).
fn install() -> std::io::Result<()> {
    let r = INSTALLED.get_or_init(|| {
        #[allow(
            unsafe_code,
            reason = "sigaction for a real-time signal, which nix's Signal cannot name"
        )]
        // SAFETY: a zeroed sigaction is valid; its mask is emptied and its handler set
        // before the call reads it; the handler only calls async-signal-safe functions and
        // touches thread-local atomics (see `on_signal`).
        let r = unsafe {
            let mut action: libc::sigaction = std::mem::zeroed();
            libc::sigemptyset(&mut action.sa_mask);
            action.sa_sigaction = on_signal as extern "C" fn(libc::c_int) as libc::sighandler_t;
            action.sa_flags = libc::SA_RESTART;
            libc::sigaction(signal(), &action, std::ptr::null_mut())
        };
        if r == 0 {
            Ok(())
        } else {
            Err(std::io::Error::last_os_error().raw_os_error().unwrap_or(0))
        }
    });
    r.map_err(std::io::Error::from_raw_os_error)
}

/// Unblocks [`signal()`] in the calling thread.
fn unblock() -> std::io::Result<()> {
    #[allow(
        unsafe_code,
        reason = "pthread_sigmask for a real-time signal, which nix's Signal cannot name"
    )]
    // SAFETY: the set is initialised by sigemptyset before use and lives for the call.
    let r = unsafe {
        let mut set: libc::sigset_t = std::mem::zeroed();
        libc::sigemptyset(&mut set);
        libc::sigaddset(&mut set, signal());
        libc::pthread_sigmask(libc::SIG_UNBLOCK, &set, std::ptr::null_mut())
    };
    if r == 0 {
        Ok(())
    } else {
        Err(std::io::Error::from_raw_os_error(r))
    }
}

/// This process's id, once asked.
static PID: OnceLock<u32> = OnceLock::new();

/// Interrupts one bus thread's wait; any thread may call it. Never blocks, never allocates.
#[derive(Debug, Default)]
pub struct Interrupter {
    /// The waiting thread's kernel id (0: none waits this way).
    tid: AtomicI32,
    /// Something is due: the thread does not wait until it took it.
    pending: AtomicBool,
}

impl Interrupter {
    /// Ends the thread's wait (or keeps it from starting): one `tgkill` unless an
    /// interruption is pending already.
    pub fn interrupt(&self) {
        if self.pending.swap(true, Ordering::AcqRel) {
            return;
        }
        let tid = self.tid.load(Ordering::Acquire);
        if tid > 0 {
            let pid = *PID.get_or_init(std::process::id);
            // ESRCH: the thread ended; its next one looks at `pending` first.
            #[allow(
                unsafe_code,
                reason = "tgkill has no safe wrapper; it sends a signal and touches no memory"
            )]
            // SAFETY: a plain system call with integer arguments.
            let _ = unsafe {
                libc::syscall(
                    libc::SYS_tgkill,
                    libc::c_long::from(pid),
                    libc::c_long::from(tid),
                    libc::c_long::from(signal()),
                )
            };
        }
    }
}

/// What a bus thread holds to wait in its socket: the timer aimed at it, and the
/// interrupter other threads use.
pub struct Waiter {
    interrupter: Arc<Interrupter>,
    /// The POSIX timer and the thread it is aimed at.
    timer: Option<(libc::pid_t, libc::timer_t)>,
    /// The deadline the timer is armed for (monotonic ns; 0: none).
    armed: u64,
    /// The deadline asked for last (monotonic ns; 0: none): armed when the timer is made.
    wanted: u64,
}

// SAFETY of the `timer_t` held: a kernel timer id (a pointer-sized handle), used only by
// the thread that holds the waiter.
#[allow(
    unsafe_code,
    reason = "timer_t is a raw handle the C library hands out; the waiter is used by one thread at a time"
)]
// SAFETY: see above: the handle is an id, not memory this type reaches through.
unsafe impl Send for Waiter {}

impl Waiter {
    /// A waiter; the handler is installed if it was not.
    pub fn new() -> std::io::Result<Waiter> {
        install()?;
        Ok(Waiter {
            interrupter: Arc::default(),
            timer: None,
            armed: 0,
            wanted: 0,
        })
    }

    /// What other threads call to end this waiter's thread's wait.
    pub fn interrupter(&self) -> Arc<Interrupter> {
        self.interrupter.clone()
    }

    /// Before a wait on `fd` from the calling thread: aims the signal and the timer at
    /// this thread (again, after a restart on a new thread), makes `fd` blocking again if
    /// a signal made it non-blocking, and says whether the thread may wait: false when an
    /// interruption is pending (taken now: the caller does what it asked for), when the
    /// deadline armed has come, or when a signal came while this ran.
    ///
    /// Every signal is seen: one before the socket is made blocking again was sent for an
    /// interruption (pending, looked at after) or a deadline (come, looked at after); one
    /// while it is made blocking leaves its mark, looked at after; one after makes the
    /// wait's call return at once.
    ///
    /// An error (the timer cannot be made or armed, the socket's mode not set): the caller
    /// must not wait in the socket, where a deadline would not end the wait.
    pub fn prepare(&mut self, fd: RawFd) -> std::io::Result<bool> {
        let changed = WAITING_FD.with(|w| w.swap(fd, Ordering::Relaxed)) != fd;
        if changed || UNBLOCKED.with(|u| u.load(Ordering::Relaxed)) {
            UNBLOCKED.with(|u| u.store(false, Ordering::Relaxed));
            set_blocking(fd)?;
            if UNBLOCKED.with(|u| u.load(Ordering::Relaxed)) {
                return Ok(false);
            }
        }
        let tid = this_thread();
        if self.timer.is_none_or(|(t, _)| t != tid) {
            self.aim(tid)?;
        }
        if self.wanted != self.armed && self.wanted != 0 {
            // An arm that failed before: again, or no wait.
            self.arm(self.wanted)?;
        }
        if self.interrupter.pending.swap(false, Ordering::AcqRel) {
            return Ok(false);
        }
        if self.armed != 0 && now_ns() >= self.armed {
            return Ok(false);
        }
        Ok(true)
    }

    /// This thread no longer waits on its socket (it is replaced or closed): a signal
    /// leaves descriptors alone.
    pub fn leave(&mut self) {
        WAITING_FD.with(|w| w.store(-1, Ordering::Relaxed));
        UNBLOCKED.with(|u| u.store(false, Ordering::Relaxed));
    }

    /// The thread that waited has ended (its component stopped): the timer is deleted and
    /// interruptions send no signal (a later thread may have its id) until a thread
    /// prepares again.
    pub fn forget_thread(&mut self) {
        self.interrupter.tid.store(0, Ordering::Release);
        self.delete_timer();
        self.armed = 0;
    }

    /// Arms the timer for `ns` (monotonic ns, at least 1), unless armed for it already.
    /// Before the thread is known (no timer yet), the time is kept and armed when the
    /// timer is made.
    pub fn arm(&mut self, ns: u64) -> std::io::Result<()> {
        let ns = ns.max(1);
        self.wanted = ns;
        let Some((_, timer)) = self.timer else {
            return Ok(());
        };
        if ns == self.armed {
            return Ok(());
        }
        let spec = libc::itimerspec {
            it_interval: libc::timespec {
                tv_sec: 0,
                tv_nsec: 0,
            },
            it_value: libc::timespec {
                tv_sec: (ns / 1_000_000_000) as libc::time_t,
                tv_nsec: (ns % 1_000_000_000) as libc::c_long,
            },
        };
        #[allow(unsafe_code, reason = "timer_settime has no safe wrapper")]
        // SAFETY: `timer` is a live timer of this waiter; `spec` lives for the call.
        let r =
            unsafe { libc::timer_settime(timer, libc::TIMER_ABSTIME, &spec, std::ptr::null_mut()) };
        if r != 0 {
            self.armed = 0;
            return Err(std::io::Error::last_os_error());
        }
        self.armed = ns;
        Ok(())
    }

    /// A timer on CLOCK_MONOTONIC whose expiry sends the signal to thread `tid`, replacing
    /// one aimed at an earlier thread; the signal unblocked in this thread.
    fn aim(&mut self, tid: libc::pid_t) -> std::io::Result<()> {
        self.delete_timer();
        unblock()?;
        #[allow(
            unsafe_code,
            reason = "timer_create with SIGEV_THREAD_ID has no safe wrapper"
        )]
        // SAFETY: a zeroed sigevent is valid; the fields set are the ones SIGEV_THREAD_ID
        // reads; `timer` is written by the call.
        let timer = unsafe {
            let mut ev: libc::sigevent = std::mem::zeroed();
            ev.sigev_notify = libc::SIGEV_THREAD_ID;
            ev.sigev_signo = signal();
            ev.sigev_notify_thread_id = tid;
            let mut timer: libc::timer_t = std::mem::zeroed();
            if libc::timer_create(libc::CLOCK_MONOTONIC, &mut ev, &mut timer) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            timer
        };
        self.timer = Some((tid, timer));
        self.armed = 0;
        self.interrupter.tid.store(tid, Ordering::Release);
        if self.wanted != 0 {
            self.arm(self.wanted)?;
        }
        Ok(())
    }

    fn delete_timer(&mut self) {
        if let Some((_, timer)) = self.timer.take() {
            #[allow(unsafe_code, reason = "timer_delete has no safe wrapper")]
            // SAFETY: a live timer of this waiter, deleted once.
            unsafe {
                libc::timer_delete(timer);
            }
        }
    }
}

impl Drop for Waiter {
    fn drop(&mut self) {
        self.forget_thread();
    }
}

/// CLOCK_MONOTONIC now, ns.
pub(crate) fn now_ns() -> u64 {
    use device_interface::time::{Clock, MonotonicClock};
    MonotonicClock.now().as_nanos()
}

/// Clears `O_NONBLOCK` on `fd`, leaving its other status flags.
fn set_blocking(fd: RawFd) -> std::io::Result<()> {
    #[allow(unsafe_code, reason = "fcntl on a raw descriptor the caller owns")]
    // SAFETY: F_GETFL and F_SETFL on a descriptor; no memory is passed.
    let r = unsafe {
        let flags = libc::fcntl(fd, libc::F_GETFL);
        if flags < 0 {
            flags
        } else {
            libc::fcntl(fd, libc::F_SETFL, flags & !libc::O_NONBLOCK)
        }
    };
    if r >= 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::fd::AsRawFd;
    use std::os::unix::net::UnixDatagram;
    use std::time::{Duration, Instant};

    /// Waits as a bus thread does: prepare, then a blocking receive on `fd`. What ended it:
    /// Some(bytes) for a datagram, None for a signal (or no wait at all).
    fn wait(w: &mut Waiter, fd: RawFd) -> Option<usize> {
        if !w.prepare(fd).unwrap() {
            return None;
        }
        let mut buf = [0u8; 16];
        match nix::sys::socket::recv(fd, &mut buf, nix::sys::socket::MsgFlags::empty()) {
            Ok(n) => Some(n),
            Err(nix::Error::EINTR | nix::Error::EAGAIN) => None,
            Err(e) => panic!("recv: {e}"),
        }
    }

    #[test]
    fn a_wait_ends_at_a_datagram_an_interruption_and_a_deadline() {
        let (a, b) = UnixDatagram::pair().unwrap();
        a.set_nonblocking(true).unwrap();
        let fd = a.as_raw_fd();
        let mut w = Waiter::new().unwrap();
        // Before the thread is known: nothing pending, no deadline; a datagram ends it.
        b.send(b"abc").unwrap();
        assert_eq!(wait(&mut w, fd), Some(3));
        // An interruption from another thread, sent while the thread waits.
        let i = w.interrupter();
        let t0 = Instant::now();
        let h = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(50));
            i.interrupt();
        });
        assert_eq!(wait(&mut w, fd), None);
        assert!(
            t0.elapsed() >= Duration::from_millis(40),
            "{:?}",
            t0.elapsed()
        );
        h.join().unwrap();
        // An interruption made before the wait: no wait at all.
        w.interrupter().interrupt();
        let t0 = Instant::now();
        assert_eq!(wait(&mut w, fd), None);
        assert!(t0.elapsed() < Duration::from_secs(5));
        // A deadline 30 ms ahead ends the wait then (the timer aimed at this thread).
        let at = now_ns() + 30_000_000;
        w.arm(at).unwrap();
        loop {
            if wait(&mut w, fd).is_none() && now_ns() >= at {
                break;
            }
            assert!(
                now_ns() < at + 5_000_000_000,
                "the deadline never ended a wait"
            );
        }
        // A deadline come keeps the thread from waiting until the next is armed (as a bus
        // does after its work); the socket is blocking again: a datagram ends the wait.
        assert_eq!(wait(&mut w, fd), None);
        w.arm(now_ns() + 60_000_000_000).unwrap();
        b.send(b"de").unwrap();
        assert_eq!(wait(&mut w, fd), Some(2));
        w.leave();
    }

    #[test]
    fn a_signal_between_the_look_and_the_call_is_not_lost() {
        // The handler makes the socket non-blocking: a signal that comes after `prepare`
        // said "wait" and before the receive makes the receive return at once.
        let (a, _b) = UnixDatagram::pair().unwrap();
        let fd = a.as_raw_fd();
        let mut w = Waiter::new().unwrap();
        for _ in 0..100 {
            assert!(w.prepare(fd).unwrap());
            // The interruption lands here, between the look and the call.
            w.interrupter().interrupt();
            let mut buf = [0u8; 4];
            let r = nix::sys::socket::recv(fd, &mut buf, nix::sys::socket::MsgFlags::empty());
            assert!(
                matches!(r, Err(nix::Error::EAGAIN | nix::Error::EINTR)),
                "{r:?}"
            );
            // Taken: the pending interruption makes the next prepare say "do not wait".
            assert!(!w.prepare(fd).unwrap());
        }
        w.leave();
    }
}
