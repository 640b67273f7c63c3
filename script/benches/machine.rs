//! The script component's step under SCHED_FIFO, beside the same logic in Rust.
//!
//! A 10-state machine with 20 transitions and 4 port reads/writes a step (machine.lua),
//! stepped at 1 kHz for 60 s (`SCRIPT_BENCH_SECONDS` to change) from a SCHED_FIFO
//! periodic activity (priority `SCRIPT_BENCH_PRIORITY`, default 80; SCHED_OTHER, said so,
//! where the machine refuses it): each step of the subject is timed around its whole
//! engine step (the script's update, its machine, the collector's step between steps).
//! Then the same script formatting a string each step (garbage for the collector), then
//! the same logic as a Rust component, in the same run, the same way. Printed: step time
//! p50/p99/p99.9/max of each and the scripts' ratios to Rust, the collector's time, the
//! script's overruns (max_step_us = 1000) and the driving activity's, and each subject's
//! mean step back to back with warm caches.
//!
//! Run: `cargo bench -p script --bench machine`. Goal on the project's 2-core machine:
//! the script's p99 ≤ 20 µs, no overrun.

#![allow(
    clippy::unwrap_used,
    reason = "benchmark setup: a failed unwrap aborts the run"
)]

use device_interface::Registry;
use hdrhistogram::Histogram;
use rtt::activity::{ActivitySpec, SchedPolicy, ThreadOptions, Timing};
use rtt::port::{FlowStatus, InputPort, OutputPort};
use rtt::{
    Component, Context, HookResult, InitialState, InterfaceBuilder, Runtime, RuntimeOptions,
    TaskContext,
};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Feeds the subject: a sweeping `a` (through every state's window) and a `b` that dips
/// below -0.95 now and then; reads `x` and `y` back.
struct Driver {
    a: OutputPort<f64>,
    b: OutputPort<f64>,
    x: InputPort<f64>,
    y: InputPort<i64>,
    k: u64,
}

impl Component for Driver {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        self.k += 1;
        let t = self.k as f64;
        self.a.write(&(5.0 * (t * 0.003).sin()));
        self.b.write(&(t * 0.0101).sin());
        let (mut x, mut y) = (0.0, 0);
        let _ = self.x.read(&mut x);
        let _ = self.y.read(&mut y);
        Ok(())
    }
}

/// The reference: machine.lua's logic in Rust.
struct RustMachine {
    a: InputPort<f64>,
    b: InputPort<f64>,
    x: OutputPort<f64>,
    y: OutputPort<i64>,
    va: f64,
    vb: f64,
    state: usize,
}

impl Component for RustMachine {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        let mut v = 0.0;
        if self.a.read(&mut v) != FlowStatus::NoData {
            self.va = v;
        }
        if self.b.read(&mut v) != FlowStatus::NoData {
            self.vb = v;
        }
        let n = self.state;
        self.x.write(&(self.va * 0.5 + n as f64));
        self.y.write(&(n as i64));
        let (low, high) = (n as f64 - 5.0, n as f64 - 4.0);
        if self.va > low && self.va < high {
            self.state = (n + 1) % 10;
        } else if self.vb < -0.95 {
            self.state = (n + 5) % 10;
        }
        Ok(())
    }
}

/// Steps the driver, then times the subject's step.
struct Probe {
    driver: TaskContext,
    subject: TaskContext,
    hist: Arc<Mutex<Histogram<u64>>>,
}

impl Component for Probe {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        let _ = self.driver.step();
        let began = Instant::now();
        let _ = self.subject.step();
        let ns = began.elapsed().as_nanos() as u64;
        if let Ok(mut h) = self.hist.try_lock() {
            let _ = h.record(ns.clamp(1, 10_000_000_000));
        }
        // An overrun (max_step_us) puts the script in Exception: said, counted in its
        // attributes, and the script put back to work so that the run goes on measuring.
        if self.subject.state() == rtt::TaskState::Exception {
            let why = self.subject.counters().last_error.unwrap_or_default();
            eprintln!(
                "{}: {why}; recovered and started again",
                self.subject.name()
            );
            let _ = self.subject.recover();
            let _ = self.subject.start();
        }
        Ok(())
    }
}

