//! `[server.opcua]` under hostile clients: 200 sessions opened and abandoned (the limit
//! holds, the rest refused and counted, the abandoned ones time out and new sessions are
//! taken again), 10 000 monitored items on one subscription (the limit holds), and
//! malformed messages from a raw socket (each connection closed; the server serves on,
//! nothing panics). The IO components' step times before and during are printed for the
//! notes (not asserted: a loaded machine's timing is no test).

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::json;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};
use testkit::Service;
use testkit::fixtures::SIM_CARD;
use testkit::opcua::UaClient;

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

/// Steps and time in steps (ns) of `component` so far.
fn steps(svc: &Service, component: &str) -> (u64, u64, u64) {
    let d = svc.ok(json!({"cmd": "describe", "component": component}));
    let a = &d["activity"];
    (
        a["steps"].as_u64().unwrap(),
        a["step_total_ns"].as_u64().unwrap(),
        a["step_max_ns"].as_u64().unwrap(),
    )
}

/// Mean step between two readings, µs.
fn mean_us(a: (u64, u64, u64), b: (u64, u64, u64)) -> f64 {
    (b.1 - a.1) as f64 / (b.0 - a.0).max(1) as f64 / 1000.0
}

/// An OPC UA TCP HEL message for `url` with the buffer and size fields given.
fn hello(url: &str, receive: u32, send: u32, max_message: u32) -> Vec<u8> {
    let mut body = Vec::new();
    for v in [0u32, receive, send, max_message, 0] {
        body.extend_from_slice(&v.to_le_bytes());
    }
    body.extend_from_slice(&(url.len() as i32).to_le_bytes());
    body.extend_from_slice(url.as_bytes());
    let mut m = b"HELF".to_vec();
    m.extend_from_slice(&(8 + body.len() as u32).to_le_bytes());
    m.extend_from_slice(&body);
    m
}

/// Sends `bytes` on a new connection; waits until the server closes it (reading what it
/// answers), at most 30 s. What it answered.
fn send_raw(addr: &str, bytes: &[u8]) -> Vec<u8> {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    // The server may close before all is written: that is an answer too.
    let _ = s.write_all(bytes);
    let start = Instant::now();
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    loop {
        match s.read(&mut buf) {
            Ok(0) => return got,
            Ok(n) => got.extend_from_slice(&buf[..n]),
            Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => return got,
            Err(e) => panic!(
                "the server kept a malformed connection open {:?}: {e}",
                start.elapsed()
            ),
        }
    }
}

