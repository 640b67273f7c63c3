//! Periodic wake-up jitter of an rtt periodic activity, side by side with cyclictest.
//!
//! Runs a periodic activity at 1 kHz for 10 s (`JITTER_SECONDS` to change), recording how
//! late each step began, then runs `cyclictest` (Debian rt-tests, with `-m`: memory locked,
//! as the activity locks it) for the same number of loops at the same interval, priority
//! and policy, and prints p50, p99, p99.9 and max of both and their ratios; five runs in a
//! row (`JITTER_RUNS`), then the median of the p99 ratios. Both hold `/dev/cpu_dma_latency` at 0 while they run (cyclictest's
//! default; the runtime's `cpu_dma_latency_us` option). Both ask for SCHED_FIFO at `JITTER_PRIORITY` (default 80); when
//! the machine refuses it, both run SCHED_OTHER, and the output says so.
//!
//! Run: `cargo bench -p rtt --bench jitter`.

#![allow(
    clippy::unwrap_used,
    reason = "benchmark setup: a failed unwrap aborts the run"
)]

use device_interface::Registry;
use hdrhistogram::Histogram;
use rtt::activity::{ActivitySpec, SchedPolicy, ThreadOptions, Timing};
use rtt::{Component, Context, HookResult, Runtime, RuntimeOptions};
use std::process::{Command, ExitCode};
use std::sync::{Arc, Mutex};
use std::time::Duration;

const PERIOD_US: u64 = 1000;

struct Probe {
    hist: Arc<Mutex<Histogram<u64>>>,
}

impl Component for Probe {
    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        // Lateness in µs, floored, as cyclictest reports it. The histogram is pre-sized and
        // never resizes, and nothing else holds the lock while the activity runs.
        let us = ctx.timing().lateness().as_micros() as u64;
        if let Ok(mut h) = self.hist.try_lock() {
            let _ = h.record(us.min(1_000_000));
        }
        Ok(())
    }
}

struct Figures {
    p50: u64,
    p99: u64,
    p999: u64,
    max: u64,
    count: u64,
}

fn figures(h: &Histogram<u64>) -> Figures {
    Figures {
        p50: h.value_at_quantile(0.5),
        p99: h.value_at_quantile(0.99),
        p999: h.value_at_quantile(0.999),
        max: h.max(),
        count: h.len(),
    }
}

fn run_rtt(loops: u64, fifo: bool, priority: i32) -> Figures {
    let hist = Arc::new(Mutex::new(
        Histogram::<u64>::new_with_bounds(1, 1_000_000, 3).unwrap(),
    ));
    // The same CPU-latency request cyclictest makes by default (/dev/cpu_dma_latency = 0).
    let options = RuntimeOptions {
        cpu_dma_latency_us: Some(0),
        ..RuntimeOptions::default()
    };
    let rt = Runtime::new(Arc::new(Registry::new()), options).unwrap();
    let spec = ActivitySpec::Periodic {
        period: Duration::from_micros(PERIOD_US),
        thread: ThreadOptions {
            policy: if fifo {
                SchedPolicy::Fifo
            } else {
                SchedPolicy::Other
            },
            priority,
            cpus: Vec::new(),
            ..ThreadOptions::default()
        },
        timing: Timing::Absolute,
        max_overruns: None,
    };
    let h = hist.clone();
    let t = rt
        .add("jitter", spec, rtt::InitialState::Stopped, move |_| {
            Ok(Probe { hist: h })
        })
        .unwrap();
    t.start().unwrap();
    while t.stats().steps < loops {
        std::thread::sleep(Duration::from_millis(50));
    }
    t.stop().unwrap();
    let stats = t.stats();
    if fifo && !stats.realtime {
        eprintln!("warning: the activity did not get SCHED_FIFO");
    }
    let h = hist.lock().unwrap();
    figures(&h)
}

