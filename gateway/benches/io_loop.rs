//! A 1 kHz real-time loop that does I/O, beside cyclictest
//! (`cargo bench -p hwgw --bench io_loop`).
//!
//! The real binary runs a `scan` component on a periodic activity of 1 ms at SCHED_FIFO
//! 80. At every step it reads analog input 0 of a simulated card and of a Modbus TCP unit
//! and writes analog output 0 of both. The unit is on loopback: a second hwgw serving a
//! simulated card with `[modbus_server]`. Its line polls every 1 ms at SCHED_FIFO 70 and
//! sends the write each poll.
//!
//! The bench alternates, as the jitter bench does, so that the host's stalls (steal) fall
//! on both alike: `IO_LOOP_ROUNDS` rounds (default 10) of `IO_LOOP_SECONDS` each (default
//! 60, so ten minutes of the loop). In each round `hwgw record` records every activity's
//! steps while the loop runs; then the loop is stopped and cyclictest runs as long at the
//! same priority and period (`-m`, its latency histogram `-h`), with the rest of the
//! deployment still running: the line polling the unit every 1 ms, the unit answering. So
//! cyclictest meets the same background I/O, less the writes the loop would send. Per
//! round and pooled over all, for both: p50 / p99 / p99.9 / max wake-up lateness, the
//! periods longer than 1.2× nominal, the steal time; then the median ratio of the maxima
//! and the rounds where the loop had long periods and cyclictest had none.
//!
//! The line is woken by its own timer (a file-descriptor activity): its lateness is that of
//! its polls, from the card's counters in `status` (`poll_lateness_p99_us`, `_max_us`),
//! printed with the loop's state and counters.
//!
//! The lateness picture (`hwgw plot --kind lateness`) of the round whose loop maximum is the
//! median, and that round's recording, are written to `IO_LOOP_DIR` (default: a folder
//! under the system's temporary one, printed).

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

