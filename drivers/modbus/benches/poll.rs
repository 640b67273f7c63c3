//! Poll transactions per second through a Line, beside a bare tokio-modbus client loop
//! against the same server in the same run; and the per-poll overhead that follows.
//!
//! Both read 10 holding registers per transaction from the in-process test server over
//! loopback TCP, back to back, in alternating rounds (`POLL_ROUNDS`, default 5, of
//! `POLL_SECONDS`, default 2 s, each side; the line is stopped during the bare client's
//! round), so a stall of the machine falls on both. Each round prints the time per poll of
//! both and their ratio; the last line the median ratio. Run:
//! `cargo bench -p driver-modbus --bench poll`.

#![allow(
    clippy::unwrap_used,
    reason = "benchmark setup: a failed unwrap aborts the run"
)]

use device_interface::time::MonotonicClock;

use driver_modbus::card::ModbusCard;
use driver_modbus::line::{LineUnit, Transport, UnitStats, UnitTiming};
use driver_modbus::map::{Map, PointConfig};
use driver_modbus::plan::Table;
use driver_modbus::testing::TestLine;
use driver_modbus::testing::TestServer;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use tokio_modbus::client::Reader;

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return;
    }
    let rounds: usize = env_or("POLL_ROUNDS", 5).max(1);
    let seconds: f64 = env_or("POLL_SECONDS", 2.0_f64).max(0.1);
    let server = TestServer::start();
    let addr = server.addr();

    // The floor: a bare client loop, one request outstanding, as fast as it goes.
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let mut ctx = rt.block_on(async {
        tokio_modbus::client::tcp::connect_slave(addr, tokio_modbus::Slave(1))
            .await
            .unwrap()
    });
    let mut bare_round = || {
        rt.block_on(async {
            let t0 = Instant::now();
            let mut n = 0u64;
            while t0.elapsed().as_secs_f64() < seconds {
                ctx.read_holding_registers(0, 10).await.unwrap().unwrap();
                n += 1;
            }
            t0.elapsed().as_secs_f64() * 1e6 / n as f64
        })
    };

    // The same transaction through a Line: a map of 10 read-only holding registers is one
    // read per poll; a 1 µs poll period makes it poll back to back.
    let points: Vec<PointConfig> = (0..10)
        .map(|a| PointConfig {
            table: Table::HoldingRegisters,
            address: a,
            ty: Default::default(),
            words: Default::default(),
            bytes: Default::default(),
            scale: 1.0,
            offset: 0.0,
            unit: String::new(),
            bit: None,
            read_only: true,
            resolution: None,
            encoder: None,
        })
        .collect();
    let card = ModbusCard::new(Map::new(&points, 0).unwrap(), Arc::new(MonotonicClock));
    let stats = Arc::new(UnitStats::default());
    let timing = UnitTiming {
        unit: 1,
        poll: Duration::from_micros(1),
        timeout: Duration::from_secs(1),
        stale_after: 3,
        offline_after: 10,
        backoff_max: Duration::from_secs(1),
    };
    let line = TestLine::spawn(
        "mb-bench",
        Transport::Tcp(addr),
        vec![LineUnit {
            card: card.clone(),
            timing,
            stats: stats.clone(),
        }],
    )
    .unwrap();
    let task = line.task();
    task.stop().unwrap();
    let line_round = || {
        // Timed from the first poll of this start on (the connection made, the thread up).
        let before = stats.polls.load(Ordering::Relaxed);
        task.start().unwrap();
        while stats.polls.load(Ordering::Relaxed) == before {
            std::thread::sleep(Duration::from_millis(1));
        }
        let (p0, t0) = (stats.polls.load(Ordering::Relaxed), Instant::now());
        std::thread::sleep(Duration::from_secs_f64(seconds));
        let (p1, t) = (stats.polls.load(Ordering::Relaxed), t0.elapsed());
        task.stop().unwrap();
        t.as_secs_f64() * 1e6 / (p1 - p0).max(1) as f64
    };

    println!(
        "10 holding registers per transaction, loopback TCP, {rounds} alternating rounds of {seconds} s"
    );
    println!(
        "{:<6} {:>22} {:>22} {:>8}",
        "round", "bare tokio-modbus µs", "hwgw Line µs", "ratio"
    );
    let mut ratios = Vec::new();
    for round in 1..=rounds {
        let bare = bare_round();
        let polled = line_round();
        ratios.push(polled / bare);
        println!(
            "{round:<6} {bare:>22.1} {polled:>22.1} {:>8.2}",
            polled / bare
        );
    }
    drop(line);
    println!(
        "median ratio line/bare (time per poll): {:.2}",
        testkit::bench::median(&mut ratios)
    );
    println!(
        "timeouts {}, exceptions {}, bad replies {}",
        stats.timeouts.load(Ordering::Relaxed),
        stats.exceptions.load(Ordering::Relaxed),
        stats.bad_replies.load(Ordering::Relaxed)
    );
}