fn run_cyclictest(loops: u64, fifo: bool, priority: i32) -> Result<Figures, String> {
    testkit::peers::require(&testkit::peers::CYCLICTEST).map_err(|e| e.to_string())?;
    let prio = if fifo { priority } else { 0 };
    let out = Command::new("cyclictest")
        .args([
            "-t1",
            &format!("-p{prio}"),
            &format!("-i{PERIOD_US}"),
            &format!("-l{loops}"),
            "-q",
            "-m",
            "-h2000",
        ])
        .args(if fifo {
            vec!["--policy=fifo"]
        } else {
            vec!["--policy=other"]
        })
        .output()
        .map_err(|e| format!("cannot run cyclictest: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "cyclictest failed: {}",
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let mut h = Histogram::<u64>::new_with_bounds(1, 1_000_000, 3).unwrap();
    let mut max_line = None;
    for line in text.lines() {
        let mut cols = line.split_whitespace();
        match (cols.next(), cols.next()) {
            (Some(us), Some(n)) if us.chars().all(|c| c.is_ascii_digit()) => {
                let (us, n): (u64, u64) = (us.parse().unwrap_or(0), n.parse().unwrap_or(0));
                if n > 0 {
                    h.record_n(us.max(1), n).map_err(|e| e.to_string())?;
                }
            }
            _ if line.starts_with("# Max Latencies:") => {
                max_line = line
                    .split(':')
                    .nth(1)
                    .and_then(|v| v.trim().parse::<u64>().ok());
            }
            _ => {}
        }
    }
    let mut f = figures(&h);
    if let Some(m) = max_line {
        f.max = m;
    }
    Ok(f)
}

fn main() -> ExitCode {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return ExitCode::SUCCESS; // `cargo test --benches` lists or smoke-runs: nothing to do.
    }
    let secs: u64 = std::env::var("JITTER_SECONDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(10);
    let priority: i32 = std::env::var("JITTER_PRIORITY")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(80);
    let loops = secs * 1_000_000 / PERIOD_US;
    let fifo = testkit::bench::can_fifo(priority);
    println!(
        "periodic wake-up lateness, {} µs period, {loops} wake-ups each, {}",
        PERIOD_US,
        if fifo {
            format!("SCHED_FIFO priority {priority}")
        } else {
            "SCHED_OTHER (SCHED_FIFO refused here)".to_string()
        }
    );
    let runs: usize = std::env::var("JITTER_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(5);
    let ratio = |a: u64, b: u64| {
        if b == 0 {
            f64::NAN
        } else {
            a as f64 / b as f64
        }
    };
    println!(
        "{:<5} {:<12} {:>8} {:>8} {:>8} {:>8} {:>9}",
        "run", "", "p50 µs", "p99 µs", "p99.9 µs", "max µs", "samples"
    );
    let mut p99_ratios = Vec::new();
    for run in 1..=runs.max(1) {
        // The two in turn, each run: a machine that gets busier or quieter over the runs
        // weighs on both alike.
        let ours = run_rtt(loops, fifo, priority);
        let theirs = match run_cyclictest(loops, fifo, priority) {
            Ok(f) => f,
            Err(e) => {
                eprintln!("{e}");
                return ExitCode::FAILURE;
            }
        };
        for (name, f) in [("rtt", &ours), ("cyclictest", &theirs)] {
            println!(
                "{:<5} {:<12} {:>8} {:>8} {:>8} {:>8} {:>9}",
                run, name, f.p50, f.p99, f.p999, f.max, f.count
            );
        }
        let r99 = ratio(ours.p99, theirs.p99);
        println!(
            "{:<5} {:<12} {:>8.2} {:>8.2} {:>8.2} {:>8.2}",
            run,
            "rtt/cyclic",
            ratio(ours.p50, theirs.p50),
            r99,
            ratio(ours.p999, theirs.p999),
            ratio(ours.max, theirs.max)
        );
        p99_ratios.push(r99);
    }
    p99_ratios.sort_by(f64::total_cmp);
    println!(
        "median p99 ratio rtt/cyclictest over {} runs: {:.2} (each: {})",
        p99_ratios.len(),
        p99_ratios[p99_ratios.len() / 2],
        p99_ratios
            .iter()
            .map(|r| format!("{r:.2}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    ExitCode::SUCCESS
}
