//! Requests per poll for a spread-out register map, before and after coalescing; and the
//! default plan against the protocol's minimum on five random maps.
//!
//! The first map is what a gateway in front of a PLC and an energy meter typically polls:
//! contiguous blocks, strided setpoints, scattered 32-bit values, sparse coils. "Before" is
//! one read per point; "after" is the planner at several gap thresholds and at its default
//! (any gap within the read limits). The random maps (44 points of 1 or 2 registers, or
//! bits, spread over addresses 0-999 of the four tables) compare the default plan with the
//! protocol's minimum, computed here independently by dynamic programming.
//! Run: `cargo bench -p driver-modbus --bench plan`.

#![allow(
    clippy::unwrap_used,
    reason = "benchmark setup: a failed unwrap aborts the run"
)]

use driver_modbus::map::ANY_GAP;
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
    let default = plan(&spans, ANY_GAP).unwrap();
    println!("{:<28} {:>8}", "default (any gap)", default.len());
    random_maps();
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

/// The fewest reads that cover `spans`, each whole in one read of at most the table's limit,
/// by dynamic programming over every way to cut (not the planner's greedy rule): per table,
/// `best[i]` = 1 + the least `best[k]` over every `k` such that one read from span `i`
/// covers spans `i..k` whole; the spans here do not overlap.
fn protocol_minimum(spans: &[Span]) -> usize {
    let mut total = 0;
    for table in [
        Table::Coils,
        Table::DiscreteInputs,
        Table::InputRegisters,
        Table::HoldingRegisters,
    ] {
        let mut s: Vec<(u32, u32)> = spans
            .iter()
            .filter(|x| x.table == table)
            .map(|x| {
                (
                    u32::from(x.address),
                    u32::from(x.address) + u32::from(x.count),
                )
            })
            .collect();
        s.sort_unstable();
        let n = s.len();
        let mut best = vec![0usize; n + 1];
        for i in (0..n).rev() {
            let limit = s[i].0 + u32::from(table.max_read());
            let mut least = usize::MAX;
            for k in i + 1..=n {
                if s[i..k].iter().any(|x| x.1 > limit) {
                    break;
                }
                least = least.min(best[k]);
            }
            best[i] = 1 + least;
        }
        total += best[0];
    }
    total
}

/// A random map: 44 points of 1 or 2 registers (or 1 bit) spread over 0-999, no overlap.
fn random_map(seed: u64) -> Vec<Span> {
    let mut x = seed;
    let mut next = move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        x
    };
    let tables = [
        Table::Coils,
        Table::DiscreteInputs,
        Table::InputRegisters,
        Table::HoldingRegisters,
    ];
    let mut v: Vec<Span> = Vec::new();
    while v.len() < 44 {
        let table = tables[(next() % 4) as usize];
        let count = if table.is_bits() {
            1
        } else {
            1 + (next() % 2) as u16
        };
        let address = (next() % 999) as u16;
        let clash = v.iter().any(|o| {
            o.table == table && address < o.address + o.count && o.address < address + count
        });
        if !clash {
            v.push(Span {
                table,
                address,
                count,
            });
        }
    }
    v
}

fn random_maps() {
    println!();
    println!("five random maps (44 points over addresses 0-999): requests per poll");
    println!(
        "{:<8} {:>10} {:>10} {:>10} {:>10} {:>8}",
        "seed", "per point", "max_gap 8", "default", "minimum", "ratio"
    );
    let mut sums = [0usize; 4];
    for seed in [1u64, 2, 3, 4, 5] {
        let spans = random_map(0x9E37_79B9_7F4A_7C15 ^ seed);
        let old = plan(&spans, 8).unwrap().len();
        let new = plan(&spans, ANY_GAP).unwrap().len();
        let min = protocol_minimum(&spans);
        for (s, v) in sums.iter_mut().zip([spans.len(), old, new, min]) {
            *s += v;
        }
        println!(
            "{seed:<8} {:>10} {:>10} {:>10} {:>10} {:>8.2}",
            spans.len(),
            old,
            new,
            min,
            new as f64 / min as f64
        );
    }
    let avg = |v: usize| v as f64 / 5.0;
    println!(
        "{:<8} {:>10.1} {:>10.1} {:>10.1} {:>10.1} {:>8.2}",
        "mean",
        avg(sums[0]),
        avg(sums[1]),
        avg(sums[2]),
        avg(sums[3]),
        sums[2] as f64 / sums[3] as f64
    );
}
