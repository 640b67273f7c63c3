//! Name-server lookup cost, against the bare data structures it is built on.
//!
//! `NameServer::get` is a lock-free load of the table, a hash lookup and an `Arc` clone. The
//! references measured in the same run: a bare `HashMap::get` + `Arc` clone (the floor: no
//! shared-table machinery at all) and the obvious alternative, an `RwLock<HashMap>`.
//! Run: `cargo bench -p device-interface --bench name_server`.

#![allow(
    clippy::unwrap_used,
    reason = "benchmark setup: a failed unwrap aborts the run"
)]

use device_interface::{Interface, NameServer};
use std::collections::HashMap;
use std::hint::black_box;
use std::sync::{Arc, RwLock};

fn main() {
    divan::main();
}

/// Registry sizes: a small rig, a cell, a large plant.
const SIZES: [usize; 3] = [8, 100, 1000];

fn name(i: usize) -> String {
    format!("plant/line{}/card{}.io", i % 7, i)
}

fn server(n: usize) -> NameServer<str> {
    let ns = NameServer::new(Interface::AnalogIn);
    for i in 0..n {
        ns.register(&name(i), "owner", Arc::from("device")).unwrap();
    }
    ns
}

#[divan::bench(args = SIZES)]
fn name_server_get(bencher: divan::Bencher, n: usize) {
    let ns = server(n);
    let key = name(n / 2);
    bencher.bench(|| black_box(ns.get(black_box(&key))));
}

#[divan::bench(args = SIZES)]
fn name_server_get_missing(bencher: divan::Bencher, n: usize) {
    let ns = server(n);
    bencher.bench(|| black_box(ns.get(black_box("plant/line9/nothing.io"))));
}

#[divan::bench(args = SIZES)]
fn reference_hashmap_get(bencher: divan::Bencher, n: usize) {
    let map: HashMap<String, Arc<str>> = (0..n).map(|i| (name(i), Arc::from("device"))).collect();
    let key = name(n / 2);
    bencher.bench(|| black_box(map.get(black_box(key.as_str())).cloned()));
}

#[divan::bench(args = SIZES)]
fn reference_rwlock_hashmap_get(bencher: divan::Bencher, n: usize) {
    let map: RwLock<HashMap<String, Arc<str>>> =
        RwLock::new((0..n).map(|i| (name(i), Arc::from("device"))).collect());
    let key = name(n / 2);
    bencher.bench(|| {
        let guard = map.read().unwrap();
        black_box(guard.get(black_box(key.as_str())).cloned())
    });
}

/// Runs `lookup` in a loop on a long-lived second thread while the benchmark thread measures,
/// so both sides are in steady state (no per-thread set-up in the figures).
fn with_background_reader(lookup: impl Fn() + Send + 'static, measure: impl FnOnce()) {
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let s = stop.clone();
    let t = std::thread::spawn(move || {
        while !s.load(std::sync::atomic::Ordering::Relaxed) {
            lookup();
        }
    });
    measure();
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    t.join().unwrap();
}

/// A lookup while another thread keeps looking the same name up (shared counters contend).
#[divan::bench(args = [100])]
fn name_server_get_contended(bencher: divan::Bencher, n: usize) {
    let ns = Arc::new(server(n));
    let key = name(n / 2);
    let (ns2, key2) = (ns.clone(), key.clone());
    with_background_reader(
        move || drop(black_box(ns2.get(&key2))),
        || bencher.bench_local(|| black_box(ns.get(black_box(&key)))),
    );
}

#[divan::bench(args = [100])]
fn reference_rwlock_hashmap_get_contended(bencher: divan::Bencher, n: usize) {
    let map: Arc<RwLock<HashMap<String, Arc<str>>>> = Arc::new(RwLock::new(
        (0..n).map(|i| (name(i), Arc::from("device"))).collect(),
    ));
    let key = name(n / 2);
    let (map2, key2) = (map.clone(), key.clone());
    with_background_reader(
        move || drop(black_box(map2.read().unwrap().get(key2.as_str()).cloned())),
        || {
            bencher.bench_local(|| {
                let guard = map.read().unwrap();
                black_box(guard.get(black_box(key.as_str())).cloned())
            })
        },
    );
}
