//! What the web and metrics servers cost the components (`cargo bench -p hwgw --bench
//! web_load`): the real binary runs the demo (its card stepped every 1 ms, inputs sampled
//! every 2 ms) with `[server.metrics]` and `[server.web]`, through four phases of
//! `WEB_BENCH_SECONDS` each (default 20):
//!
//! 1. quiet: the servers up, nobody connected (the reference);
//! 2. four pages open: four live streams read, `/api/status` every 2 s and a scrape of
//!    `/metrics` every second each;
//! 3. four Foxglove clients (`[server.foxglove]` with `devices` and `steps`), each
//!    subscribed to every channel and reading all;
//! 4. hostile: 1000 connections held and opened again, 50 slowloris clients, a 1 MB
//!    header every 100 ms, paths that climb out, as fast as answered; a Foxglove client
//!    sending garbage as fast as it can, opened again when closed;
//! 5. quiet again.
//!
//! `WEB_BENCH_FIFO=1` runs the card's thread and the blinker under SCHED_FIFO (the
//! servers' threads stay SCHED_OTHER), as a real-time deployment would.
//!
//! For each phase, from the activities' own histograms (`hwgw status`, the difference
//! between the phase's end and start): every periodic component's mean step time (exact),
//! its step time and wake-up lateness p99 (the upper bound of the power-of-two bucket the
//! p99 falls in), and the ratio of each to the first quiet phase. All traffic goes to
//! 127.0.0.1, bounded in count and time.

#![allow(
    clippy::unwrap_used,
    reason = "bench code: a failed unwrap is a failed run"
)]

use serde_json::{Value, json};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};
use testkit::Service;

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const DEMO: &str = include_str!("../../config/demo.toml");
const WATCHED: [&str; 4] = ["sim0", "sim0.ai", "blink", "output_watchdog"];

/// One component's figures over a phase.
#[derive(Debug, Clone, Copy)]
struct Figures {
    steps: u64,
    step_mean_us: f64,
    step_p99_us: f64,
    late_p99_us: f64,
}

fn histogram(c: &Value, key: &str) -> Vec<u64> {
    serde_json::from_value(c[key].clone()).unwrap_or_default()
}

/// The upper bound of the bucket `q` of the counts falls in, µs.
fn quantile_us(h: &[u64], q: f64) -> f64 {
    let total: u64 = h.iter().sum();
    if total == 0 {
        return 0.0;
    }
    let want = (q * total as f64).ceil() as u64;
    let mut seen = 0;
    for (i, n) in h.iter().enumerate() {
        seen += n;
        if seen >= want {
            return (1u64 << (i + 1)) as f64 / 1e3;
        }
    }
    f64::NAN
}

fn minus(a: &[u64], b: &[u64]) -> Vec<u64> {
    (0..a.len().max(b.len()))
        .map(|i| {
            a.get(i)
                .unwrap_or(&0)
                .saturating_sub(*b.get(i).unwrap_or(&0))
        })
        .collect()
}

fn components(svc: &Service) -> Vec<Value> {
    svc.ok(json!({"cmd": "status"}))["components"]
        .as_array()
        .unwrap()
        .clone()
}

fn figures(before: &[Value], after: &[Value], name: &str) -> Figures {
    let find = |l: &[Value]| l.iter().find(|c| c["name"] == name).unwrap().clone();
    let (a, b) = (find(before), find(after));
    let steps = b["steps"].as_u64().unwrap() - a["steps"].as_u64().unwrap();
    let total = b["step_total_ns"].as_u64().unwrap() - a["step_total_ns"].as_u64().unwrap();
    let step = minus(
        &histogram(&b, "step_histogram"),
        &histogram(&a, "step_histogram"),
    );
    let late = minus(
        &histogram(&b, "lateness_histogram"),
        &histogram(&a, "lateness_histogram"),
    );
    Figures {
        steps,
        step_mean_us: total as f64 / steps.max(1) as f64 / 1e3,
        step_p99_us: quantile_us(&step, 0.99),
        late_p99_us: quantile_us(&late, 0.99),
    }
}

