//! Runtime costs, each beside a reference measured in the same run.
//!
//! - data-port write+read of an f64 and of a 64-byte struct; buffer-port push+pop;
//! - a ClientThread call, beside a direct call of the same closure through `dyn Fn`;
//! - an OwnThread call round trip to a non-periodic component, beside the floor: a bare
//!   crossbeam-channel round trip to an echo thread; each back to back (the callee still
//!   spinning from the call before) and with 1 ms between calls (the callee parked, woken
//!   by the scheduler; only the call is timed).
//!
//! Run: `cargo bench -p rtt --bench runtime`.

#![allow(
    clippy::unwrap_used,
    reason = "benchmark setup: a failed unwrap aborts the run"
)]

use crossbeam_channel::bounded;
use device_interface::Registry;
use divan::{Bencher, black_box};
use rtt::port::{ConnPolicy, InputPort, OutputPort, connect};
use rtt::{ActivitySpec, Component, Runtime, RuntimeOptions};
use std::sync::Arc;

fn main() {
    divan::main();
}

#[derive(Clone, Default, serde::Serialize, serde::Deserialize)]
struct Sample64 {
    v: [f64; 8],
}

fn pair<T: Clone + Send + Default + 'static>(policy: ConnPolicy) -> (OutputPort<T>, InputPort<T>) {
    let out = OutputPort::new("o");
    let inp = InputPort::new("i");
    connect(&out, &inp, policy).unwrap();
    (out, inp)
}

#[divan::bench]
fn port_data_f64_write_read(b: Bencher) {
    let (mut out, mut inp) = pair::<f64>(ConnPolicy::data());
    let mut x = 0.0;
    b.bench_local(|| {
        out.write(black_box(&1.5));
        black_box(inp.read(&mut x));
    });
}

#[divan::bench]
fn port_data_struct64_write_read(b: Bencher) {
    let (mut out, mut inp) = pair::<Sample64>(ConnPolicy::data());
    let mut s = Sample64::default();
    let w = Sample64 { v: [1.0; 8] };
    b.bench_local(|| {
        out.write(black_box(&w));
        black_box(inp.read(&mut s));
    });
}

#[divan::bench]
fn port_buffer_f64_push_pop(b: Bencher) {
    let (mut out, mut inp) = pair::<f64>(ConnPolicy::buffer(16));
    let mut x = 0.0;
    b.bench_local(|| {
        out.write(black_box(&1.5));
        black_box(inp.read(&mut x));
    });
}

struct Nothing;
impl Component for Nothing {}

#[divan::bench]
fn client_thread_call(b: Bencher) {
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
    b.bench_local(|| black_box(op.call(black_box((1.0, 2.0)))));
}

#[divan::bench]
fn reference_dyn_fn_call(b: Bencher) {
    let f: Box<dyn Fn((f64, f64)) -> f64> = Box::new(|(a, b)| a + b);
    b.bench_local(|| black_box(f(black_box((1.0, 2.0)))));
}

struct Count(i64);
impl Component for Count {}

/// A started non-periodic component with OwnThread operation `add`.
fn counter(rt: &Runtime) -> rtt::TaskContext {
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
    t
}

/// The pause between the parked benches' calls: far past the spin (20 µs by default).
const PARKED_GAP: std::time::Duration = std::time::Duration::from_millis(1);

#[divan::bench(sample_count = 500)]
fn call_parked_own_thread(b: Bencher) {
    let rt = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default()).unwrap();
    let t = counter(&rt);
    let op = t.operation::<(i64,), i64>("add").unwrap();
    b.with_inputs(|| std::thread::sleep(PARKED_GAP))
        .bench_local_values(|()| black_box(op.call(black_box((1,))).unwrap()));
    t.stop().unwrap();
}

#[divan::bench(sample_count = 500)]
fn call_parked_reference_channel(b: Bencher) {
    let (req_tx, req_rx) = bounded::<i64>(1);
    let (rep_tx, rep_rx) = bounded::<i64>(1);
    let echo = std::thread::spawn(move || {
        while let Ok(n) = req_rx.recv() {
            if rep_tx.send(n).is_err() {
                break;
            }
        }
    });
    b.with_inputs(|| std::thread::sleep(PARKED_GAP))
        .bench_local_values(|()| {
            req_tx.send(black_box(1)).unwrap();
            black_box(rep_rx.recv().unwrap())
        });
    drop(req_tx);
    echo.join().unwrap();
}

#[divan::bench(sample_count = 2000)]
fn call_awake_own_thread(b: Bencher) {
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
    b.bench_local(|| black_box(op.call(black_box((1,))).unwrap()));
    t.stop().unwrap();
}

#[divan::bench(sample_count = 2000)]
fn call_awake_reference_channel(b: Bencher) {
    let (req_tx, req_rx) = bounded::<i64>(1);
    let (rep_tx, rep_rx) = bounded::<i64>(1);
    let echo = std::thread::spawn(move || {
        let mut total = 0;
        while let Ok(n) = req_rx.recv() {
            total += n;
            if rep_tx.send(total).is_err() {
                break;
            }
        }
    });
    b.bench_local(|| {
        req_tx.send(black_box(1)).unwrap();
        black_box(rep_rx.recv().unwrap())
    });
    drop(req_tx);
    echo.join().unwrap();
}
