//! Runtime costs, each printed beside a reference measured in the same run, with the ratio:
//!
//! - a data connection's own protocol for an `f64` (the word register, without the port
//!   around it) and a data-port write+read of an `f64`, beside the floor for it, a
//!   single-writer seqlock over the same value (write, then read, in one thread); a
//!   64-byte struct and a buffer connection beside the same seqlock;
//! - a ClientThread call beside a direct call of the same closure through `dyn Fn`;
//! - an OwnThread call round trip to a non-periodic component beside the floor, a bare
//!   crossbeam-channel round trip to an echo thread: back to back (the callee still awake
//!   from the call before) and with 1 ms between calls (both parked; only the call is
//!   timed). The channel on a virtual machine is bistable back to back: its threads either
//!   stay awake (~0.3 µs) or park every time (~9 µs); each run prints what it got.
//!
//! Nanosecond figures are the median over 101 samples of 20 000 iterations; call figures
//! the median of 2 000 (back to back) or 500 (parked) timed calls. Run:
//! `cargo bench -p rtt --bench runtime` (`RUNTIME_RUNS` repeats the whole set, default 3).

#![allow(
    clippy::unwrap_used,
    reason = "benchmark setup: a failed unwrap aborts the run"
)]

use crossbeam_channel::bounded;
use device_interface::Registry;
use rtt::port::{ConnPolicy, InputPort, OutputPort, connect};
use rtt::{ActivitySpec, Component, Runtime, RuntimeOptions};
use std::hint::black_box;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering, fence};
use std::time::{Duration, Instant};

#[derive(Clone, Default, serde::Serialize, serde::Deserialize)]
struct Sample64 {
    v: [f64; 8],
}

/// The median time of one iteration of `f`, ns: 101 samples of 20 000.
fn per_iter(mut f: impl FnMut()) -> f64 {
    const N: u32 = 20_000;
    for _ in 0..N {
        f();
    }
    let mut samples: Vec<f64> = (0..101)
        .map(|_| {
            let t = Instant::now();
            for _ in 0..N {
                f();
            }
            t.elapsed().as_nanos() as f64 / f64::from(N)
        })
        .collect();
    samples.sort_by(f64::total_cmp);
    samples[samples.len() / 2]
}

/// The median of `n` timed calls of `f`, ns, with `gap` slept before each.
fn per_call(n: usize, gap: Duration, mut f: impl FnMut()) -> f64 {
    let mut samples: Vec<f64> = (0..n)
        .map(|_| {
            if !gap.is_zero() {
                std::thread::sleep(gap);
            }
            let t = Instant::now();
            f();
            t.elapsed().as_nanos() as f64
        })
        .collect();
    samples.sort_by(f64::total_cmp);
    samples[samples.len() / 2]
}

fn pair<T: Clone + Send + Default + 'static>(policy: ConnPolicy) -> (OutputPort<T>, InputPort<T>) {
    let out = OutputPort::new("o");
    let inp = InputPort::new("i");
    connect(&out, &inp, policy).unwrap();
    (out, inp)
}

/// The reference: a single-writer seqlock over one f64 (sequence odd while writing).
struct SeqLock {
    seq: AtomicU64,
    data: AtomicU64,
}

impl SeqLock {
    fn write(&self, v: f64) {
        let s = self.seq.load(Ordering::Relaxed);
        self.seq.store(s + 1, Ordering::Relaxed);
        fence(Ordering::Release);
        self.data.store(v.to_bits(), Ordering::Relaxed);
        self.seq.store(s + 2, Ordering::Release);
    }

    fn read(&self) -> f64 {
        loop {
            let s1 = self.seq.load(Ordering::Acquire);
            if s1 & 1 == 1 {
                continue;
            }
            let d = self.data.load(Ordering::Relaxed);
            fence(Ordering::Acquire);
            if self.seq.load(Ordering::Relaxed) == s1 {
                return f64::from_bits(d);
            }
        }
    }
}

fn seqlock() -> f64 {
    let lock = SeqLock {
        seq: AtomicU64::new(0),
        data: AtomicU64::new(0),
    };
    per_iter(|| {
        lock.write(black_box(1.5));
        black_box(lock.read());
    })
}

/// The data connection's own protocol for a one-word sample, without the port around it.
fn word_cell() -> f64 {
    let cell: rtt::port::word::WordCell = rtt::port::word::WordCell::new();
    let (mut written, mut seen) = (0u64, 0u64);
    per_iter(|| {
        written += 1;
        cell.write(written, black_box(1.5f64).to_bits());
        if let rtt::port::word::Found::New { version, value } = cell.read(seen) {
            seen = version;
            black_box(f64::from_bits(value));
        }
    })
}

fn port<T: Clone + Send + Default + 'static>(policy: ConnPolicy, value: T) -> f64 {
    let (mut out, mut inp) = pair::<T>(policy);
    let mut x = T::default();
    per_iter(|| {
        out.write(black_box(&value));
        black_box(inp.read(&mut x));
    })
}