/// Four open pages: a live stream each, status every 2 s, a scrape every second.
fn pages(web: SocketAddr, metrics: SocketAddr, stop: &Arc<AtomicBool>, bytes: &Arc<AtomicU64>) {
    let mut threads = Vec::new();
    for _ in 0..4 {
        let (stop, bytes) = (stop.clone(), bytes.clone());
        threads.push(std::thread::spawn(move || {
            let mut c = TcpStream::connect(web).unwrap();
            c.write_all(b"GET /api/live HTTP/1.1\r\nhost: x\r\n\r\n")
                .unwrap();
            c.set_read_timeout(Some(Duration::from_millis(200)))
                .unwrap();
            let mut buf = [0u8; 4096];
            let mut last = Instant::now() - Duration::from_secs(10);
            while !stop.load(Ordering::Relaxed) {
                if let Ok(n) = c.read(&mut buf) {
                    bytes.fetch_add(n as u64, Ordering::Relaxed);
                }
                if last.elapsed() >= Duration::from_secs(1) {
                    last = Instant::now();
                    let _ = testkit::http::request(metrics, "GET", "/metrics", &[], b"");
                    let _ = testkit::http::request(web, "GET", "/api/status", &[], b"");
                }
            }
        }));
    }
    for t in threads {
        t.join().unwrap();
    }
}

/// A Foxglove client subscribed to every channel, reading until `stop`; messages read.
fn foxglove(addr: SocketAddr, stop: &AtomicBool) -> u64 {
    use tungstenite::client::IntoClientRequest;
    let tcp = TcpStream::connect(addr).unwrap();
    tcp.set_read_timeout(Some(Duration::from_millis(200)))
        .unwrap();
    let mut req = format!("ws://{addr}/").into_client_request().unwrap();
    req.headers_mut().insert(
        "sec-websocket-protocol",
        "foxglove.websocket.v1".parse().unwrap(),
    );
    let Ok((mut ws, _)) = tungstenite::client::client(req, tcp) else {
        return 0;
    };
    let mut read = 0;
    let mut subscribed = false;
    while !stop.load(Ordering::Relaxed) {
        match ws.read() {
            Ok(tungstenite::Message::Text(t)) if !subscribed => {
                let v: Value = serde_json::from_str(t.as_str()).unwrap_or(Value::Null);
                if v["op"] == "advertise" {
                    let subs: Vec<Value> = v["channels"]
                        .as_array()
                        .unwrap()
                        .iter()
                        .map(|c| json!({"id": c["id"], "channelId": c["id"]}))
                        .collect();
                    let op = json!({"op": "subscribe", "subscriptions": subs});
                    let _ = ws.send(tungstenite::Message::text(op.to_string()));
                    subscribed = true;
                }
            }
            Ok(_) => read += 1,
            Err(tungstenite::Error::Io(e)) if e.kind() == std::io::ErrorKind::WouldBlock => {}
            Err(_) => break,
        }
    }
    read
}

