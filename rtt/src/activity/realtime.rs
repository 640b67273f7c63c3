//! Putting an activity's thread where its options ask: CPU affinity and SCHED_FIFO, said
//! once, with the reason, when the process may not have it.

use super::{MAX_SPIN_US, SchedPolicy, ThreadOptions};
use std::sync::atomic::{AtomicBool, Ordering};

/// Thread options that cannot be had ([`ThreadOptions::check`]).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ThreadError {
    /// A SCHED_FIFO priority outside 1 to 99.
    #[error("priority {0}: SCHED_FIFO takes 1 to 99")]
    Priority(i32),
    /// A spin longer than [`MAX_SPIN_US`].
    #[error("spin_us {0}: at most {MAX_SPIN_US} µs")]
    Spin(u32),
    /// A CPU this machine does not have.
    #[error("cpu {cpu} does not exist (this machine has {configured}: 0..={})", configured.saturating_sub(1))]
    NoCpu {
        /// The CPU asked for.
        cpu: usize,
        /// CPUs this machine has configured.
        configured: usize,
    },
}

impl ThreadOptions {
    /// Checks the options against what the system can do: a SCHED_FIFO priority of 1 to
    /// 99, CPUs this machine has.
    pub fn check(&self) -> Result<(), ThreadError> {
        if self.policy == SchedPolicy::Fifo && !(1..=99).contains(&self.priority) {
            return Err(ThreadError::Priority(self.priority));
        }
        if self.spin_us > MAX_SPIN_US {
            return Err(ThreadError::Spin(self.spin_us));
        }
        let configured = cpus_configured();
        if let Some(&cpu) = self.cpus.iter().find(|&&c| c >= configured) {
            return Err(ThreadError::NoCpu { cpu, configured });
        }
        Ok(())
    }
}

/// CPUs this machine has configured (online or not).
fn cpus_configured() -> usize {
    match nix::unistd::sysconf(nix::unistd::SysconfVar::_NPROCESSORS_CONF) {
        Ok(Some(n)) if n > 0 => usize::try_from(n).unwrap_or(1),
        _ => std::thread::available_parallelism().map_or(1, usize::from),
    }
}

static RT_WARNED: AtomicBool = AtomicBool::new(false);

/// Applies the thread options to the calling thread; true when SCHED_FIFO was granted.
pub(super) fn apply_thread_options(name: &str, opts: &ThreadOptions) -> bool {
    if !opts.cpus.is_empty() {
        let mut set = nix::sched::CpuSet::new();
        for &c in &opts.cpus {
            if set.set(c).is_err() {
                tracing::warn!(
                    activity = name,
                    cpu = c,
                    "CPU {c} is beyond what this system can address; ignored"
                );
            }
        }
        if let Err(e) = nix::sched::sched_setaffinity(nix::unistd::Pid::from_raw(0), &set) {
            tracing::warn!(activity = name, cpus = ?opts.cpus, "could not pin the thread to CPUs {:?}: {e}", opts.cpus);
        }
    }
    if opts.policy != SchedPolicy::Fifo {
        return false;
    }
    match set_fifo(opts.priority) {
        Ok(()) => {
            crate::spin::note_realtime();
            true
        }
        Err(e) => {
            if !RT_WARNED.swap(true, Ordering::Relaxed) {
                tracing::warn!(
                    activity = name,
                    priority = opts.priority,
                    "SCHED_FIFO at priority {} is not available ({e}); running SCHED_OTHER. \
                     Real-time scheduling needs CAP_SYS_NICE or an RLIMIT_RTPRIO of at least \
                     the priority (systemd: LimitRTPRIO=, AmbientCapabilities=CAP_SYS_NICE).",
                    opts.priority
                );
            }
            false
        }
    }
}

#[allow(unsafe_code)]
fn set_fifo(priority: i32) -> std::io::Result<()> {
    let param = libc::sched_param {
        sched_priority: priority,
    };
    // SAFETY: pthread_self() is the calling thread, and `param` is a valid sched_param
    // that outlives the call.
    let rc = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &param) };
    if rc == 0 {
        Ok(())
    } else {
        Err(std::io::Error::from_raw_os_error(rc))
    }
}

