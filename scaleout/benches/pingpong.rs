//! A remote write through hwgw's Zenoh node against a bare Zenoh query/reply pair, ping-pong
//! style: as Zenoh's own published comparison measures, a 64-byte payload, back to back,
//! the latency being half the round trip.
//!
//! The bench runs itself three times: **B** starts a [`Node`] whose control handler takes
//! `set` requests (it parses the request, stores the value and acknowledges, as a gateway's
//! handler does before its port write), and beside it a bare Zenoh session with a queryable
//! that answers each query with 64 bytes from its callback; **A** sends, through its own
//! node, `{"cmd":"set","component":…,"port":"ch0","value":…}` of exactly 64 bytes
//! (`Node::request`, what `hwgw set B/…` sends) and waits for B's acknowledgement, then the
//! bare query of 64 bytes, with the same query options (all targets, no consolidation).
//! Both on loopback TCP with the same Zenoh settings; each waits for its peer's first
//! answer before it measures.
//!
//! `PINGPONG_ROUNDS` rounds (default 10) of `PINGPONG_COUNT` (default 1000) of each, the two
//! in turn within each round (which goes first alternates). Prints each round's p50 and p99
//! of half the round trip for both and their ratios, then the same over every round.
//!
//! `cargo bench -p scaleout --bench pingpong`.

mod common;

use device_interface::Registry;
use hdrhistogram::Histogram;
use scaleout::Node;
use std::io::Read;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use zenoh::Wait;

const PAYLOAD: usize = 64;
const BARE_KEY: &str = "bench/pong";