#[test]
fn abandoned_sessions_many_items_and_malformed_messages_are_bounded() {
    let port = testkit::free_port();
    let addr = format!("127.0.0.1:{port}");
    let url = format!("opc.tcp://{addr}/");
    let text = format!(
        "{SIM_CARD}\n[server.opcua]\nlisten = \"{addr}\"\npki_dir = \"pki\"\n\
         [server.opcua.limits]\nsessions = 20\nsession_timeout_s = 5\n\
         monitored_items_per_subscription = 5000\n"
    );
    let svc = Service::run_text(HWGW, "opcua-hostile", &text).unwrap();
    let counters = || svc.server_status("server.opcua")["counters"].clone();
    // A quiet baseline: the input component's next 100 steps.
    let start = steps(&svc, "sim0.ai");
    let mut t0 = start;
    testkit::wait_until("100 quiet steps", || {
        t0 = steps(&svc, "sim0.ai");
        t0.0 >= start.0 + 100
    });

    // 200 sessions opened and never closed: the limit holds, the rest refused.
    let mut flooder = UaClient::open(&url);
    let a = flooder.ask(json!({"cmd": "flood", "url": url, "sessions": 200}));
    let opened = a["opened"].as_u64().unwrap_or_else(|| panic!("{a}"));
    let refused: u64 = a["refused"]
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    assert_eq!(opened + refused, 200, "{a}");
    assert_eq!(
        opened, 19,
        "the limit is 20 sessions, the flooder's own one of them: {a}"
    );
    assert_eq!(a["refused"]["BadTooManySessions"], 181, "{a}");
    let c = counters();
    assert_eq!(c["sessions"], 20, "{c}");
    let t1 = steps(&svc, "sim0.ai");
    drop(flooder);

    // Abandoned, they time out (5 s); then sessions are taken again.
    testkit::wait_until("the abandoned sessions timed out", || {
        counters()["sessions"] == 0
    });
    let c = counters();
    assert_eq!(c["sessions_timed_out"], 20, "{c}");

    // 10 000 monitored items on one subscription: 5000 taken, the rest refused.
    let mut client = UaClient::open(&url);
    let a = client.ask(json!({"cmd": "many_items", "id": "sim0.ai.ch0", "count": 10000, "chunk": 1000, "interval": 100}));
    assert_eq!(
        a["items"],
        json!({"Good": 5000, "BadTooManyMonitoredItems": 5000}),
        "{a}"
    );
    let v = client.ask(json!({"cmd": "read", "ids": ["sim0.ai.ch0"]}));
    assert_eq!(v["values"][0]["status"], "Good", "{v}");
    let t2 = steps(&svc, "sim0.ai");
    // (Closed now: asyncua's subscription, quiet longer than these 5 s sessions last, would
    // be dropped by the server as its session timed out.)
    client.ask(json!({"cmd": "close"}));

    // Malformed messages from a raw socket: each connection closed, nothing else.
    let mut rng = testkit::rng::Rng::new(7);
    let garbage: Vec<u8> = (0..65536).map(|_| rng.next_u64() as u8).collect();
    let mut huge = b"HELF".to_vec();
    huge.extend_from_slice(&u32::MAX.to_le_bytes());
    let mut truncated = hello(&url, 65536, 65536, 0);
    truncated.truncate(20);
    let mut bad_open = hello(&url, 65536, 65536, 0);
    bad_open.extend_from_slice(b"OPNF");
    bad_open.extend_from_slice(&64u32.to_le_bytes());
    bad_open.extend_from_slice(&[0xAB; 56]);
    let mut tiny_buffers = hello(&url, 1, 1, 1);
    tiny_buffers.extend_from_slice(b"MSGF\x10\x00\x00\x00\x01\x00\x00\x00\x02\x00\x00\x00");
    let long_url = hello(&"x".repeat(100_000), 65536, 65536, 0);
    let cases: [(&str, &[u8]); 7] = [
        ("random bytes", &garbage),
        ("a HEL of 4 GiB", &huge),
        ("a HEL cut short", &truncated),
        ("a garbled OPN", &bad_open),
        ("buffers of one byte", &tiny_buffers),
        ("an endpoint URL of 100 kB", &long_url),
        ("HTTP", b"GET / HTTP/1.1\r\nHost: x\r\n\r\n"),
    ];
    for (what, bytes) in cases {
        let answer = send_raw(&addr, bytes);
        eprintln!(
            "{what}: closed, answered {} bytes {:?}",
            answer.len(),
            String::from_utf8_lossy(&answer[..answer.len().min(4)])
        );
    }
    let t3 = steps(&svc, "sim0.ai");
    let v = UaClient::open(&url).ask(json!({"cmd": "read", "ids": ["sim0.ai.ch0"]}));
    assert_eq!(v["values"][0]["status"], "Good", "{v}");
    let c = counters();
    assert!(c["requests_rejected"].as_u64().unwrap() >= 181, "{c}");
    assert!(!svc.log_text().contains("panicked"), "{}", svc.log_text());
    eprintln!(
        "sim0.ai step mean, µs: before {:.1}; 200 sessions {:.1}; 10 000 items {:.1}; \
         malformed {:.1}; longest step so far {:.1}",
        mean_us(start, t0),
        mean_us(t0, t1),
        mean_us(t1, t2),
        mean_us(t2, t3),
        t3.2 as f64 / 1000.0
    );
    eprintln!("counters: {}", counters());
}