/// Bytes of stack a periodic thread touches before its first wake-up.
const PREFAULT_STACK: usize = 256 * 1024;

/// The process's memory lock: 0 not tried, 1 locked, 2 refused.
static MEMORY_LOCK: std::sync::atomic::AtomicU8 = std::sync::atomic::AtomicU8::new(0);

/// What a periodic activity's thread does before its first wake-up, as cyclictest does:
/// its timer slack at the minimum (1 ns: a SCHED_OTHER thread's sleeps are not rounded up
/// by the default 50 µs), and — for a thread that got SCHED_FIFO — its stack's first
/// [`PREFAULT_STACK`] bytes touched (no page fault in a step) and, once per process, all
/// memory locked (`mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT)`: a page touched is
/// never paged out), said once with the reason when that is refused. A SCHED_OTHER
/// periodic thread (a card's bus thread, a sampling component) does not prefault: 256 KiB
/// of resident stack each would be most of a large deployment's memory. True when the
/// process's memory is locked.
pub(super) fn prepare_periodic(name: &str, realtime: bool) -> bool {
    if let Err(e) = nix::sys::prctl::set_timerslack(1) {
        tracing::debug!(activity = name, "timer slack stays as it was: {e}");
    }
    if realtime {
        prefault_stack();
        if MEMORY_LOCK.load(Ordering::Acquire) == 0 {
            lock_memory(name);
        }
    }
    MEMORY_LOCK.load(Ordering::Acquire) == 1
}

#[inline(never)]
fn prefault_stack() {
    let mut stack = [0u8; PREFAULT_STACK];
    for page in stack.chunks_mut(4096) {
        page[0] = 1;
    }
    std::hint::black_box(&stack);
}

fn lock_memory(name: &str) {
    use nix::sys::mman::{MlockAllFlags, mlockall};
    // MCL_ONFAULT: pages are locked as they are touched, not all populated at once (which
    // stalls every thread of a large process while it runs, and fills each new thread's
    // whole stack); the real-time thread touches its own stack first.
    let flags =
        MlockAllFlags::from_bits_retain(libc::MCL_CURRENT | libc::MCL_FUTURE | libc::MCL_ONFAULT);
    let locked = mlockall(flags);
    if locked.is_ok() {
        keep_heap();
    }
    let state = if locked.is_ok() { 1 } else { 2 };
    if MEMORY_LOCK
        .compare_exchange(0, state, Ordering::AcqRel, Ordering::Acquire)
        .is_err()
    {
        return;
    }
    match locked {
        Ok(()) => tracing::info!(
            activity = name,
            "memory locked (mlockall) for real-time activities"
        ),
        Err(e) => tracing::warn!(
            activity = name,
            "memory cannot be locked ({e}): a real-time step may wait for a page fault. \
             Locking needs CAP_IPC_LOCK or an RLIMIT_MEMLOCK above the process's size \
             (systemd: LimitMEMLOCK=infinity)."
        ),
    }
}

/// Once memory is locked, glibc's allocator keeps what it has: it never gives heap back
/// (`M_TRIM_THRESHOLD` off: a `free` on any thread is not followed by `brk`/`madvise`,
/// and the next allocation does not fault a fresh page in) and serves large blocks from the
/// heap rather than a fresh `mmap` each (`M_MMAP_MAX` 0) — what real-time guides ask
/// beside `mlockall`.
#[allow(unsafe_code)]
fn keep_heap() {
    // SAFETY: mallopt only sets the allocator's parameters; it takes no pointer and any
    // value is accepted or refused (0 returned) by glibc.
    let kept = unsafe {
        libc::mallopt(libc::M_TRIM_THRESHOLD, -1) != 0 && libc::mallopt(libc::M_MMAP_MAX, 0) != 0
    };
    if !kept {
        tracing::debug!("the allocator's trim and mmap settings stay as they were");
    }
}
