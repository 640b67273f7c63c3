//! What recording costs, side by side in one run (`cargo bench -p hwgw --bench recorder`):
//!
//! 1. A 1 kHz component writing 100 f64 output ports each step (SCHED_FIFO 80 when
//!    allowed): wake-up lateness and step time p50/p99 without a recorder (the reference)
//!    and with the `recorder` component recording all 100 ports and the component's steps
//!    into an MCAP file, in turns (A B A B), and the ratios.
//! 2. The highest sample rate recorded without loss: the same component writing K samples
//!    per port per step (100 000·K samples/s), K rising until the recording counts a loss;
//!    beside it, the rate at which the same MCAP writer takes the same samples in a tight
//!    loop with no runtime (the reference), and the ratio.
//!
//! `BENCH_SECONDS` (default 5) sets each turn of part 1; part 2 runs 3 s per K.

use device_interface::Registry;
use hdrhistogram::Histogram;
use recording::{Closing, Item, Options, PortSpec, Recorder};
use rtt::activity::{ActivitySpec, SchedPolicy, StepRecord, ThreadOptions, Timing};
use rtt::port::OutputPort;
use rtt::{Component, Context, HookResult, Runtime, RuntimeOptions, TaskContext};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

const PORTS: usize = 100;

struct Source {
    ports: Vec<OutputPort<f64>>,
    per_step: usize,
    n: u64,
}

impl Component for Source {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        for _ in 0..self.per_step {
            let v = self.n as f64;
            for p in &mut self.ports {
                p.write(&v);
            }
            self.n += 1;
        }
        Ok(())
    }
}

fn source(rt: &Runtime, per_step: usize, fifo: bool) -> TaskContext {
    let spec = ActivitySpec::Periodic {
        period: Duration::from_millis(1),
        thread: ThreadOptions {
            policy: if fifo {
                SchedPolicy::Fifo
            } else {
                SchedPolicy::Other
            },
            priority: 80,
            ..ThreadOptions::default()
        },
        timing: Timing::Absolute,
        max_overruns: None,
    };
    rt.add("src", spec, rtt::InitialState::Stopped, move |iface| {
        let mut ports = Vec::with_capacity(PORTS);
        for i in 0..PORTS {
            ports.push(iface.output(&format!("ch{i}"), "a channel")?);
        }
        Ok(Source {
            ports,
            per_step,
            n: 0,
        })
    })
    .expect("the source component")
}

fn recorder(rt: &Runtime, file: &std::path::Path, buffer: u32) -> TaskContext {
    let spec = ActivitySpec::Periodic {
        period: Duration::from_millis(20),
        thread: ThreadOptions::default(),
        timing: Timing::Absolute,
        max_overruns: None,
    };
    let t = hwgw::components::ComponentTypes::builtin()
        .build(rt, "rec", "recorder", spec)
        .expect("the recorder")
        .expect("a built-in type");
    let p = t.properties();
    let set = |k: &str, v: serde_json::Value| p.set_value(k, v).expect("a property");
    set("ports", serde_json::json!(["src"]));
    set("activities", serde_json::json!(["src"]));
    set(
        "file",
        serde_json::json!(file.to_str().expect("a UTF-8 path")),
    );
    set("buffer", serde_json::json!(buffer));
    t.configure().expect("configure the recorder");
    t
}

struct Turn {
    lateness: Histogram<u64>,
    step: Histogram<u64>,
    meta: std::collections::BTreeMap<String, String>,
    overruns: u64,
}

fn turn(per_step: usize, fifo: bool, record: Option<(&std::path::Path, u32)>, secs: f64) -> Turn {
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).expect("runtime");
    let src = source(&rt, per_step, fifo);
    let tap = src.activity().tap_steps(1 << 20);
    let rec = record.map(|(f, b)| recorder(&rt, f, b));
    if let Some(r) = &rec {
        r.start().expect("start the recorder");
    }
    src.start().expect("start the source");
    let end = Instant::now() + Duration::from_secs_f64(secs);
    let mut lateness = Histogram::<u64>::new_with_bounds(1, 1_000_000_000, 3).expect("histogram");
    let mut step = lateness.clone();
    let mut steps: Vec<StepRecord> = Vec::new();
    while Instant::now() < end {
        std::thread::sleep(Duration::from_millis(100));
        steps.clear();
        tap.drain(&mut steps);
        for s in &steps {
            let _ = lateness.record(s.lateness_ns().max(1));
            let _ = step.record(s.duration_ns().max(1));
        }
    }
    src.stop().expect("stop the source");
    let overruns = src.stats().overruns;
    let mut meta = Default::default();
    if let (Some(r), Some((f, _))) = (rec, record) {
        r.stop().expect("stop the recorder");
        meta = recording::read::Recording::read(f)
            .expect("the recording")
            .metadata;
        let _ = std::fs::remove_file(f);
    }
    Turn {
        lateness,
        step,
        meta,
        overruns,
    }
}

fn us(h: &Histogram<u64>, q: f64) -> f64 {
    h.value_at_quantile(q) as f64 / 1e3
}

