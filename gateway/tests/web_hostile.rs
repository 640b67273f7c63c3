//! Hostile clients of the web and metrics servers, against the real binary: a thousand
//! connections at once, slowloris, a 1 MB header, paths that try to climb out. Each is
//! bounded and counted (`hwgw status` shows the server's counters), and the gateway goes
//! on serving. (How its components' step times fare meanwhile is measured by
//! `cargo bench -p hwgw --bench web_load`, never asserted here.)
#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::Value;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::Duration;
use testkit::http::{get, parse};
use testkit::{Service, wait_until};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const DEMO: &str = include_str!("../../config/demo.toml");
const CLIENTS: usize = 16;

fn start(tag: &str) -> (Service, SocketAddr) {
    let text = format!(
        "{DEMO}\n[server.web]\nlisten = \"127.0.0.1:0\"\nmax_clients = {CLIENTS}\n\
         ports = [\"sim0.ai.ch0\"]\n"
    );
    let svc = Service::run_text(HWGW, tag, &text).unwrap();
    let addr = counters(&svc)["bus"].as_str().unwrap().parse().unwrap();
    (svc, addr)
}

/// The web server's entry in `hwgw status`.
fn counters(svc: &Service) -> Value {
    svc.server_status("server.web")
}

fn counter(svc: &Service, name: &str) -> u64 {
    counters(svc)["counters"][name].as_u64().unwrap()
}

/// The server still answers a plain request, once its slots are free again.
fn serves(addr: SocketAddr) {
    wait_until("the page is served again", || {
        testkit::http::request(addr, "GET", "/health", &[], b"").is_ok_and(|a| a.status == 200)
    });
}

/// What a connection got: an answer, or nothing before it closed (or the timeout).
fn answer_of(c: &mut TcpStream) -> Option<u16> {
    let _ = c.set_read_timeout(Some(Duration::from_secs(20)));
    let mut raw = Vec::new();
    let _ = c.read_to_end(&mut raw);
    parse(&raw).map(|a| a.status)
}

#[test]
fn a_thousand_connections_at_once_are_bounded_and_counted() {
    let _ = testkit::set_fd_limit(None);
    let (svc, addr) = start("web-thousand");
    let mut conns: Vec<TcpStream> = (0..1000)
        .filter_map(|_| TcpStream::connect_timeout(&addr, Duration::from_secs(10)).ok())
        .collect();
    assert!(conns.len() > 900, "only {} connected", conns.len());
    // While all are held, the server holds no more than its limit.
    let held = counters(&svc)["counters"]["connected"].as_u64().unwrap();
    assert!(held <= CLIENTS as u64, "{held} connections held");
    // The ones past the limit are told so at once; the others wait for a request that
    // never comes, and are closed when the head timeout ends.
    let answers: Vec<Option<u16>> = conns.iter_mut().map(answer_of).collect();
    let busy = answers.iter().filter(|a| **a == Some(503)).count();
    assert!(busy > 0, "nobody was told busy");
    assert!(
        answers
            .iter()
            .all(|a| matches!(a, None | Some(503) | Some(408))),
        "{answers:?}"
    );
    drop(conns);
    serves(addr);
    assert!(counter(&svc, "refused") >= busy as u64);
    assert!(counter(&svc, "head_timeouts") >= 1);
    assert_eq!(get(addr, "/health").status, 200);
}

#[test]
fn slowloris_is_closed_at_the_head_timeout() {
    let (svc, addr) = start("web-slowloris");
    let mut slow: Vec<TcpStream> = (0..CLIENTS)
        .map(|_| {
            let mut c = TcpStream::connect(addr).unwrap();
            c.write_all(b"GET / HTTP/1.1\r\nhost: x\r\n").unwrap();
            c
        })
        .collect();
    // A header a byte at a time, for longer than the head may take (5 s).
    for _ in 0..16 {
        for c in &mut slow {
            let _ = c.write_all(b"x");
        }
        std::thread::sleep(Duration::from_millis(500));
    }
    // By now the server closed each: a read ends (or is reset) rather than waiting.
    let closed: Vec<bool> = slow
        .iter_mut()
        .map(|c| {
            let _ = c.set_read_timeout(Some(Duration::from_secs(10)));
            let mut buf = Vec::new();
            match c.read_to_end(&mut buf) {
                Ok(_) => true,
                Err(e) => !matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ),
            }
        })
        .collect();
    assert!(closed.iter().all(|d| *d), "still open: {closed:?}");
    wait_until("every slow client counted", || {
        counter(&svc, "head_timeouts") >= CLIENTS as u64
    });
    serves(addr);
}

#[test]
fn a_megabyte_of_headers_is_refused_and_counted() {
    let (svc, addr) = start("web-big-head");
    let mut c = TcpStream::connect(addr).unwrap();
    let mut req = b"GET / HTTP/1.1\r\nhost: x\r\nx-big: ".to_vec();
    req.extend(std::iter::repeat_n(b'a', 1 << 20));
    req.extend(b"\r\n\r\n");
    // The server stops reading after its limit: the rest may not be written.
    let _ = c.write_all(&req);
    let status = answer_of(&mut c);
    assert!(matches!(status, None | Some(431)), "{status:?}");
    wait_until("the big head counted", || {
        counter(&svc, "bad_requests") >= 1
    });
    serves(addr);
}

#[test]
fn paths_that_climb_out_find_nothing() {
    let (_svc, addr) = start("web-paths");
    for path in [
        "/../../../../etc/passwd",
        "/%2e%2e/%2e%2e/etc/passwd",
        "/%2E%2E%2F%2E%2E%2Fetc%2Fpasswd",
        "//etc/passwd",
        "/app.js/../../../etc/passwd",
        "/api/../../etc/passwd",
        "/style.css%00.html",
        "/index.html",
        "/api/status/../../etc/passwd",
    ] {
        let a = get(addr, path);
        assert!(
            a.status == 404 || a.status == 400,
            "{path}: {} {}",
            a.status,
            a.text()
        );
        assert!(!a.text().contains("root:"), "{path}");
    }
    // Not a path at all.
    let mut c = TcpStream::connect(addr).unwrap();
    c.write_all(b"GET ../etc/passwd HTTP/1.1\r\nhost: x\r\n\r\n")
        .unwrap();
    let status = answer_of(&mut c);
    assert!(matches!(status, None | Some(400)), "{status:?}");
    assert_eq!(get(addr, "/health").status, 200);
    // A name that is not this host's (a site's own name resolved to 127.0.0.1).
    let rebound = [("host", "evil.example")];
    let a = testkit::http::request(addr, "GET", "/api/status", &rebound, b"").unwrap();
    assert_eq!(a.status, 421, "{}", a.text());
}
