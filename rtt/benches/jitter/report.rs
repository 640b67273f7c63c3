//! The jitter bench's settings (from the environment) and what it prints: each piece's
//! rows, what was seen around the worst periods, and the summary over the rounds.

use crate::together::Together;
use crate::{Figures, LATE_US, PERIOD_US, WITNESS_MARGIN_MS};
use testkit::stalls::{Class, Seen};

/// An environment variable's value, or `default` when unset or unreadable.
fn env<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn ratio(a: u64, b: u64) -> f64 {
    if b == 0 {
        f64::NAN
    } else {
        a as f64 / b as f64
    }
}

pub fn print_rows(run: usize, ours: &Figures, theirs: &Figures) {
    for (name, f) in [("rtt", ours), ("cyclictest", theirs)] {
        println!(
            "{:<5} {:<12} {:>8} {:>8} {:>8} {:>8} {:>9} {:>6} {:>9} {:>8}",
            run, name, f.p50, f.p99, f.p999, f.max, f.count, f.long, f.longest, f.steal_ms
        );
    }
    println!(
        "{:<5} {:<12} {:>8.2} {:>8.2} {:>8.2} {:>8.2}",
        run,
        "rtt/cyclic",
        ratio(ours.p50, theirs.p50),
        ratio(ours.p99, theirs.p99),
        ratio(ours.p999, theirs.p999),
        ratio(ours.max, theirs.max)
    );
}

pub fn print_worst(run: usize, ours: &Figures, theirs: &Figures) {
    for (name, f) in [("rtt", ours), ("cyclictest", theirs)] {
        let w = &f.worst;
        let thread = match w.thread {
            Some((faults, switches)) => format!(
                "; its thread over the half: {faults} page faults, {switches} involuntary switches"
            ),
            None => String::new(),
        };
        let steal = match w.steal_ms {
            Some(ms) => format!("steal within {WITNESS_MARGIN_MS} ms of it {ms} ms"),
            None => "steal not sampled around it".to_string(),
        };
        let rebuilt = if name == "cyclictest" {
            " (rebuilt)"
        } else {
            ""
        };
        println!(
            "{run:<5} {name:<12} longest period {} µs at {:.3} s{rebuilt}: {steal}{thread}",
            f.longest, w.at_s,
        );
    }
}

/// The ratios of a kind of piece over the rounds, and the rounds where hwgw alone had long
/// periods.
#[derive(Default)]
pub struct Tally {
    p99: Vec<f64>,
    max: Vec<f64>,
    ours_only: Vec<usize>,
    /// Each round's late wake-ups of hwgw and of cyclictest, classified (the piece
    /// together only).
    pub seen: Vec<(Seen, Seen)>,
}

impl Tally {
    pub fn add(&mut self, run: usize, ours: &Figures, theirs: &Figures) {
        self.p99.push(ratio(ours.p99, theirs.p99));
        self.max.push(ratio(ours.max, theirs.max));
        if ours.long > 0 && theirs.long == 0 {
            self.ours_only.push(run);
        }
    }

    pub fn print(&mut self, what: &str) {
        let median = |v: &mut Vec<f64>| {
            let m = testkit::bench::median(v);
            let each = v.iter().map(|r| format!("{r:.2}")).collect::<Vec<_>>();
            format!("{m:.2} (sorted: {})", each.join(", "))
        };
        let n = self.max.len();
        println!(
            "{what}: median max ratio rtt/cyclictest over {n} rounds: {}",
            median(&mut self.max)
        );
        println!(
            "{what}: median p99 ratio rtt/cyclictest over {n} rounds: {}",
            median(&mut self.p99)
        );
        if self.ours_only.is_empty() {
            println!(
                "{what}: no round where rtt had periods over 1.2× nominal and cyclictest had none"
            );
        } else {
            println!(
                "{what}: rounds where rtt had periods over 1.2× nominal and cyclictest had none: {:?}",
                self.ours_only
            );
        }
        if !self.seen.is_empty() {
            let sum = |pick: fn(&(Seen, Seen)) -> Seen| {
                self.seen
                    .iter()
                    .map(pick)
                    .fold(Seen::default(), |a, s| Seen {
                        shared: a.shared + s.shared,
                        alone: a.alone + s.alone,
                        not_compared: a.not_compared + s.not_compared,
                    })
            };
            println!(
                "{what}, wake-ups over {LATE_US} µs late over all rounds: rtt {}; cyclictest {}",
                seen_text(&sum(|s| s.0)),
                seen_text(&sum(|s| s.1))
            );
        }
    }
}

fn seen_text(s: &Seen) -> String {
    format!(
        "{} shared, {} alone, {} not compared",
        s.shared, s.alone, s.not_compared
    )
}

fn worst_text(class: Option<Class>) -> String {
    match class {
        Some(c) => format!("{c:?}"),
        None => format!("not over {LATE_US} µs late"),
    }
}

/// What the environment asks of a run (see the bench's doc).
pub struct Settings {
    pub loops: u64,
    pub priority: i32,
    pub fifo: bool,
    pub runs: usize,
    /// The halves in turn are run.
    pub apart: bool,
    /// The piece together is run.
    pub together: bool,
    /// The CPU of the piece together, and of the halves unless `JITTER_PIN=0`.
    pub cpu: usize,
    pub apart_cpu: Option<usize>,
    /// The other CPUs this process may use, where the bench's own threads and cyclictest's
    /// main thread are kept while the measured CPU runs the measured threads alone (empty:
    /// none, or `JITTER_PIN=0`).
    pub others: Vec<usize>,
}

