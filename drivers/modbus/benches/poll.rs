//! Poll transactions per second through a Line, beside a bare tokio-modbus client loop
//! against the same server in the same run; and the per-poll overhead that follows.
//!
//! Both read 10 holding registers per transaction from the in-process test server over
//! loopback TCP. Run: `cargo bench -p driver-modbus --bench poll`.

#![allow(
    clippy::unwrap_used,
    reason = "benchmark setup: a failed unwrap aborts the run"
)]

use device_interface::time::MonotonicClock;
use device_interface::{Device, Status};
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

const SECONDS: f64 = 3.0;

fn main() {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return;
    }
    let server = TestServer::start();
    let addr = server.addr();

    // The floor: a bare client loop, one request outstanding, as fast as it goes.
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let (bare_n, bare_t) = rt.block_on(async {
        let mut ctx = tokio_modbus::client::tcp::connect_slave(addr, tokio_modbus::Slave(1))
            .await
            .unwrap();
        let t0 = Instant::now();
        let mut n = 0u64;
        while t0.elapsed().as_secs_f64() < SECONDS {
            ctx.read_holding_registers(0, 10).await.unwrap().unwrap();
            n += 1;
        }
        (n, t0.elapsed())
    });

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
    while card.health().status != Status::Online {
        std::thread::sleep(Duration::from_millis(5));
    }
    let (p0, t0) = (stats.polls.load(Ordering::Relaxed), Instant::now());
    std::thread::sleep(Duration::from_secs_f64(SECONDS));
    let (p1, line_t) = (stats.polls.load(Ordering::Relaxed), t0.elapsed());
    drop(line);

    let bare_rate = bare_n as f64 / bare_t.as_secs_f64();
    let line_rate = (p1 - p0) as f64 / line_t.as_secs_f64();
    println!("10 holding registers per transaction, loopback TCP, {SECONDS} s each");
    println!(
        "{:<34} {:>10.0} transactions/s  ({:.1} µs each)",
        "bare tokio-modbus client loop",
        bare_rate,
        1e6 / bare_rate
    );
    println!(
        "{:<34} {:>10.0} polls/s         ({:.1} µs each)",
        "hwgw Line (decode into the image)",
        line_rate,
        1e6 / line_rate
    );
    println!(
        "ratio line/bare: {:.2}; per-poll overhead: {:.1} µs",
        line_rate / bare_rate,
        1e6 / line_rate - 1e6 / bare_rate
    );
    println!(
        "timeouts {}, exceptions {}, bad replies {}",
        stats.timeouts.load(Ordering::Relaxed),
        stats.exceptions.load(Ordering::Relaxed),
        stats.bad_replies.load(Ordering::Relaxed)
    );
}