/// Samples per second the MCAP writer takes in a tight loop (no runtime, no buffers).
fn writer_rate(dir: &std::path::Path) -> f64 {
    let ports: Vec<PortSpec> = (0..PORTS)
        .map(|i| PortSpec {
            name: format!("src.ch{i}"),
            type_name: "f64".into(),
        })
        .collect();
    let file = dir.join("reference.mcap");
    let mut r = Recorder::create(&file, ports, vec![], Options::default()).expect("reference file");
    let n = 2_000_000u64;
    let start = Instant::now();
    for k in 0..n {
        let item = Item::Sample {
            port: (k % PORTS as u64) as u32,
            at_ns: k,
            value: serde_json::json!(k as f64),
        };
        r.write(&item, k).expect("write");
    }
    r.finish(&Closing::default()).expect("finish");
    let rate = n as f64 / start.elapsed().as_secs_f64();
    let _ = std::fs::remove_file(&file);
    rate
}

fn main() -> ExitCode {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return ExitCode::SUCCESS; // `cargo test --benches` lists or smoke-runs: nothing to do.
    }
    let secs: f64 = std::env::var("BENCH_SECONDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(5.0);
    let fifo = testkit::bench::can_fifo(80);
    let dir = testkit::TempDir::new("bench-recorder");
    let file = dir.path().join("bench.mcap");
    part1(fifo, secs, &file);
    part2(fifo, dir.path(), &file);
    ExitCode::SUCCESS
}

/// A 1 kHz component with and without recording, in turns.
fn part1(fifo: bool, secs: f64, file: &std::path::Path) {
    println!(
        "1. a 1 kHz component writing {PORTS} f64 ports, {} ({secs} s a turn)",
        if fifo {
            "SCHED_FIFO 80"
        } else {
            "SCHED_OTHER (SCHED_FIFO refused here)"
        }
    );
    println!(
        "{:<6} {:<14} {:>9} {:>9} {:>9} {:>9} {:>9} {:>6}",
        "turn", "", "late p50", "late p99", "step p50", "step p99", "messages", "lost"
    );
    let mut rows = Vec::new();
    for round in 1..=2 {
        for rec in [false, true] {
            let t = turn(1, fifo, rec.then_some((file, 4096)), secs);
            let m = |k: &str| t.meta.get(k).cloned().unwrap_or_else(|| "-".into());
            println!(
                "{:<6} {:<14} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>9} {:>6}",
                round,
                if rec { "recording" } else { "no recorder" },
                us(&t.lateness, 0.5),
                us(&t.lateness, 0.99),
                us(&t.step, 0.5),
                us(&t.step, 0.99),
                m("messages"),
                m("lost"),
            );
            rows.push(t);
        }
    }
    let q = |i: usize, f: &dyn Fn(&Turn) -> f64| f(&rows[i]);
    for (name, f) in [
        (
            "lateness p50",
            &(|t: &Turn| us(&t.lateness, 0.5)) as &dyn Fn(&Turn) -> f64,
        ),
        ("lateness p99", &|t: &Turn| us(&t.lateness, 0.99)),
        ("step p50", &|t: &Turn| us(&t.step, 0.5)),
        ("step p99", &|t: &Turn| us(&t.step, 0.99)),
    ] {
        println!(
            "recording / no recorder, {name}: {:.2} and {:.2}",
            q(1, f) / q(0, f),
            q(3, f) / q(2, f)
        );
    }
}

/// The highest sample rate recorded without loss, beside the MCAP writer alone.
fn part2(fifo: bool, dir: &std::path::Path, file: &std::path::Path) {
    println!(
        "\n2. samples/s recorded without loss (the recorder at 20 ms; buffers of 2^20 samples in all)"
    );
    // The best of three: the first runs on a cold file and CPU.
    let reference = (0..3).map(|_| writer_rate(dir)).fold(0.0, f64::max);
    println!("reference: the MCAP writer alone takes {reference:.0} samples/s (best of 3)");
    println!(
        "{:>6} {:>12} {:>10} {:>10} {:>9} {:>9}",
        "K", "samples/s", "messages", "lost", "overruns", "ratio"
    );
    let mut best = 0.0;
    for k in [1usize, 2, 5, 10, 20, 30, 40, 50, 100] {
        let t = turn(k, fifo, Some((file, 40_000)), 3.0);
        let rate = (PORTS * k * 1000) as f64;
        let lost: u64 = t
            .meta
            .get("lost")
            .and_then(|v| v.parse().ok())
            .unwrap_or(u64::MAX);
        let over: u64 = t
            .meta
            .get("over_limit")
            .and_then(|v| v.parse().ok())
            .unwrap_or(u64::MAX);
        println!(
            "{:>6} {:>12.0} {:>10} {:>10} {:>9} {:>9.2}",
            k,
            rate,
            t.meta.get("messages").map_or("-", String::as_str),
            lost.saturating_add(over),
            t.overruns,
            rate / reference
        );
        // More than 1 % of its steps late by a period: the source, not the recorder, is
        // the limit from here on.
        if t.overruns > 30 {
            println!("the source overran its 1 ms period: it, not the recorder, is the limit here");
            break;
        }
        if lost == 0 && over == 0 {
            best = rate;
        } else {
            break;
        }
    }
    println!(
        "highest rate recorded without loss: {best:.0} samples/s ({:.2}× the writer alone)",
        best / reference
    );
}
