//! Remote reads through hwgw on Zenoh against bare Zenoh, side by side between the same
//! two processes.
//!
//! The bench runs itself twice: **B** serves 10 devices of 100 analog channels (1 000
//! channels) through a [`Node`] publishing at 100 Hz, and beside it publishes the same
//! values with bare `put`s on a session of its own (10 keys at 100 Hz, 100 raw `i64` and
//! the send time as bytes); **A** imports B's devices through its own node and subscribes
//! to the bare keys. Both paths run at once on loopback TCP, with the same Zenoh settings,
//! and both publish express, as the node does.
//!
//! Latency is the way of one sample on the same host's monotonic clock: for hwgw from B
//! reading the device to the sample being taken into A's proxy (JSON, the node's threads
//! and the proxy's atomics included); for bare Zenoh from just before the payload is built
//! to the subscriber's callback. Each process also reports its CPU time and resident
//! memory over the measured window.
//!
//! `cargo bench -p scaleout --bench remote` (set `HWGW_BENCH_SECONDS` to measure longer).

mod common;

use device_interface::time::{Clock, MonotonicClock};
use device_interface::{AnalogIn, Device, DeviceError, Health, RawRange, Scale, Status, Unit};
use hdrhistogram::Histogram;
use scaleout::config::ImportConfig;
use scaleout::{Node, ZenohConfig};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use zenoh::Wait;

const DEVICES: usize = 10;
const CHANNELS: u32 = 100;
const PERIOD: Duration = Duration::from_millis(10);

/// A device whose channel `c` reads `c + its step count`.
struct Counting {
    step: AtomicU64,
    scale: Scale,
}

impl Device for Counting {
    fn health(&self) -> Health {
        let now = MonotonicClock.now();
        Health {
            status: Status::Online,
            last_good: Some(now),
            checked_at: now,
            last_error: None,
        }
    }
}

impl AnalogIn for Counting {
    fn channel_count(&self) -> u32 {
        CHANNELS
    }
    fn scale(&self, _: u32) -> Result<Scale, DeviceError> {
        Ok(self.scale)
    }
    fn read_raw(&self, c: u32) -> Result<i64, DeviceError> {
        Ok((i64::from(c) + self.step.load(Ordering::Relaxed) as i64) % 65_536)
    }
}

fn config(name: &str, listen: Option<String>, connect: Option<String>) -> ZenohConfig {
    common::config(name, listen, connect, PERIOD.as_secs_f64() * 1000.0)
}

fn stat_cpu(path: &std::path::Path) -> f64 {
    let stat = std::fs::read_to_string(path).unwrap_or_default();
    let fields: Vec<&str> = stat
        .rsplit_once(')')
        .map_or("", |(_, r)| r)
        .split_whitespace()
        .collect();
    let ticks = |i: usize| {
        fields
            .get(i)
            .and_then(|f| f.parse::<f64>().ok())
            .unwrap_or(0.0)
    };
    // utime and stime are fields 14 and 15 of stat, 12 and 13 after the name.
    (ticks(11) + ticks(12)) / 100.0
}

/// CPU time (user + system) of this process, s, and its resident set, KiB.
fn cpu_and_rss() -> (f64, u64) {
    let cpu = stat_cpu(std::path::Path::new("/proc/self/stat"));
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let rss = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
        .unwrap_or(0);
    (cpu, rss)
}

/// CPU time of this process's thread named `name`, s (0 when there is none).
fn named_thread_cpu(name: &str) -> f64 {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
        return 0.0;
    };
    tasks
        .flatten()
        .find(|t| std::fs::read_to_string(t.path().join("comm")).is_ok_and(|c| c.trim() == name))
        .map_or(0.0, |t| stat_cpu(&t.path().join("stat")))
}

/// CPU time of the calling thread, s.
fn thread_cpu() -> f64 {
    nix::time::clock_gettime(nix::time::ClockId::CLOCK_THREAD_CPUTIME_ID)
        .map_or(0.0, |t| t.tv_sec() as f64 + t.tv_nsec() as f64 / 1e9)
}