fn env(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

struct Run {
    hist: Histogram<u64>,
    realtime: bool,
    overruns: u64,
    subject: TaskContext,
}

/// Runs `subject` (built by `make` as a slave) for `seconds` under the probe.
fn run(
    rt: &Runtime,
    tag: &str,
    seconds: u64,
    make: impl FnOnce(&Runtime, &str) -> TaskContext,
) -> Run {
    let driver = rt
        .add(
            &format!("{tag}_driver"),
            ActivitySpec::Slave,
            InitialState::Stopped,
            |i: &mut InterfaceBuilder<Driver>| {
                Ok(Driver {
                    a: i.output("a", "")?,
                    b: i.output("b", "")?,
                    x: i.input("x", "")?,
                    y: i.input("y", "")?,
                    k: 0,
                })
            },
        )
        .unwrap();
    let subject = make(rt, tag);
    for (from, to) in [(&driver, &subject), (&subject, &driver)] {
        for p in from.ports() {
            if p.direction == rtt::component::Direction::Output
                && let Ok(input) = to.port(&p.name)
            {
                from.port(&p.name)
                    .unwrap()
                    .connect_to(&*input, rtt::port::ConnPolicy::data())
                    .unwrap();
            }
        }
    }
    driver.start().unwrap();
    subject.start().unwrap();
    let hist = Arc::new(Mutex::new(
        Histogram::<u64>::new_with_bounds(1, 10_000_000_000, 3).unwrap(),
    ));
    let fifo = env("SCRIPT_BENCH_FIFO", 1) == 1;
    let spec = ActivitySpec::Periodic {
        period: Duration::from_millis(1),
        thread: ThreadOptions {
            policy: if fifo {
                SchedPolicy::Fifo
            } else {
                SchedPolicy::Other
            },
            priority: env("SCRIPT_BENCH_PRIORITY", 80) as i32,
            ..ThreadOptions::default()
        },
        timing: Timing::Absolute,
        max_overruns: None,
    };
    let (d, s, h) = (driver.clone(), subject.clone(), hist.clone());
    let probe = rt
        .add(
            &format!("{tag}_probe"),
            spec,
            InitialState::Stopped,
            move |_| {
                Ok(Probe {
                    driver: d,
                    subject: s,
                    hist: h,
                })
            },
        )
        .unwrap();
    probe.start().unwrap();
    let loops = seconds * 1000;
    while probe.stats().steps < loops {
        std::thread::sleep(Duration::from_millis(100));
    }
    probe.stop().unwrap();
    let stats = probe.stats();
    let hist = hist.lock().unwrap().clone();
    Run {
        hist,
        realtime: stats.realtime,
        overruns: stats.overruns,
        subject,
    }
}

fn us(ns: u64) -> f64 {
    ns as f64 / 1000.0
}

fn main() {
    let seconds = env("SCRIPT_BENCH_SECONDS", 60);
    let rt = Runtime::new(
        Arc::new(Registry::new()),
        RuntimeOptions {
            cpu_dma_latency_us: Some(0),
            ..RuntimeOptions::default()
        },
    )
    .unwrap();
    let lua = run(&rt, "lua", seconds, |rt, tag| {
        script_machine(rt, tag, false)
    });
    let alloc = run(&rt, "lua_alloc", seconds, |rt, tag| {
        script_machine(rt, tag, true)
    });
    let rust = run(&rt, "rust", seconds, |rt, tag| {
        rt.add(
            &format!("{tag}_machine"),
            ActivitySpec::Slave,
            InitialState::Stopped,
            |i: &mut InterfaceBuilder<RustMachine>| {
                Ok(RustMachine {
                    a: i.input("a", "")?,
                    b: i.input("b", "")?,
                    x: i.output("x", "")?,
                    y: i.output("y", "")?,
                    va: 0.0,
                    vb: 0.0,
                    state: 0,
                })
            },
        )
        .unwrap()
    });
    let fifo = [&lua, &alloc, &rust].iter().all(|r| r.realtime);
    println!(
        "script step at 1 kHz for {seconds} s, {} (10 states, 20 transitions, 4 port reads/writes a step)",
        if fifo {
            "SCHED_FIFO"
        } else {
            "NOT SCHED_FIFO: the machine refused it"
        }
    );
    println!(
        "{:<10} {:>10} {:>10} {:>10} {:>10} {:>8}",
        "", "p50 µs", "p99 µs", "p99.9 µs", "max µs", "steps"
    );
    let runs = [("lua", &lua), ("lua+alloc", &alloc), ("rust", &rust)];
    for (name, r) in runs {
        let h = &r.hist;
        println!(
            "{name:<10} {:>10.2} {:>10.2} {:>10.2} {:>10.2} {:>8}",
            us(h.value_at_quantile(0.5)),
            us(h.value_at_quantile(0.99)),
            us(h.value_at_quantile(0.999)),
            us(h.max()),
            h.len()
        );
    }
    for (name, r) in [("lua/rust", &lua), ("alloc/rust", &alloc)] {
        let ratio = |q: f64| {
            r.hist.value_at_quantile(q) as f64 / rust.hist.value_at_quantile(q).max(1) as f64
        };
        println!(
            "{name:<10} {:>10.1} {:>10.1} {:>10.1} {:>10.1}",
            ratio(0.5),
            ratio(0.99),
            ratio(0.999),
            r.hist.max() as f64 / rust.hist.max().max(1) as f64
        );
    }
    for (name, r) in [("lua", &lua), ("lua+alloc", &alloc)] {
        let steps = r.hist.len().max(1);
        println!(
            "{name}: collector (inside the step) {:.2} µs a step on average, {:.2} µs at most; \
             {} full collections; Lua memory {} KiB; script overruns {}",
            us(attr(r, "gc_ns_total")) / steps as f64,
            us(attr(r, "gc_ns_max")),
            attr(r, "full_collections"),
            attr(r, "memory_used_kb"),
            attr(r, "overruns"),
        );
    }
    println!(
        "driving activity overruns (its 1 ms period missed): {} (lua), {} (lua+alloc), {} (rust)",
        lua.overruns, alloc.overruns, rust.overruns
    );
    let p99 = us(lua.hist.value_at_quantile(0.99));
    let met = p99 <= 20.0 && attr(&lua, "overruns") == 0 && lua.overruns == 0;
    println!(
        "goal (lua) p99 <= 20 µs and no overrun: {}",
        if met { "met" } else { "NOT met" }
    );
    for (name, r) in runs {
        println!("{name}: {}", hot(&rt, r));
    }
    rt.stop_all();
}

/// The benchmark's script as a slave component; `alloc`: formatting a string each step.
fn script_machine(rt: &Runtime, tag: &str, alloc: bool) -> TaskContext {
    let file = concat!(env!("CARGO_MANIFEST_DIR"), "/benches/machine.lua");
    let t = script::add(rt, &format!("{tag}_machine"), ActivitySpec::Slave).unwrap();
    let p = t.properties();
    p.set_value("file", serde_json::json!(file)).unwrap();
    let bound = env("SCRIPT_BENCH_MAX_STEP_US", 1000);
    p.set_value("max_step_us", serde_json::json!(bound))
        .unwrap();
    p.set_value("vars", serde_json::json!({ "alloc": alloc }))
        .unwrap();
    t.configure().unwrap();
    t
}

/// A script component's attribute `name` (0 when there is none).
fn attr(r: &Run, name: &str) -> u64 {
    r.subject
        .attributes()
        .get_value(name)
        .ok()
        .and_then(|v| v.as_u64())
        .unwrap_or(0)
}

/// The subject stepped back to back from this thread (caches warm): the mean step.
fn hot(rt: &Runtime, r: &Run) -> String {
    let name = r.subject.name().replace("_machine", "_driver");
    let driver = rt.component(&name).unwrap();
    let n = 100_000;
    let began = Instant::now();
    for _ in 0..n {
        let _ = driver.step();
        let _ = r.subject.step();
    }
    let with_driver = began.elapsed();
    let began = Instant::now();
    for _ in 0..n {
        let _ = driver.step();
    }
    let driver_only = began.elapsed();
    format!(
        "back to back, caches warm: {:.2} µs a step",
        (with_driver.saturating_sub(driver_only)).as_nanos() as f64 / n as f64 / 1000.0
    )
}
