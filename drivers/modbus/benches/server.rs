//! hwgw's Modbus TCP server beside pymodbus's (Debian's python3-pymodbus, the tests' peer)
//! in the same run: requests per second and p50/p99 latency with 1, 10 and 100 masters at
//! once on loopback, each a thread with its own connection and one request outstanding,
//! every one reading input registers 0..=2 (which both servers serve).
//! Run: `cargo bench -p driver-modbus --bench server`.

#![allow(
    clippy::unwrap_used,
    reason = "benchmark setup: a failed unwrap aborts the run"
)]

use device_interface::AnalogIn;
use driver_modbus::codec::{ByteOrder, Layout, ValueType, WordOrder};
use driver_modbus::listener::{Limits, ModbusServer};
use driver_modbus::plan::Table;
use driver_modbus::server::{Entry, RegisterTable, Source};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};
use testkit::fixtures::MODBUS_MAP;
use testkit::peers::{PYMODBUS, PYTHON, ensure};

const SECONDS: f64 = 2.0;
const REQUEST: [u8; 5] = [4, 0, 0, 0, 3];

fn table() -> RegisterTable {
    let card = driver_modbus::testing::card(MODBUS_MAP, 4);
    card.poll_succeeded();
    let ai: Arc<dyn AnalogIn> = card.clone();
    let e = |address, ty, ch| Entry {
        table: Table::InputRegisters,
        address,
        layout: Layout {
            ty,
            words: WordOrder::HighFirst,
            bytes: ByteOrder::Normal,
        },
        scale: 0.1,
        offset: 0.0,
        source: Source::AnalogIn(ai.clone(), ch),
    };
    RegisterTable::new(vec![e(0, ValueType::I16, 0), e(1, ValueType::F32, 1)]).unwrap()
}

struct Peer(Child);
impl Drop for Peer {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn pymodbus() -> (Peer, SocketAddr) {
    ensure(&PYMODBUS);
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/peers/pymodbus_server.py"
    );
    let child = Command::new(PYTHON)
        .args([script, "tcp", &port.to_string()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let addr: SocketAddr = format!("127.0.0.1:{port}").parse().unwrap();
    let end = Instant::now() + Duration::from_secs(20);
    while TcpStream::connect(addr).is_err() {
        assert!(Instant::now() < end, "pymodbus did not listen");
        std::thread::sleep(Duration::from_millis(50));
    }
    (Peer(child), addr)
}

/// One master: requests for `SECONDS`; its latencies, µs.
fn master(addr: SocketAddr) -> Vec<f64> {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_nodelay(true).unwrap();
    let mut frame = vec![0, 0, 0, 0, 0, (REQUEST.len() + 1) as u8, 1];
    frame.extend_from_slice(&REQUEST);
    let mut reply = [0u8; 7 + 2 + 6];
    let mut lat = Vec::new();
    let end = Instant::now() + Duration::from_secs_f64(SECONDS);
    let mut tid = 0u16;
    while Instant::now() < end {
        tid = tid.wrapping_add(1);
        frame[..2].copy_from_slice(&tid.to_be_bytes());
        let t0 = Instant::now();
        s.write_all(&frame).unwrap();
        s.read_exact(&mut reply).unwrap();
        lat.push(t0.elapsed().as_secs_f64() * 1e6);
        assert_eq!(&reply[..2], &tid.to_be_bytes(), "the transaction id echoed");
        assert_eq!(reply[7], 4, "a reply, not an exception: {reply:x?}");
    }
    lat
}

/// (requests/s, p50 µs, p99 µs) with `n` masters at once.
fn load(addr: SocketAddr, n: usize) -> (f64, f64, f64) {
    let t0 = Instant::now();
    let threads: Vec<_> = (0..n)
        .map(|_| std::thread::spawn(move || master(addr)))
        .collect();
    let mut all: Vec<f64> = threads
        .into_iter()
        .flat_map(|t| t.join().unwrap())
        .collect();
    let s = t0.elapsed().as_secs_f64();
    all.sort_by(f64::total_cmp);
    let q = |p: f64| all[((all.len() as f64 * p) as usize).min(all.len() - 1)];
    (all.len() as f64 / s, q(0.5), q(0.99))
}

fn main() {
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return;
    }
    // 100 masters, all on 127.0.0.1.
    let limits = Limits {
        max_clients: 128,
        max_clients_per_address: 128,
        ..Limits::default()
    };
    let hwgw = ModbusServer::start("127.0.0.1:0".parse().unwrap(), table(), limits).unwrap();
    let (_py, py_addr) = pymodbus();
    println!("Modbus TCP servers, FC4 read of 3 input registers, {SECONDS} s per run");
    println!(
        "{:>8} {:>12} {:>10} {:>10}   {:>12} {:>10} {:>10}   {:>7}",
        "masters", "hwgw req/s", "p50 µs", "p99 µs", "pymodbus", "p50 µs", "p99 µs", "ratio"
    );
    for n in [1, 10, 100] {
        let (hr, h50, h99) = load(hwgw.addr(), n);
        let (pr, p50, p99) = load(py_addr, n);
        println!(
            "{n:>8} {hr:>12.0} {h50:>10.1} {h99:>10.1}   {pr:>12.0} {p50:>10.1} {p99:>10.1}   {:>7.2}",
            hr / pr
        );
    }
    let c = hwgw.counters();
    println!(
        "hwgw server: {} connections, {} requests, {} exceptions, {} evicted, {} refused, {} panics",
        c.connections, c.requests, c.exceptions, c.evicted, c.refused_per_address, c.panics
    );
}
