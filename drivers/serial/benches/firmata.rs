//! The Firmata card beside pyfirmata2 on the same simulated Uno running StandardFirmata,
//! in the same run: the digital round trip (an output written, the firmware drives pin 12,
//! a jumper in the simulator carries it to pin 2, the firmware reports it, the client sees
//! it) as p50/p99, and analog reports received per second with A0–A5 reported every 1 ms
//! (the 57600-baud line is the limit). The simulation runs at 0.7–0.95× real time: compare
//! the ratio, not the absolute figures. hwgw's card goes first; its stop turns the board's
//! reports off, so pyfirmata2 starts on a quiet line as hwgw did.
#![allow(clippy::unwrap_used, reason = "bench code")]

use device_interface::time::MonotonicClock;
use device_interface::{DigitalIn, DigitalOut};
use driver_serial::bus::FirmataBus;
use driver_serial::card::FirmataCard;
use driver_serial::component::FirmataIo;
use driver_serial::config::FirmataConfig;
use std::process::Command;
use std::sync::Arc;
use std::time::{Duration, Instant};
use testkit::peers::PYTHON;
use testkit::uno::pyfirmata2;
use testkit::{SimUno, wait_until};

const TRIPS: usize = 300;
const ANALOG_SECONDS: f64 = 5.0;

const PYFIRMATA: &str = r#"
import json, sys, time, threading, pyfirmata2
trips, seconds = int(sys.argv[2]), float(sys.argv[3])
board = pyfirmata2.Arduino(sys.argv[1])
seen = threading.Event(); level = [None]
def on_d2(v):
    level[0] = v; seen.set()
d2 = board.get_pin('d:2:i'); d2.register_callback(on_d2); d2.enable_reporting()
d12 = board.get_pin('d:12:o')
board.samplingOn(1)
times = []
for i in range(trips):
    want = bool(i % 2 == 0)
    seen.clear(); t0 = time.perf_counter(); d12.write(want)
    while level[0] != want:
        seen.wait(1.0); seen.clear()
        if time.perf_counter() - t0 > 10:
            sys.exit("pyfirmata2: round trip %d not back in 10 s" % i)
    times.append(time.perf_counter() - t0)
count = [0]
pins = [board.get_pin('a:%d:i' % c) for c in range(6)]
for p in pins:
    p.register_callback(lambda v: count.__setitem__(0, count[0] + 1)); p.enable_reporting()
time.sleep(0.5); count[0] = 0; t0 = time.perf_counter(); time.sleep(seconds)
rate = count[0] / (time.perf_counter() - t0)
times.sort()
print(json.dumps({"p50": times[len(times)//2], "p99": times[int(len(times)*0.99)], "rate": rate}))
sys.stdout.flush()
board.exit()
"#;

fn quantile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() as f64 * q) as usize).min(sorted.len() - 1)]
}

/// hwgw's card: (p50 s, p99 s, analog reports/s).
fn hwgw(port: &str) -> (f64, f64, f64) {
    let config: FirmataConfig = toml::from_str(&format!(
        "port = \"{port}\"\nsampling_ms = 1\ndigital_in = [{{ pin = 2 }}]\ndigital_out = [{{ pin = 12 }}]"
    ))
    .unwrap();
    let card = Arc::new(FirmataCard::new(&config, Arc::new(MonotonicClock)).unwrap());
    let rt = rtt::Runtime::new(
        Arc::new(device_interface::Registry::new()),
        Default::default(),
    )
    .unwrap();
    let task = FirmataIo::add(
        &rt,
        "uno",
        FirmataBus::new(card.clone()),
        Default::default(),
    )
    .unwrap();
    task.start().unwrap();
    wait_until("online", || card.is_online());
    let mut times = Vec::with_capacity(TRIPS);
    for i in 0..TRIPS {
        let want = i % 2 == 0;
        let t0 = Instant::now();
        card.set_bit(0, want).unwrap();
        while card.read_bit(0).ok() != Some(want) {
            assert!(
                t0.elapsed() < Duration::from_secs(10),
                "hwgw: round trip {i} not back in 10 s"
            );
            std::thread::sleep(Duration::from_micros(50));
        }
        times.push(t0.elapsed().as_secs_f64());
    }
    task.stop().unwrap();
    // Analog: a card of the six channels, its decoded messages counted.
    let config: FirmataConfig = toml::from_str(&format!(
        "port = \"{port}\"\nsampling_ms = 1\nanalog_in = [{{ channel = 0 }}, {{ channel = 1 }}, {{ channel = 2 }}, {{ channel = 3 }}, {{ channel = 4 }}, {{ channel = 5 }}]"
    ))
    .unwrap();
    let card = Arc::new(FirmataCard::new(&config, Arc::new(MonotonicClock)).unwrap());
    let task = FirmataIo::add(
        &rt,
        "uno-a",
        FirmataBus::new(card.clone()),
        Default::default(),
    )
    .unwrap();
    task.start().unwrap();
    wait_until("online", || card.is_online());
    std::thread::sleep(Duration::from_millis(500));
    let (m0, t0) = (card.counters().line.messages, Instant::now());
    std::thread::sleep(Duration::from_secs_f64(ANALOG_SECONDS));
    let rate = (card.counters().line.messages - m0) as f64 / t0.elapsed().as_secs_f64();
    task.stop().unwrap();
    times.sort_by(f64::total_cmp);
    (quantile(&times, 0.5), quantile(&times, 0.99), rate)
}

fn main() {
    let py = pyfirmata2().unwrap();
    let mut sim = SimUno::start().unwrap();
    sim.wire(12, 2).unwrap();
    let port = sim.pty().to_str().unwrap().to_string();
    let (h50, h99, hrate) = hwgw(&port);
    let out = Command::new(PYTHON)
        .env("PYTHONPATH", &py)
        .args([
            "-c",
            PYFIRMATA,
            &port,
            &TRIPS.to_string(),
            &ANALOG_SECONDS.to_string(),
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let (p50, p99, prate) = (
        v["p50"].as_f64().unwrap(),
        v["p99"].as_f64().unwrap(),
        v["rate"].as_f64().unwrap(),
    );
    println!("digital round trip ({TRIPS} toggles, output pin 12 -> jumper -> input pin 2):");
    println!(
        "  hwgw       p50 {:7.2} ms  p99 {:7.2} ms",
        h50 * 1e3,
        h99 * 1e3
    );
    println!(
        "  pyfirmata2 p50 {:7.2} ms  p99 {:7.2} ms",
        p50 * 1e3,
        p99 * 1e3
    );
    println!(
        "  ratio hwgw/pyfirmata2: p50 {:.2}, p99 {:.2}",
        h50 / p50,
        h99 / p99
    );
    println!("analog reports per second (A0-A5, sampling 1 ms, {ANALOG_SECONDS} s):");
    println!(
        "  hwgw {hrate:8.1}/s  pyfirmata2 {prate:8.1}/s  ratio {:.2}",
        hrate / prate
    );
}
