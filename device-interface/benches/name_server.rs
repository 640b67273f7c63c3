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

/// Lookups while another thread keeps reading too (contention on shared counters).
#[divan::bench(threads = [2], args = [100])]
fn name_server_get_2_threads(bencher: divan::Bencher, n: usize) {
    let ns = server(n);
    let key = name(n / 2);
    bencher.bench(|| black_box(ns.get(black_box(&key))));
}

#[divan::bench(threads = [2], args = [100])]
fn reference_rwlock_hashmap_get_2_threads(bencher: divan::Bencher, n: usize) {
    let map: RwLock<HashMap<String, Arc<str>>> =
        RwLock::new((0..n).map(|i| (name(i), Arc::from("device"))).collect());
    let key = name(n / 2);
    bencher.bench(|| {
        let guard = map.read().unwrap();
        black_box(guard.get(black_box(key.as_str())).cloned())
    });
}