/// Figures of lateness values (ns, sorted), with `long` periods over 1.2× nominal.
fn of_lateness(late: &[u64], long: u64, steal_ms: u64) -> Figures {
    let q = |q: f64| {
        let i = ((q * late.len() as f64) - 1e-9).ceil().max(1.0) as usize - 1;
        late.get(i).map_or(0.0, |ns| *ns as f64 / 1e3)
    };
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

/// The lateness (ns, sorted) of recorded steps, and their periods over 1.2× nominal.
fn of_steps(steps: &[recording::Step], period_ns: u64) -> (Vec<u64>, u64) {
    let mut late: Vec<u64> = steps
        .iter()
        .map(|s| s.started_ns.saturating_sub(s.scheduled_ns))
        .collect();
    late.sort_unstable();
    let long = steps
        .windows(2)
        .filter(|w| w[1].started_ns.saturating_sub(w[0].started_ns) * 5 > period_ns * 6)
        .count() as u64;
    (late, long)
}

/// cyclictest's histogram: (µs, count) with counts, the loops past its end, its maximum.
struct Histogram {
    buckets: Vec<(u64, u64)>,
    overflows: u64,
    max: u64,
}

impl Histogram {
    fn figures(&self, steal_ms: u64) -> Figures {
        let count = self.buckets.iter().map(|(_, n)| n).sum::<u64>() + self.overflows;
        // A wake-up more than 0.2 periods late makes a period over 1.2× nominal (the one
        // before it).
        let long = self
            .buckets
            .iter()
            .filter(|(us, _)| *us * 5 > PERIOD_US)
            .map(|(_, n)| n)
            .sum::<u64>()
            + self.overflows;
        Figures {
            count,
            p50: quantile(&self.buckets, 0.5),
            p99: quantile(&self.buckets, 0.99),
            p999: quantile(&self.buckets, 0.999),
            max: self.max as f64,
            long,
            steal_ms,
        }
    }

    /// `other`'s counts added to these.
    fn add(&mut self, other: &Histogram) {
        let mut all: std::collections::BTreeMap<u64, u64> = self.buckets.iter().copied().collect();
        for (us, n) in &other.buckets {
            *all.entry(*us).or_default() += n;
        }
        self.buckets = all.into_iter().collect();
        self.overflows += other.overflows;
        self.max = self.max.max(other.max);
    }
}

/// cyclictest for `loops` loops at the loop's priority and period: its histogram and the
/// steal time while it ran.
fn cyclictest(loops: u64) -> Result<(Histogram, u64), String> {
    let (text, steal) = testkit::bench::cyclictest(PRIORITY, PERIOD_US, loops, &["-h20000"])?;
    // `-h` prints `us count` a line, then `# Max Latencies: N` and the overflows.
    let number = |line: &str| {
        line.rsplit(':')
            .next()
            .and_then(|v| v.trim().parse::<u64>().ok())
    };
    let mut h = Histogram {
        buckets: Vec::new(),
        overflows: 0,
        max: 0,
    };
    let mut max = None;
    for line in text.lines() {
        let mut cols = line.split_whitespace();
        match (cols.next(), cols.next(), cols.next()) {
            (Some(us), Some(n), None) if !us.starts_with('#') => {
                if let (Ok(us), Ok(n)) = (us.parse::<u64>(), n.parse::<u64>())
                    && n > 0
                {
                    h.buckets.push((us, n));
                }
            }
            _ if line.starts_with("# Max Latencies:") => max = number(line),
            _ if line.starts_with("# Histogram Overflows:") => {
                h.overflows = number(line).unwrap_or(0);
            }
            _ => {}
        }
    }
    h.max = max.ok_or("cyclictest printed no maximum")?;
    let count: u64 = h.buckets.iter().map(|(_, n)| n).sum::<u64>() + h.overflows;
    if count != loops {
        return Err(format!(
            "cyclictest's histogram holds {count} loops of {loops}:\n{text}"
        ));
    }
    Ok((h, steal))
}

/// Asks the gateway to `cmd` (start, stop) the loop.
fn lifecycle(svc: &Service, cmd: &str) {
    svc.ok(serde_json::json!({"cmd": cmd, "component": "loop"}));
}

/// Records the running deployment's steps for `seconds` into `file`; the steal time.
fn record(svc: &Service, seconds: u64, file: &Path) -> u64 {
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

fn env(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn row(name: &str, f: &Figures) {
    println!(
        "{name:<24} {:>9} {:>8.0} {:>8.0} {:>8.0} {:>9.0} {:>7} {:>9}",
        f.count, f.p50, f.p99, f.p999, f.max, f.long, f.steal_ms
    );
}

fn main() -> ExitCode {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return ExitCode::SUCCESS; // `cargo test --benches` lists or smoke-runs: nothing to do.
    }
    if !testkit::bench::can_fifo(PRIORITY) {
        eprintln!("SCHED_FIFO is refused here: the bench needs it (root or CAP_SYS_NICE)");
        return ExitCode::FAILURE;
    }
    let (rounds, seconds) = (env("IO_LOOP_ROUNDS", 10), env("IO_LOOP_SECONDS", 60));
    let dir = std::env::var_os("IO_LOOP_DIR")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| std::env::temp_dir().join(format!("io-loop-{}", std::process::id())));
    std::fs::create_dir_all(&dir).unwrap();
    println!(
        "1 kHz scan loop (SCHED_FIFO {PRIORITY}) over sim + Modbus TCP, {rounds} rounds of {seconds} s, each then cyclictest as long"
    );
    let unit = Service::run_text(HWGW, "io-loop-unit", common::UNIT).unwrap();
    let port = unit.wait_listening("modbus_server").port();
    let svc = Service::run_text(HWGW, "io-loop", &common::scan_loop(port, PRIORITY)).unwrap();
    testkit::wait_until("the loop running", || {
        svc.ok(serde_json::json!({"cmd": "describe", "component": "loop"}))["state"] == "running"
    });
    println!(
        "{:<24} {:>9} {:>8} {:>8} {:>8} {:>9} {:>7} {:>9}",
        "", "steps", "p50 µs", "p99 µs", "p99.9 µs", "max µs", ">1.2×", "steal ms"
    );
    let (mut all_late, mut all_long, mut all_steal) = (Vec::new(), 0, 0);
    let mut theirs_all = Histogram {
        buckets: Vec::new(),
        overflows: 0,
        max: 0,
    };
    let mut their_steal = 0;
    let mut rounds_seen = Vec::new();
    for r in 1..=rounds {
        if r > 1 {
            lifecycle(&svc, "start");
        }
        let file = dir.join(format!("io-loop-{r}.mcap"));
        let _ = std::fs::remove_file(&file);
        let steal = record(&svc, seconds, &file);
        lifecycle(&svc, "stop");
        let rec = recording::read::Recording::read(&file).unwrap();
        let Some(steps) = rec.activities.iter().find(|a| a.activity == "loop") else {
            eprintln!("round {r}: the recording has no steps of the loop");
            return ExitCode::FAILURE;
        };
        let (late, long) = of_steps(&steps.steps, PERIOD_US * 1000);
        let ours = of_lateness(&late, long, steal);
        let (hist, steal_c) = match cyclictest(seconds * 1_000_000 / PERIOD_US) {
            Ok(h) => h,
            Err(e) => {
                eprintln!("{e}");
                return ExitCode::FAILURE;
            }
        };
        let theirs = hist.figures(steal_c);
        row(&format!("round {r} hwgw loop"), &ours);
        row(&format!("round {r} cyclictest"), &theirs);
        all_late.extend_from_slice(&late);
        all_long += long;
        all_steal += steal;
        theirs_all.add(&hist);
        their_steal += steal_c;
        rounds_seen.push((r, ours, theirs, file));
    }
    println!(
        "gateway status after the run: {}",
        status_line(&svc.ok(serde_json::json!({"cmd": "status"})))
    );
    all_late.sort_unstable();
    println!("all rounds:");
    row("hwgw loop", &of_lateness(&all_late, all_long, all_steal));
    row("cyclictest", &theirs_all.figures(their_steal));
    let mut ratios: Vec<f64> = rounds_seen
        .iter()
        .map(|(_, o, t, _)| o.max / t.max.max(1.0))
        .collect();
    let n = ratios.len();
    let median = testkit::bench::median(&mut ratios);
    println!("median max ratio loop/cyclictest over {n} rounds: {median:.2} (sorted {ratios:.2?})");
    let alone: Vec<u64> = rounds_seen
        .iter()
        .filter(|(_, o, t, _)| o.long > 0 && t.long == 0)
        .map(|(r, ..)| *r)
        .collect();
    println!(
        "rounds where the loop had periods over 1.2× nominal and cyclictest had none: {alone:?}"
    );
    // The picture: the round whose loop maximum is the median.
    let mut by_max: Vec<&(u64, Figures, Figures, std::path::PathBuf)> =
        rounds_seen.iter().collect();
    by_max.sort_by(|a, b| a.1.max.total_cmp(&b.1.max));
    let (r, _, _, file) = by_max[by_max.len() / 2];
    let picture = dir.join("io-loop-lateness.png");
    let _ = std::fs::remove_file(&picture);
    let plotted = Command::new(HWGW)
        .args(["plot", "--kind", "lateness", "-o"])
        .arg(&picture)
        .arg(file)
        .output()
        .unwrap();
    assert!(plotted.status.success(), "hwgw plot: {plotted:?}");
    for (other, _, _, f) in &rounds_seen {
        if other != r {
            let _ = std::fs::remove_file(f);
        }
    }
    println!(
        "picture of round {r}: {}, its recording {}",
        picture.display(),
        file.display()
    );
    ExitCode::SUCCESS
}