/// Hostile clients until `stop`: held connections, slowloris, big heads, bad paths.
fn hostile(web: SocketAddr, fox: SocketAddr, stop: &Arc<AtomicBool>, sent: &Arc<AtomicU64>) {
    let mut threads = Vec::new();
    {
        let (stop, sent) = (stop.clone(), sent.clone());
        threads.push(std::thread::spawn(move || {
            use tungstenite::client::IntoClientRequest;
            while !stop.load(Ordering::Relaxed) {
                let Ok(tcp) = TcpStream::connect(fox) else {
                    continue;
                };
                let mut req = format!("ws://{fox}/").into_client_request().unwrap();
                req.headers_mut().insert(
                    "sec-websocket-protocol",
                    "foxglove.websocket.v1".parse().unwrap(),
                );
                let Ok((mut ws, _)) = tungstenite::client::client(req, tcp) else {
                    continue;
                };
                while !stop.load(Ordering::Relaxed)
                    && ws.send(tungstenite::Message::text("garbage")).is_ok()
                {
                    sent.fetch_add(1, Ordering::Relaxed);
                }
            }
        }));
    }
    {
        let (stop, sent) = (stop.clone(), sent.clone());
        threads.push(std::thread::spawn(move || {
            while !stop.load(Ordering::Relaxed) {
                let held: Vec<TcpStream> = (0..1000)
                    .filter_map(|_| TcpStream::connect_timeout(&web, Duration::from_secs(1)).ok())
                    .collect();
                sent.fetch_add(held.len() as u64, Ordering::Relaxed);
                std::thread::sleep(Duration::from_millis(500));
            }
        }));
    }
    {
        let (stop, sent) = (stop.clone(), sent.clone());
        threads.push(std::thread::spawn(move || {
            let mut slow: Vec<TcpStream> = Vec::new();
            while !stop.load(Ordering::Relaxed) {
                while slow.len() < 50 {
                    match TcpStream::connect_timeout(&web, Duration::from_secs(1)) {
                        Ok(mut c) => {
                            let _ = c.write_all(b"GET / HTTP/1.1\r\nhost: x\r\n");
                            slow.push(c);
                        }
                        Err(_) => break,
                    }
                }
                slow.retain_mut(|c| c.write_all(b"x").is_ok());
                sent.fetch_add(1, Ordering::Relaxed);
                std::thread::sleep(Duration::from_millis(500));
            }
        }));
    }
    {
        let (stop, sent) = (stop.clone(), sent.clone());
        threads.push(std::thread::spawn(move || {
            let mut big = b"GET / HTTP/1.1\r\nhost: x\r\nx-big: ".to_vec();
            big.extend(std::iter::repeat_n(b'a', 1 << 20));
            big.extend(b"\r\n\r\n");
            let paths = [
                "/../../etc/passwd",
                "/%2e%2e/%2e%2e/etc/passwd",
                "//etc/passwd",
            ];
            let mut i = 0;
            while !stop.load(Ordering::Relaxed) {
                if let Ok(mut c) = TcpStream::connect_timeout(&web, Duration::from_secs(1)) {
                    let _ = c.write_all(&big);
                }
                for _ in 0..10 {
                    let _ = testkit::http::request(web, "GET", paths[i % 3], &[], b"");
                    i += 1;
                }
                sent.fetch_add(11, Ordering::Relaxed);
                std::thread::sleep(Duration::from_millis(100));
            }
        }));
    }
    for t in threads {
        t.join().unwrap();
    }
}

fn phase(
    svc: &Service,
    seconds: u64,
    load: impl FnOnce(Arc<AtomicBool>) + Send + 'static,
) -> Vec<(String, Figures)> {
    let before = components(svc);
    let stop = Arc::new(AtomicBool::new(false));
    let s = stop.clone();
    let t = std::thread::spawn(move || load(s));
    std::thread::sleep(Duration::from_secs(seconds));
    stop.store(true, Ordering::Relaxed);
    t.join().unwrap();
    let after = components(svc);
    WATCHED
        .iter()
        .map(|n| (n.to_string(), figures(&before, &after, n)))
        .collect()
}

