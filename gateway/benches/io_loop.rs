//! A 1 kHz real-time loop that does I/O, beside cyclictest
//! (`cargo bench -p hwgw --bench io_loop`).
//!
//! The real binary runs a `scan` component on a periodic activity of 1 ms at SCHED_FIFO
//! 80. At every step it reads analog input 0 of a simulated card and of a Modbus TCP unit
//! and writes analog output 0 of both. The unit is on loopback: a second hwgw serving a
//! simulated card with `[modbus_server]`. Its line polls every 1 ms at SCHED_FIFO 70 and
//! sends the write each poll.
//!
//! `hwgw record` records every activity's steps for `IO_LOOP_SECONDS` (default 600). The
//! bench then reads the recording back and prints, for the loop:
//! - p50 / p99 / p99.9 / max wake-up lateness;
//! - the periods longer than 1.2× nominal;
//! - the steal time of the run.
//!
//! The line is woken by its own timer (a file-descriptor activity): its lateness is that of
//! its polls, from the card's counters in `status` (`poll_lateness_p99_us`, `_max_us`),
//! printed with the loop's state and counters.
//!
//! After that, cyclictest runs alone as long, at the same priority and period (`-m`, its
//! latency histogram `-h`), and the same figures come from its histogram. The lateness
//! picture (`hwgw plot --kind lateness`) and the recording are written to `IO_LOOP_DIR`
//! (default: a folder under the system's temporary one, printed).

#![allow(
    clippy::unwrap_used,
    reason = "bench code: a failed unwrap is a failed run"
)]

use std::path::Path;
use std::process::{Command, ExitCode};
use testkit::Service;

mod common;

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const PERIOD_US: u64 = 1000;
const PRIORITY: i32 = 80;

/// The loop, the simulated card and the Modbus card polling the unit at `port`.
fn deployment(port: u16) -> String {
    format!(
        r#"
cpu_dma_latency_us = 0

[[card]]
name = "sim0"
driver = "sim"
period_ms = 10
safe_analog_out = [0.0]
[card.sim]
analog_in = [{{ range = {{ lowest = -10.0, highest = 10.0, unit = "V" }}, waveform = {{ kind = "sine", amplitude = 5.0, frequency = 0.5 }} }}]
analog_out = [{{ range = {{ lowest = -10.0, highest = 10.0, unit = "V" }} }}]
{meter}
[[component]]
name = "loop"
type = "scan"
activity = {{ type = "periodic", period_ms = 1, policy = "fifo", priority = {PRIORITY} }}
properties = {{ inputs = ["sim0:0", "meter:0"], outputs = ["meter:0", "sim0:0"], gain = 0.05 }}
"#,
        meter = common::meter(port, 1, 70)
    )
}

/// Lateness figures of one run, µs.
struct Figures {
    count: u64,
    p50: f64,
    p99: f64,
    p999: f64,
    max: f64,
    /// Periods longer than 1.2× nominal.
    long: u64,
    steal_ms: u64,
}

/// The `q` quantile of a histogram of (µs, count), sorted by µs.
fn quantile(hist: &[(u64, u64)], q: f64) -> f64 {
    let total: u64 = hist.iter().map(|(_, n)| n).sum();
    let rank = ((q * total as f64) - 1e-9).ceil().max(1.0) as u64;
    let mut seen = 0;
    for (us, n) in hist {
        seen += n;
        if seen >= rank {
            return *us as f64;
        }
    }
    hist.last().map_or(0.0, |(us, _)| *us as f64)
}

/// Figures of recorded steps (lateness in ns, and the period between starts).
fn of_steps(steps: &[recording::Step], period_ns: u64, steal_ms: u64) -> Figures {
    let mut late: Vec<u64> = steps
        .iter()
        .map(|s| s.started_ns.saturating_sub(s.scheduled_ns))
        .collect();
    late.sort_unstable();
    let q = |q: f64| {
        let i = ((q * late.len() as f64) - 1e-9).ceil().max(1.0) as usize - 1;
        late.get(i).map_or(0.0, |ns| *ns as f64 / 1e3)
    };
    let long = steps
        .windows(2)
        .filter(|w| w[1].started_ns.saturating_sub(w[0].started_ns) * 5 > period_ns * 6)
        .count() as u64;
    Figures {
        count: late.len() as u64,
        p50: q(0.5),
        p99: q(0.99),
        p999: q(0.999),
        max: late.last().map_or(0.0, |ns| *ns as f64 / 1e3),
        long,
        steal_ms,
    }
}

/// cyclictest for `loops` loops at the loop's priority and period; its histogram.
fn cyclictest(loops: u64) -> Result<Figures, String> {
    let (text, steal) = testkit::bench::cyclictest(PRIORITY, PERIOD_US, loops, &["-h20000"])?;
    // `-h` prints `us count` a line, then `# Max Latencies: N` and the overflows.
    let mut hist = Vec::new();
    let mut max = None;
    let mut overflows = 0;
    for line in text.lines() {
        let mut cols = line.split_whitespace();
        match (cols.next(), cols.next(), cols.next()) {
            (Some(us), Some(n), None) if !us.starts_with('#') => {
                if let (Ok(us), Ok(n)) = (us.parse::<u64>(), n.parse::<u64>())
                    && n > 0
                {
                    hist.push((us, n));
                }
            }
            _ if line.starts_with("# Max Latencies:") => {
                max = line
                    .rsplit(':')
                    .next()
                    .and_then(|v| v.trim().parse::<u64>().ok());
            }
            _ if line.starts_with("# Histogram Overflows:") => {
                overflows = line
                    .rsplit(':')
                    .next()
                    .and_then(|v| v.trim().parse::<u64>().ok())
                    .unwrap_or(0);
            }
            _ => {}
        }
    }
    let count: u64 = hist.iter().map(|(_, n)| n).sum::<u64>() + overflows;
    if count != loops {
        return Err(format!(
            "cyclictest's histogram holds {count} loops of {loops}:\n{text}"
        ));
    }
    // A wake-up more than 0.2 periods late makes a period over 1.2× nominal (the one
    // before it).
    let long = hist
        .iter()
        .filter(|(us, _)| *us * 5 > PERIOD_US)
        .map(|(_, n)| n)
        .sum::<u64>()
        + overflows;
    Ok(Figures {
        count,
        p50: quantile(&hist, 0.5),
        p99: quantile(&hist, 0.99),
        p999: quantile(&hist, 0.999),
        max: max.ok_or("cyclictest printed no maximum")? as f64,
        long,
        steal_ms: steal,
    })
}