fn seconds() -> u64 {
    std::env::var("HWGW_BENCH_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(10)
}

fn role_b(ports: (u16, u16)) {
    let registry = Arc::new(device_interface::Registry::new());
    let scale = Scale::linear(
        RawRange {
            min: 0,
            max: 65_535,
        },
        -10.0,
        10.0,
        Unit::new("V").unwrap_or_else(|e| panic!("{e}")),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let devices: Vec<Arc<Counting>> = (0..DEVICES)
        .map(|_| {
            Arc::new(Counting {
                step: AtomicU64::new(0),
                scale,
            })
        })
        .collect();
    for (i, d) in devices.iter().enumerate() {
        registry
            .analog_in()
            .register(&format!("dev{i}"), "bench", d.clone())
            .unwrap_or_else(|e| panic!("{e}"));
    }
    let node = Node::new(
        config("B", Some(format!("tcp/127.0.0.1:{}", ports.0)), None),
        registry,
    )
    .unwrap_or_else(|e| panic!("{e}"));
    node.start().unwrap_or_else(|e| panic!("{e}"));
    let bare = scaleout::session::open(&config(
        "Bbare",
        Some(format!("tcp/127.0.0.1:{}", ports.1)),
        None,
    ))
    .unwrap_or_else(|e| panic!("{e}"));
    let publishers: Vec<_> = (0..DEVICES)
        .map(|i| {
            bare.inner
                .declare_publisher(format!("bare/dev{i}"))
                .express(true)
                .wait()
                .unwrap_or_else(|e| panic!("{e}"))
        })
        .collect();
    let end = Instant::now() + Duration::from_secs(seconds() + 4);
    let mut next = Instant::now();
    let mut measured = None;
    let mut payload = Vec::with_capacity(8 + 8 * CHANNELS as usize);
    let mut cycle = 0u64;
    while Instant::now() < end {
        for (d, p) in devices.iter().zip(&publishers) {
            let step = d.step.fetch_add(1, Ordering::Relaxed);
            let t0 = MonotonicClock.now().as_nanos();
            payload.clear();
            payload.extend_from_slice(&t0.to_le_bytes());
            for c in 0..CHANNELS {
                let v = (i64::from(c) + step as i64 + 1) % 65_536;
                payload.extend_from_slice(&v.to_le_bytes());
            }
            let _ = p.put(payload.clone()).wait();
        }
        if measured.is_none()
            && end.duration_since(Instant::now()) < Duration::from_secs(seconds() + 1)
        {
            measured = Some((
                Instant::now(),
                cpu_and_rss().0,
                named_thread_cpu("hwgw-zn-pub"),
                thread_cpu(),
            ));
        }
        next += PERIOD;
        // Every 100 periods the bare puts move 1.3 ms against the node's, so one run
        // measures both paths over every phase of the two loops, not one by chance.
        cycle += 1;
        if cycle.is_multiple_of(100) {
            next += Duration::from_micros(1300);
        }
        std::thread::sleep(next.saturating_duration_since(Instant::now()));
    }
    let (cpu, rss) = cpu_and_rss();
    let (publisher, bare_loop) = (named_thread_cpu("hwgw-zn-pub"), thread_cpu());
    let (t, cpu0, publisher0, bare0) =
        measured.unwrap_or((Instant::now(), cpu, publisher, bare_loop));
    let pct = |a: f64, b: f64| 100.0 * (a - b) / t.elapsed().as_secs_f64();
    println!(
        "B cpu_percent={:.1} rss_mib={:.1} publisher_percent={:.2} bare_loop_percent={:.2}",
        pct(cpu, cpu0),
        rss as f64 / 1024.0,
        pct(publisher, publisher0),
        pct(bare_loop, bare0),
    );
    node.stop();
}

struct Stats {
    hist: Histogram<u64>,
    samples: u64,
}

impl Stats {
    fn new() -> Stats {
        Stats {
            hist: Histogram::new_with_bounds(1, 10_000_000_000, 3)
                .unwrap_or_else(|e| panic!("{e}")),
            samples: 0,
        }
    }
    fn record(&mut self, ns: u64) {
        self.samples += 1;
        let _ = self.hist.record(ns.max(1));
    }
}

fn role_a(ports: (u16, u16)) {
    let registry = Arc::new(device_interface::Registry::new());
    let mut cfg = config("A", None, Some(format!("tcp/127.0.0.1:{}", ports.0)));
    cfg.import = (0..DEVICES)
        .map(|i| ImportConfig {
            gateway: "B".into(),
            device: format!("dev{i}"),
            analog_in: Some(CHANNELS),
            analog_out: None,
            digital_in: None,
            digital_out: None,
            encoder: false,
        })
        .collect();
    let node = Node::new(cfg, registry.clone()).unwrap_or_else(|e| panic!("{e}"));
    node.start().unwrap_or_else(|e| panic!("{e}"));
    let bare = scaleout::session::open(&config(
        "Abare",
        None,
        Some(format!("tcp/127.0.0.1:{}", ports.1)),
    ))
    .unwrap_or_else(|e| panic!("{e}"));
    let measuring = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let bare_stats = Arc::new(Mutex::new(Stats::new()));
    let (m, st) = (measuring.clone(), bare_stats.clone());
    let _sub = bare
        .inner
        .declare_subscriber("bare/**")
        .callback(move |s: zenoh::sample::Sample| {
            let now = MonotonicClock.now().as_nanos();
            let bytes = s.payload().to_bytes();
            let Some(t0) = bytes.get(..8).and_then(|b| b.try_into().ok()) else {
                return;
            };
            // Read the values as a user would.
            let sum: i64 = bytes[8..]
                .chunks_exact(8)
                .filter_map(|c| c.try_into().ok().map(i64::from_le_bytes))
                .sum();
            std::hint::black_box(sum);
            if m.load(Ordering::Relaxed) {
                let t0 = u64::from_le_bytes(t0);
                if let Ok(mut st) = st.lock() {
                    st.record(now.saturating_sub(t0));
                }
            }
        })
        .wait()
        .unwrap_or_else(|e| panic!("{e}"));
    // Wait for B (bounded), then warm up.
    let proxy = registry
        .analog_in()
        .lookup("B/dev0")
        .unwrap_or_else(|e| panic!("{e}"));
    let end = Instant::now() + Duration::from_secs(20);
    while proxy.read(0).is_err() {
        assert!(
            Instant::now() < end,
            "B's devices never came: {:?}",
            node.report()
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    std::thread::sleep(Duration::from_secs(1));
    let mut hw = Stats::new();
    let mut last: Vec<u64> = vec![0; node.images().len()];
    let received = |node: &Node| -> u64 {
        node.images()
            .iter()
            .map(|i| i.counters.received.load(Ordering::Relaxed))
            .sum()
    };
    let received0 = received(&node);
    let (cpu0, _) = cpu_and_rss();
    let poller0 = thread_cpu();
    let start = Instant::now();
    measuring.store(true, Ordering::Relaxed);
    let window = Duration::from_secs(seconds());
    while start.elapsed() < window {
        for (img, last) in node.images().iter().zip(last.iter_mut()) {
            if let Some((read, rx)) = img.sample_times()
                && rx != *last
            {
                *last = rx;
                if rx >= read {
                    hw.record(rx - read);
                }
            }
        }
        std::thread::sleep(Duration::from_micros(50));
    }
    measuring.store(false, Ordering::Relaxed);
    let secs = start.elapsed().as_secs_f64();
    let (cpu, rss) = cpu_and_rss();
    // The bench's own poller is not the gateway's work.
    let poller = thread_cpu() - poller0;
    let received = received(&node) - received0;
    let lost: u64 = node
        .images()
        .iter()
        .map(|i| i.counters.lost.load(Ordering::Relaxed))
        .sum();
    let bare = bare_stats
        .lock()
        .map(|s| (s.hist.clone(), s.samples))
        .unwrap_or_else(|e| panic!("{e}"));
    let us = |h: &Histogram<u64>, q: f64| h.value_at_quantile(q) as f64 / 1000.0;
    println!(
        "A hwgw_p50_us={:.1} hwgw_p99_us={:.1} hwgw_seen={} bare_p50_us={:.1} bare_p99_us={:.1} bare_samples_per_s={:.0} hwgw_received={} hwgw_lost_total={} cpu_percent={:.1} rss_mib={:.1} window_s={:.1}",
        us(&hw.hist, 0.5),
        us(&hw.hist, 0.99),
        hw.samples,
        us(&bare.0, 0.5),
        us(&bare.0, 0.99),
        bare.1 as f64 / secs,
        received,
        lost,
        100.0 * (cpu - cpu0 - poller) / secs,
        rss as f64 / 1024.0,
        secs,
    );
    let _ = (received, hw.samples);
    node.stop();
}

fn field(line: &str, key: &str) -> f64 {
    line.split_whitespace()
        .find_map(|kv| kv.strip_prefix(key)?.strip_prefix('='))
        .and_then(|v| v.parse().ok())
        .unwrap_or(f64::NAN)
}

fn main() {
    match common::role() {
        Some((role, ports)) if role == "a" => return role_a(ports),
        Some((role, ports)) if role == "b" => return role_b(ports),
        _ => {}
    }
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    let ports = common::ports();
    let spawn = |role: &str| common::spawn(role, &ports);
    let b = spawn("b");
    let a = spawn("a");
    let a = a.wait_with_output().unwrap_or_else(|e| panic!("{e}"));
    let b = b.wait_with_output().unwrap_or_else(|e| panic!("{e}"));
    let a = String::from_utf8_lossy(&a.stdout).trim().to_string();
    let b = String::from_utf8_lossy(&b.stdout).trim().to_string();
    println!("{b}\n{a}");
    let per_s = field(&a, "hwgw_received") / field(&a, "window_s");
    println!(
        "remote read, {DEVICES} devices x {CHANNELS} channels at {} Hz ({} channels):",
        1000 / PERIOD.as_millis(),
        DEVICES as u32 * CHANNELS
    );
    println!(
        "  hwgw  p50 {:>7.1} us  p99 {:>7.1} us  ~{per_s:.0} samples/s ({} channel values/s), lost {}",
        field(&a, "hwgw_p50_us"),
        field(&a, "hwgw_p99_us"),
        per_s * f64::from(CHANNELS),
        field(&a, "hwgw_lost_total"),
    );
    println!(
        "  bare  p50 {:>7.1} us  p99 {:>7.1} us  {:.0} samples/s",
        field(&a, "bare_p50_us"),
        field(&a, "bare_p99_us"),
        field(&a, "bare_samples_per_s"),
    );
    println!(
        "  ratio hwgw/bare: p50 {:.2}x, p99 {:.2}x",
        field(&a, "hwgw_p50_us") / field(&a, "bare_p50_us"),
        field(&a, "hwgw_p99_us") / field(&a, "bare_p99_us"),
    );
    println!(
        "  process A (importer): cpu {:.1} % (the bench's poller left out), rss {:.1} MiB; process B (publisher): cpu {:.1} %, rss {:.1} MiB (both paths and Zenoh's threads)",
        field(&a, "cpu_percent"),
        field(&a, "rss_mib"),
        field(&b, "cpu_percent"),
        field(&b, "rss_mib"),
    );
    println!(
        "  in B: hwgw's publisher thread {:.2} % (reading, JSON, puts), the bare put loop {:.2} %",
        field(&b, "publisher_percent"),
        field(&b, "bare_loop_percent"),
    );
}