fn main() {
    let _ = testkit::set_fd_limit(None);
    let seconds: u64 = std::env::var("WEB_BENCH_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(20);
    let mut demo = DEMO
        .replace("period_ms = 10 ", "period_ms = 1 ")
        .replace("sample_period_ms = 20 ", "sample_period_ms = 2 ");
    let fifo = std::env::var_os("WEB_BENCH_FIFO").is_some();
    if fifo {
        // The card's thread and the blinker under SCHED_FIFO, as a real-time deployment has
        // them (the servers' threads stay SCHED_OTHER).
        demo = demo
            .replace(
                "[card.sim]",
                "thread = { policy = \"fifo\", priority = 60 }\n\n[card.sim]",
            )
            .replace(
                "activity = { type = \"periodic\", period_ms = 250 }",
                "activity = { type = \"periodic\", period_ms = 250, policy = \"fifo\", priority = 50 }",
            );
    }
    let text = format!(
        "{demo}\n[server.metrics]\nlisten = \"127.0.0.1:0\"\n\
         [server.web]\nlisten = \"127.0.0.1:0\"\nports = [\"sim0.ai.ch0\", \"sim0.ai.ch1\", \"sim0.ai.ch3\"]\n\
         [server.foxglove]\nlisten = \"127.0.0.1:0\"\ndevices = true\nsteps = true\n"
    );
    let svc = Service::run_text(HWGW, "web-bench", &text).unwrap();
    let (web, metrics) = (
        svc.server_address("server.web"),
        svc.server_address("server.metrics"),
    );
    let fox = svc.server_address("server.foxglove");
    let fox_read = Arc::new(AtomicU64::new(0));
    let streamed = Arc::new(AtomicU64::new(0));
    let hostile_sent = Arc::new(AtomicU64::new(0));
    let realtime: Vec<String> = components(&svc)
        .iter()
        .filter(|c| c["realtime"] == true)
        .map(|c| c["name"].as_str().unwrap().to_string())
        .collect();
    println!(
        "web_load: {seconds} s a phase; the demo's card stepped every 1 ms; \
         SCHED_FIFO asked: {fifo}, got by: {realtime:?}"
    );
    let quiet = phase(&svc, seconds, |_| {});
    let b = streamed.clone();
    let four = phase(&svc, seconds, move |stop| pages(web, metrics, &stop, &b));
    let r = fox_read.clone();
    let four_fox = phase(&svc, seconds, move |stop| {
        let readers: Vec<_> = (0..4)
            .map(|_| {
                let (stop, r) = (stop.clone(), r.clone());
                std::thread::spawn(move || r.fetch_add(foxglove(fox, &stop), Ordering::Relaxed))
            })
            .collect();
        for t in readers {
            t.join().unwrap();
        }
    });
    let h = hostile_sent.clone();
    let attacked = phase(&svc, seconds, move |stop| hostile(web, fox, &stop, &h));
    let again = phase(&svc, seconds, |_| {});
    println!(
        "four pages: {} bytes of live events read; four Foxglove clients: {} messages read; \
         hostile: {} connections, requests and messages",
        streamed.load(Ordering::Relaxed),
        fox_read.load(Ordering::Relaxed),
        hostile_sent.load(Ordering::Relaxed)
    );
    let web_status = svc.ok(json!({"cmd": "status"}))["servers"].clone();
    println!("servers after: {web_status}");
    println!(
        "\n| component | phase | steps | step mean µs | step p99 ≤ µs | lateness p99 ≤ µs | mean ÷ quiet | lateness p99 ÷ quiet |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for (i, name) in WATCHED.iter().enumerate() {
        let q = quiet[i].1;
        for (label, f) in [
            ("quiet", quiet[i].1),
            ("4 pages", four[i].1),
            ("4 Foxglove clients", four_fox[i].1),
            ("hostile", attacked[i].1),
            ("quiet again", again[i].1),
        ] {
            println!(
                "| {name} | {label} | {} | {:.1} | {:.0} | {:.0} | {:.2} | {:.2} |",
                f.steps,
                f.step_mean_us,
                f.step_p99_us,
                f.late_p99_us,
                f.step_mean_us / q.step_mean_us,
                f.late_p99_us / q.late_p99_us.max(f64::MIN_POSITIVE)
            );
        }
    }
    let health = svc.ok(json!({"cmd": "status"}))["health"].clone();
    println!("\nhealth at the end: {health}");
}