/// Runs the deployment and records its steps for `seconds` into `file`; the steal time.
fn record(seconds: u64, file: &Path) -> u64 {
    let unit = Service::run_text(HWGW, "io-loop-unit", common::UNIT).unwrap();
    let port = unit.wait_listening("modbus_server").port();
    let svc = Service::run_text(HWGW, "io-loop", &deployment(port)).unwrap();
    testkit::wait_until("the loop running", || {
        svc.ok(serde_json::json!({"cmd": "describe", "component": "loop"}))["state"] == "running"
    });
    let steal = testkit::bench::steal_ms();
    let out = Command::new(HWGW)
        .arg("--socket")
        .arg(&svc.socket)
        .arg("record")
        .arg(file)
        .arg(format!("--duration={seconds}s"))
        .output()
        .unwrap();
    let steal = testkit::bench::steal_ms().saturating_sub(steal);
    assert!(out.status.success(), "hwgw record: {out:?}");
    let status = svc.ok(serde_json::json!({"cmd": "status"}));
    println!("gateway status after the run: {}", status_line(&status));
    steal
}

/// The loop's and the line's state and counters from `status`, in a line.
fn status_line(status: &serde_json::Value) -> String {
    let find = |list: &str, name: &str| {
        status[list]
            .as_array()
            .and_then(|l| l.iter().find(|c| c["name"] == name).cloned())
            .unwrap_or_default()
    };
    let (scan, line) = (find("components", "loop"), find("components", "meter"));
    format!(
        "loop {} overruns {} realtime {} counters {}; line {} overruns {} realtime {}; card meter {}",
        scan["state"],
        scan["overruns"],
        scan["realtime"],
        scan["counters"],
        line["state"],
        line["overruns"],
        line["realtime"],
        find("cards", "meter")["counters"]
    )
}

fn main() -> ExitCode {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return ExitCode::SUCCESS; // `cargo test --benches` lists or smoke-runs: nothing to do.
    }
    if !testkit::bench::can_fifo(PRIORITY) {
        eprintln!("SCHED_FIFO is refused here: the bench needs it (root or CAP_SYS_NICE)");
        return ExitCode::FAILURE;
    }
    let seconds: u64 = std::env::var("IO_LOOP_SECONDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(600);
    let dir = std::env::var_os("IO_LOOP_DIR")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| std::env::temp_dir().join(format!("io-loop-{}", std::process::id())));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("io-loop.mcap");
    let _ = std::fs::remove_file(&file);
    println!(
        "1 kHz scan loop (SCHED_FIFO {PRIORITY}) over sim + Modbus TCP, {seconds} s, then cyclictest as long"
    );
    let steal = record(seconds, &file);
    let rec = recording::read::Recording::read(&file).unwrap();
    let picture = dir.join("io-loop-lateness.png");
    let _ = std::fs::remove_file(&picture);
    let plotted = Command::new(HWGW)
        .args(["plot", "--kind", "lateness", "-o"])
        .arg(&picture)
        .arg(&file)
        .output()
        .unwrap();
    assert!(plotted.status.success(), "hwgw plot: {plotted:?}");
    let theirs = match cyclictest(seconds * 1_000_000 / PERIOD_US) {
        Ok(f) => f,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
    };
    println!(
        "{:<22} {:>9} {:>8} {:>8} {:>8} {:>9} {:>7} {:>9}",
        "", "steps", "p50 µs", "p99 µs", "p99.9 µs", "max µs", ">1.2×", "steal ms"
    );
    let Some(steps) = rec.activities.iter().find(|a| a.activity == "loop") else {
        eprintln!("the recording has no steps of the loop");
        return ExitCode::FAILURE;
    };
    let rows = [
        ("hwgw loop", of_steps(&steps.steps, PERIOD_US * 1000, steal)),
        ("cyclictest", theirs),
    ];
    for (name, f) in &rows {
        println!(
            "{name:<22} {:>9} {:>8.0} {:>8.0} {:>8.0} {:>9.0} {:>7} {:>9}",
            f.count, f.p50, f.p99, f.p999, f.max, f.long, f.steal_ms
        );
    }
    let (ours, theirs) = (&rows[0].1, &rows[1].1);
    println!(
        "loop / cyclictest: p50 {:.2}, p99 {:.2}, max {:.2}",
        ours.p50 / theirs.p50.max(1.0),
        ours.p99 / theirs.p99.max(1.0),
        ours.max / theirs.max.max(1.0)
    );
    println!(
        "recording {}, picture {}",
        file.display(),
        picture.display()
    );
    ExitCode::SUCCESS
}