impl Settings {
    pub fn from_env() -> Result<Settings, String> {
        let secs: u64 = env("JITTER_SECONDS", 10);
        let priority: i32 = env("JITTER_PRIORITY", 80);
        // 1: with the piece together, 0: without, 2: that piece only.
        let mode = match std::env::var("JITTER_TOGETHER").as_deref() {
            Err(_) | Ok("1") => 1,
            Ok("0") => 0,
            Ok("2") => 2,
            Ok(v) => return Err(format!("JITTER_TOGETHER is 0, 1 or 2, not {v:?}")),
        };
        let usable = usable_cpus()?;
        let cpu: usize = env("JITTER_CPU", usable[usable.len() - 1]);
        if !usable.contains(&cpu) {
            return Err(format!(
                "JITTER_CPU is {cpu}, but this process may run on CPUs {usable:?}"
            ));
        }
        let pin = env("JITTER_PIN", 1u8) != 0;
        Ok(Settings {
            loops: secs * 1_000_000 / PERIOD_US,
            priority,
            fifo: testkit::bench::can_fifo(priority),
            runs: env("JITTER_RUNS", 5),
            apart: mode != 2,
            together: mode != 0,
            cpu,
            // The halves in turn run on that CPU too, unless JITTER_PIN=0 leaves them where
            // the scheduler puts them (on this machine it put hwgw's thread on CPU 1 and
            // cyclictest's on CPU 0 in each half watched: each half met another CPU's stalls).
            apart_cpu: pin.then_some(cpu),
            others: if pin {
                usable.into_iter().filter(|&c| c != cpu).collect()
            } else {
                Vec::new()
            },
        })
    }

    /// Keeps this thread, and so every thread it starts after (the steal sampler, the
    /// runtime's own), off the measured CPU: on a kernel that does not preempt kernel code
    /// (this machine's runs `preempt=none`), a thread in a system call on that CPU holds a
    /// real-time thread's wake-up until it leaves the kernel. The measured threads pin
    /// themselves to it.
    pub fn keep_off_measured_cpu(&self) -> Result<(), String> {
        if self.others.is_empty() {
            return Ok(());
        }
        let mut set = nix::sched::CpuSet::new();
        for &c in &self.others {
            set.set(c).map_err(|e| format!("CPU {c}: {e}"))?;
        }
        nix::sched::sched_setaffinity(nix::unistd::Pid::from_raw(0), &set)
            .map_err(|e| format!("cannot keep the bench off CPU {}: {e}", self.cpu))
    }

    /// cyclictest's arguments for its main thread: on the other CPUs, as the bench's own.
    pub fn cyclictest_main(&self) -> Option<String> {
        (!self.others.is_empty()).then(|| {
            let list: Vec<String> = self.others.iter().map(ToString::to_string).collect();
            format!("--mainaffinity={}", list.join(","))
        })
    }

    pub fn print_header(&self) {
        println!(
            "periodic wake-up lateness, {} µs period, {} wake-ups each, {}",
            PERIOD_US,
            self.loops,
            if self.fifo {
                format!("SCHED_FIFO priority {}", self.priority)
            } else {
                "SCHED_OTHER (SCHED_FIFO refused here)".to_string()
            }
        );
        match self.apart_cpu {
            Some(c) => println!("the halves in turn: both on CPU {c}"),
            None => println!("the halves in turn: where the scheduler puts them"),
        }
        if !self.others.is_empty() {
            println!(
                "CPU {} runs the measured threads only; the rest of both programs on {:?}",
                self.cpu, self.others
            );
        }
        println!(
            "{:<5} {:<12} {:>8} {:>8} {:>8} {:>8} {:>9} {:>6} {:>9} {:>8}",
            "round",
            "",
            "p50 µs",
            "p99 µs",
            "p99.9 µs",
            "max µs",
            "samples",
            ">1.2×",
            "longest",
            "steal ms"
        );
    }
}

pub fn print_together(run: usize, t: &Together) {
    println!(
        "{run:<5} together on CPU {}, grids at +{} / +{} µs of each period:",
        t.cpu, t.phases.0, t.phases.1
    );
    print_rows(run, &t.ours, &t.theirs);
    println!(
        "{run:<5} together: wake-ups over {LATE_US} µs late, rtt: {}; cyclictest: {}",
        seen_text(&t.ours_seen),
        seen_text(&t.theirs_seen)
    );
    println!(
        "{run:<5} together: the most late wake-up of rtt: {}; of cyclictest: {}",
        worst_text(t.worst.0),
        worst_text(t.worst.1)
    );
}

/// The CPUs this process may run on.
fn usable_cpus() -> Result<Vec<usize>, String> {
    let set = nix::sched::sched_getaffinity(nix::unistd::Pid::from_raw(0))
        .map_err(|e| format!("cannot read this process's CPUs: {e}"))?;
    let cpus: Vec<usize> = (0..nix::sched::CpuSet::count())
        .filter(|&c| set.is_set(c).unwrap_or(false))
        .collect();
    if cpus.is_empty() {
        return Err("this process may run on no CPU".to_string());
    }
    Ok(cpus)
}