struct Nothing;
impl Component for Nothing {}

fn client_thread_call() -> f64 {
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
    let t = rt
        .add(
            "c",
            ActivitySpec::Slave,
            rtt::InitialState::Stopped,
            |iface| {
                iface.client_operation("add", "", &[], |(a, b): (f64, f64)| a + b)?;
                Ok(Nothing)
            },
        )
        .unwrap();
    let op = t.operation::<(f64, f64), f64>("add").unwrap();
    per_iter(|| {
        black_box(op.call(black_box((1.0, 2.0))).unwrap());
    })
}

fn dyn_fn_call() -> f64 {
    let f: Box<dyn Fn((f64, f64)) -> f64> = Box::new(|(a, b)| a + b);
    per_iter(|| {
        black_box(f(black_box((1.0, 2.0))));
    })
}

struct Count(i64);
impl Component for Count {}

/// An OwnThread call to a started non-periodic component: (back to back, parked), ns.
fn own_thread_calls() -> (f64, f64) {
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
    let t = rt
        .add(
            "c",
            ActivitySpec::non_periodic(),
            rtt::InitialState::Stopped,
            |iface| {
                iface.own_operation("add", "", &[], |c: &mut Count, (n,): (i64,)| {
                    c.0 += n;
                    c.0
                })?;
                Ok(Count(0))
            },
        )
        .unwrap();
    t.start().unwrap();
    let op = t.operation::<(i64,), i64>("add").unwrap();
    let mut call = || {
        black_box(op.call(black_box((1,))).unwrap());
    };
    for _ in 0..2000 {
        call();
    }
    let awake = per_call(2000, Duration::ZERO, &mut call);
    let parked = per_call(500, PARKED_GAP, &mut call);
    t.stop().unwrap();
    (awake, parked)
}

/// The pause between the parked calls: far past the spin (20 µs by default).
const PARKED_GAP: Duration = Duration::from_millis(1);

/// The same round trips through a bare crossbeam channel to an echo thread.
fn channel_calls() -> (f64, f64) {
    let (req_tx, req_rx) = bounded::<i64>(1);
    let (rep_tx, rep_rx) = bounded::<i64>(1);
    let echo = std::thread::spawn(move || {
        while let Ok(n) = req_rx.recv() {
            if rep_tx.send(n).is_err() {
                break;
            }
        }
    });
    let mut call = || {
        req_tx.send(black_box(1)).unwrap();
        black_box(rep_rx.recv().unwrap());
    };
    for _ in 0..2000 {
        call();
    }
    let awake = per_call(2000, Duration::ZERO, &mut call);
    let parked = per_call(500, PARKED_GAP, &mut call);
    drop(req_tx);
    echo.join().unwrap();
    (awake, parked)
}

fn row(what: &str, ours: f64, reference: &str, theirs: f64) {
    println!(
        "{what:<34} {:>10} {reference:<30} {:>10} {:>7.2}",
        show(ours),
        show(theirs),
        ours / theirs
    );
}

fn show(ns: f64) -> String {
    if ns >= 10_000.0 {
        format!("{:.1} µs", ns / 1000.0)
    } else if ns >= 1000.0 {
        format!("{:.2} µs", ns / 1000.0)
    } else {
        format!("{ns:.2} ns")
    }
}

fn main() {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return; // `cargo test --benches` lists or smoke-runs: nothing to do.
    }
    let runs: usize = std::env::var("RUNTIME_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    for run in 1..=runs.max(1) {
        println!(
            "run {run}: {:<28} {:>10} {:<30} {:>10} {:>7}",
            "", "hwgw", "reference", "", "ratio"
        );
        let floor = seqlock();
        row(
            "data connection f64 (word register)",
            word_cell(),
            "seqlock f64 write+read",
            floor,
        );
        row(
            "data port f64 write+read",
            port::<f64>(ConnPolicy::data(), 1.5),
            "seqlock f64 write+read",
            floor,
        );
        row(
            "data port 64-byte struct",
            port::<Sample64>(ConnPolicy::data(), Sample64 { v: [1.0; 8] }),
            "seqlock f64 write+read",
            floor,
        );
        row(
            "buffer port f64 push+pop",
            port::<f64>(ConnPolicy::buffer(16), 1.5),
            "seqlock f64 write+read",
            floor,
        );
        row(
            "ClientThread call",
            client_thread_call(),
            "dyn Fn call",
            dyn_fn_call(),
        );
        let (own_awake, own_parked) = own_thread_calls();
        let (ch_awake, ch_parked) = channel_calls();
        row(
            "OwnThread call, back to back",
            own_awake,
            "crossbeam channel round trip",
            ch_awake,
        );
        row(
            "OwnThread call, 1 ms apart",
            own_parked,
            "crossbeam channel round trip",
            ch_parked,
        );
    }
}
