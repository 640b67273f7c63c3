//! Putting an activity's thread where its options ask: CPU affinity and SCHED_FIFO, said
//! once, with the reason, when the process may not have it.

use super::{SchedPolicy, ThreadOptions};
use std::sync::atomic::{AtomicBool, Ordering};

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
        Ok(()) => true,
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