fn env(key: &str, default: u64) -> u64 {
    std::env::var(key)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

/// B: serves until its standard input closes.
fn role_b(ports: (u16, u16)) {
    let node = Node::new(
        common::config("B", Some(format!("tcp/127.0.0.1:{}", ports.0)), None, 10.0),
        Arc::new(Registry::new()),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let written = Arc::new(AtomicU64::new(0));
    let w = written.clone();
    node.set_control(Arc::new(move |req: serde_json::Value| {
        match (req["cmd"].as_str(), req["value"].as_f64()) {
            (Some("set"), Some(v)) => {
                w.store(v.to_bits(), Ordering::Relaxed);
                serde_json::json!({"ok": null})
            }
            _ => serde_json::json!({"error": {"kind": "invalid", "message": "not a set"}}),
        }
    }));
    node.start().unwrap_or_else(|e| panic!("{e}"));
    let bare = scaleout::session::open(&common::config(
        "Bbare",
        Some(format!("tcp/127.0.0.1:{}", ports.1)),
        None,
        10.0,
    ))
    .unwrap_or_else(|e| panic!("{e}"));
    let _queryable = bare
        .inner
        .declare_queryable(BARE_KEY)
        .callback(|q| {
            let _ = q.reply(q.key_expr().clone(), vec![0x55u8; PAYLOAD]).wait();
        })
        .wait()
        .unwrap_or_else(|e| panic!("{e}"));
    println!("B ready");
    let mut sink = Vec::new();
    let _ = std::io::stdin().read_to_end(&mut sink);
    println!(
        "B last_value={}",
        f64::from_bits(written.load(Ordering::Relaxed))
    );
    node.stop();
}

/// The `set` request of value `v`, padded to exactly [`PAYLOAD`] bytes by the component's
/// name.
fn request(v: f64) -> serde_json::Value {
    let make = |name: &str| serde_json::json!({"cmd": "set", "component": name, "port": "ch0", "value": v});
    let len = make("").to_string().len();
    let r = make(&"x".repeat(PAYLOAD.saturating_sub(len)));
    assert_eq!(r.to_string().len(), PAYLOAD, "{r}");
    r
}

fn hist() -> Histogram<u64> {
    Histogram::new_with_bounds(1, 10_000_000_000, 3).unwrap_or_else(|e| panic!("{e}"))
}

/// One hwgw ping-pong: the round trip, ns.
fn hwgw_once(node: &Node, v: f64) -> Result<u64, String> {
    let req = request(v);
    let t0 = Instant::now();
    let reply = node.request("B", &req).map_err(|e| e.to_string())?;
    let ns = t0.elapsed().as_nanos() as u64;
    if reply.get("error").is_some() {
        return Err(format!("B refused the set: {reply}"));
    }
    Ok(ns)
}

/// One bare ping-pong: the round trip, ns.
fn bare_once(s: &zenoh::Session) -> Result<u64, String> {
    let t0 = Instant::now();
    let replies = s
        .get(BARE_KEY)
        .payload(vec![0xAAu8; PAYLOAD])
        .target(zenoh::query::QueryTarget::All)
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(Duration::from_secs(5))
        .wait()
        .map_err(|e| e.to_string())?;
    let reply = replies.recv().map_err(|e| e.to_string())?;
    let ns = t0.elapsed().as_nanos() as u64;
    match reply.result() {
        Ok(s) if s.payload().len() == PAYLOAD => Ok(ns),
        Ok(s) => Err(format!("a reply of {} bytes", s.payload().len())),
        Err(e) => Err(format!("an error reply: {e:?}")),
    }
}

fn role_a(ports: (u16, u16)) {
    let node = Node::new(
        common::config("A", None, Some(format!("tcp/127.0.0.1:{}", ports.0)), 10.0),
        Arc::new(Registry::new()),
    )
    .unwrap_or_else(|e| panic!("{e}"));
    node.start().unwrap_or_else(|e| panic!("{e}"));
    let bare = scaleout::session::open(&common::config(
        "Abare",
        None,
        Some(format!("tcp/127.0.0.1:{}", ports.1)),
        10.0,
    ))
    .unwrap_or_else(|e| panic!("{e}"));
    // Ready when each path has answered once (B's node and queryable are up and routed).
    let end = Instant::now() + Duration::from_secs(60);
    while hwgw_once(&node, 0.0).is_err() || bare_once(&bare.inner).is_err() {
        assert!(Instant::now() < end, "B did not answer in 60 s");
    }
    let rounds = env("PINGPONG_ROUNDS", 10).max(1);
    let count = env("PINGPONG_COUNT", 1000).max(1);
    let (mut all_h, mut all_b) = (hist(), hist());
    println!(
        "{:<6} {:>12} {:>12} {:>12} {:>12} {:>9} {:>9}",
        "round", "hwgw p50 µs", "hwgw p99 µs", "bare p50 µs", "bare p99 µs", "p50 ×", "p99 ×"
    );
    for round in 0..rounds {
        let (mut h, mut b) = (hist(), hist());
        let hwgw = |h: &mut Histogram<u64>| {
            for i in 0..count {
                let ns = hwgw_once(&node, i as f64 * 0.5).unwrap_or_else(|e| panic!("{e}"));
                let _ = h.record(ns / 2);
            }
        };
        let bare_run = |b: &mut Histogram<u64>| {
            for _ in 0..count {
                let ns = bare_once(&bare.inner).unwrap_or_else(|e| panic!("{e}"));
                let _ = b.record(ns / 2);
            }
        };
        if round % 2 == 0 {
            hwgw(&mut h);
            bare_run(&mut b);
        } else {
            bare_run(&mut b);
            hwgw(&mut h);
        }
        print_row(&(round + 1).to_string(), &h, &b);
        let _ = all_h.add(&h);
        let _ = all_b.add(&b);
    }
    print_row("all", &all_h, &all_b);
    node.stop();
}

fn print_row(name: &str, h: &Histogram<u64>, b: &Histogram<u64>) {
    let us = |h: &Histogram<u64>, q: f64| h.value_at_quantile(q) as f64 / 1000.0;
    println!(
        "{:<6} {:>12.1} {:>12.1} {:>12.1} {:>12.1} {:>9.2} {:>9.2}",
        name,
        us(h, 0.5),
        us(h, 0.99),
        us(b, 0.5),
        us(b, 0.99),
        us(h, 0.5) / us(b, 0.5),
        us(h, 0.99) / us(b, 0.99)
    );
}

fn main() {
    match common::role() {
        Some((role, ports)) if role == "a" => return role_a(ports),
        Some((role, ports)) if role == "b" => return role_b(ports),
        _ => {}
    }
    if std::env::args().any(|a| a == "--list" || a == "--test") {
        return;
    }
    let ports = common::ports();
    let spawn = |role: &str| common::spawn(role, &ports);
    println!(
        "remote set through hwgw's node vs a bare Zenoh query/reply, {PAYLOAD}-byte payload, \
         back to back; half the round trip"
    );
    let mut b = spawn("b");
    let a = spawn("a");
    let a = a.wait_with_output().unwrap_or_else(|e| panic!("{e}"));
    drop(b.stdin.take());
    let _ = b.wait();
    print!("{}", String::from_utf8_lossy(&a.stdout));
    assert!(a.status.success(), "A failed: {}", a.status);
}
