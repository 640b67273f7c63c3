//! Requests per poll for a spread-out register map, before and after coalescing.
//!
//! The map is what a gateway in front of a PLC and an energy meter typically polls:
//! contiguous blocks, strided setpoints, scattered 32-bit values, sparse coils. "Before" is
//! one read per point; "after" is the planner at several gap thresholds.
//! Run: `cargo bench -p driver-modbus --bench plan`.

#![allow(
    clippy::unwrap_used,
    reason = "benchmark setup: a failed unwrap aborts the run"
)]

use driver_modbus::plan::{Span, Table, plan};
use std::time::Instant;

fn map() -> Vec<Span> {
    let mut v = Vec::new();
    let mut add = |table, address, count| {
        v.push(Span {
            table,
            address,
            count,
        })
    };
    for i in 0..40 {
        add(Table::HoldingRegisters, i * 2, 2); // 40 f32 measurements, back to back
    }
    for i in 0..20 {
        add(Table::HoldingRegisters, 1000 + i * 10, 1); // setpoints every 10 registers
    }
    for i in 0..10 {
        add(Table::HoldingRegisters, 3000 + i * 50, 2); // u32 counters, far apart
    }
    for i in 0..64 {
        add(Table::InputRegisters, i, 1); // a 64-channel i16 input block
    }
    for i in 0..16 {
        add(Table::InputRegisters, 500 + i * 6, 2); // f32 with 4 unused registers between
    }
    for i in 0..32 {
        add(Table::Coils, i * 3, 1); // sparse coils
    }
    for i in 0..100 {
        add(Table::DiscreteInputs, i, 1);
    }
    v
}

fn main() {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return;
    }
    let spans = map();
    println!("register map: {} points", spans.len());
    println!("{:<28} {:>8}", "", "requests per poll");
    println!("{:<28} {:>8}", "one read per point", spans.len());
    for gap in [0u16, 4, 16, 64] {
        let reads = plan(&spans, gap).unwrap();
        let words: u32 = reads
            .iter()
            .filter(|r| !r.table.is_bits())
            .map(|r| u32::from(r.count))
            .sum();
        println!(
            "{:<28} {:>8}   ({} registers read)",
            format!("coalesced, max_gap {gap}"),
            reads.len(),
            words
        );
    }
    let t = Instant::now();
    let n = 1000;
    for _ in 0..n {
        std::hint::black_box(plan(std::hint::black_box(&spans), 16).unwrap());
    }
    println!(
        "planning the map: {:.1} µs (done once at start-up)",
        t.elapsed().as_secs_f64() * 1e6 / f64::from(n)
    );
}
