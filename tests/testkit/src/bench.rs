//! What the bench binaries that compare hwgw with a bare reference share: timing a number
//! of cycles that each count their operations, and averaging interleaved rounds.

use std::time::Instant;

/// (operations per second, µs per cycle) of `cycles` cycles of `f`, which returns how many
/// operations (transfers, samples) it made.
pub fn rate(cycles: u32, mut f: impl FnMut() -> u64) -> (f64, f64) {
    let start = Instant::now();
    let mut ops = 0;
    for _ in 0..cycles {
        ops += f();
    }
    let s = start.elapsed().as_secs_f64();
    (ops as f64 / s, s * 1e6 / f64::from(cycles.max(1)))
}

/// The mean of `v` (NaN when empty).
pub fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = v.fold((0.0, 0.0), |(s, n), x| (s + x, n + 1.0));
    sum / n
}

/// Sorts `v` and returns its median (the mean of the middle two for an even count; NaN
/// when empty): the benches' summary of ratios over rounds.
pub fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    match n {
        0 => f64::NAN,
        _ if n.is_multiple_of(2) => (v[n / 2 - 1] + v[n / 2]) / 2.0,
        _ => v[n / 2],
    }
}

/// Whether this process may run a thread SCHED_FIFO at `priority` (tried on a short-lived
/// thread of its own).
pub fn can_fifo(priority: i32) -> bool {
    std::thread::spawn(move || fifo_here(priority))
        .join()
        .unwrap_or(false)
}

/// Runs the calling thread SCHED_FIFO at `priority` from now on, if this process may
/// (root, or CAP_SYS_NICE): a test's peer that timestamps what it receives is then not
/// delayed by a loaded machine's other work. Whether it took.
pub fn fifo_here(priority: i32) -> bool {
    let p = libc::sched_param {
        sched_priority: priority,
    };
    #[allow(unsafe_code, reason = "pthread_setschedparam has no safe wrapper")]
    // SAFETY: sets the calling thread's own policy with a valid param.
    let rc = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &p) };
    rc == 0
}

/// A process's CPU time so far (user and system, its threads included) and its resident
/// memory now, from `/proc`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProcUsage {
    /// CPU seconds.
    pub cpu_s: f64,
    /// Resident set, KiB.
    pub rss_kib: u64,
}

impl ProcUsage {
    /// The CPU this process used between `earlier` and this reading, `seconds` apart, as a
    /// % of one core.
    pub fn cpu_percent_since(self, earlier: ProcUsage, seconds: f64) -> f64 {
        (self.cpu_s - earlier.cpu_s) / seconds * 100.0
    }
}

/// A simulated card `big` of `channels` analog inputs, each new noise every 100 ms: the
/// northbound servers' benchmarks' load (`channels` values changing at 10 Hz).
pub fn noise_card(channels: u32) -> String {
    format!(
        r#"
[[card]]
name = "big"
driver = "sim"
period_ms = 100
sample_period_ms = 100

[card.sim]
seed = 7

[[card.sim.analog_in]]
count = {channels}
range = {{ lowest = -10.0, highest = 10.0, unit = "V" }}
waveform = {{ kind = "noise", mean = 0.0, amplitude = 5.0 }}
"#
    )
}

/// [`ProcUsage`] of process `pid`; `None` when it is gone.
pub fn proc_usage(pid: u32) -> Option<ProcUsage> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command's closing parenthesis: utime and stime are the 12th and
    // 13th of them.
    let rest = stat.rsplit_once(')')?.1;
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    #[allow(unsafe_code, reason = "sysconf has no safe wrapper")]
    // SAFETY: sysconf reads a constant of the system.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as f64;
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let rss_kib = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())?;
    Some(ProcUsage {
        cpu_s: ticks / hz.max(1.0),
        rss_kib,
    })
}

/// CPU time the hypervisor took from this machine so far (steal, summed over the CPUs),
/// ms; 0 where `/proc/stat` does not say. It counts in ticks of 10 ms.
pub fn steal_ms() -> u64 {
    std::fs::read_to_string("/proc/stat")
        .ok()
        .and_then(|s| {
            s.lines()
                .next()
                .and_then(|l| l.split_whitespace().nth(8))
                .and_then(|v| v.parse::<u64>().ok())
        })
        .map_or(0, |ticks| ticks * 10)
}

/// Runs cyclictest (Debian rt-tests, installed when missing): one thread, at SCHED_FIFO
/// `priority` (0: SCHED_OTHER), every `period_us`, for `loops` loops, quiet, with memory
/// locked (`-q -m`) and `extra`. Its standard output, and the steal time while it ran (ms).
pub fn cyclictest(
    priority: i32,
    period_us: u64,
    loops: u64,
    extra: &[&str],
) -> Result<(String, u64), String> {
    crate::peers::require(&crate::peers::CYCLICTEST).map_err(|e| e.to_string())?;
    let policy = if priority > 0 {
        "--policy=fifo"
    } else {
        "--policy=other"
    };
    let steal = steal_ms();
    let out = std::process::Command::new("cyclictest")
        .args([
            "-t1",
            &format!("-p{priority}"),
            &format!("-i{period_us}"),
            &format!("-l{loops}"),
            "-q",
            "-m",
            policy,
        ])
        .args(extra)
        .output()
        .map_err(|e| format!("cannot run cyclictest: {e}"))?;
    let steal = steal_ms().saturating_sub(steal);
    if !out.status.success() {
        return Err(format!(
            "cyclictest failed: {}",
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    Ok((String::from_utf8_lossy(&out.stdout).into_owned(), steal))
}

#[cfg(test)]
mod tests {
    #[test]
    fn median_of_odd_even_and_no_values() {
        assert_eq!(super::median(&mut [3.0, 1.0, 2.0]), 2.0);
        assert_eq!(super::median(&mut [4.0, 1.0, 3.0, 2.0]), 2.5);
        assert!(super::median(&mut []).is_nan());
    }
}
