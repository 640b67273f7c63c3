//! The control server within the process's descriptor limit: a deployment asking for more
//! clients than the descriptors allow (each client costs two) takes as many as fit — the
//! log says so with both numbers — and turns the rest away as busy, rather than running
//! out of descriptors under them. A test binary of its own: it lowers this process's
//! descriptor limit, which the gateway it starts inherits.

use serde_json::Value;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::time::Duration;
use testkit::service::{Service, TempDir};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");

#[test]
fn clients_beyond_the_descriptor_limit_are_turned_away_not_starved() {
    use nix::sys::resource::{Resource, setrlimit};
    // Soft and hard: the gateway can raise neither. 256 kept for the rest leaves room for
    // (400 - 256) / 2 = 72 clients.
    setrlimit(Resource::RLIMIT_NOFILE, 400, 400).unwrap_or_else(|e| panic!("{e}"));
    let dir = TempDir::new("control-fds");
    let cfg = dir.path().join("fds.toml");
    // A top-level key goes before the first table.
    let text = format!(
        "control_clients = 1024\n{}",
        include_str!("../../config/demo.toml")
    );
    std::fs::write(&cfg, text).unwrap_or_else(|e| panic!("{e}"));
    let svc = Service::start(HWGW, "fds", &[&cfg], &[]).unwrap_or_else(|e| panic!("{e}"));
    let log = svc.log_text();
    assert!(
        log.contains("control_clients = 1024 needs 2304 file descriptors")
            && log.contains("taking 72 clients at once"),
        "{log}"
    );
    // 100 clients, each asking for the list: 72 are answered, the rest told busy.
    let mut held = Vec::new();
    let (mut served, mut busy) = (0, 0);
    for _ in 0..100 {
        let mut c = UnixStream::connect(&svc.socket).unwrap_or_else(|e| panic!("{e}"));
        c.set_read_timeout(Some(Duration::from_secs(30)))
            .unwrap_or_else(|e| panic!("{e}"));
        // A client turned away may be told so and closed before its request is written
        // (a broken pipe): its answer is read all the same.
        let _ = c.write_all(b"{\"cmd\":\"ls\"}\n");
        let mut line = String::new();
        BufReader::new(&c)
            .read_line(&mut line)
            .unwrap_or_else(|e| panic!("{e}"));
        let reply: Value = serde_json::from_str(&line).unwrap_or_else(|e| panic!("{line}: {e}"));
        if reply.get("ok").is_some() {
            served += 1;
        } else {
            assert_eq!(reply["error"]["kind"], "busy", "{reply}");
            busy += 1;
        }
        held.push(c);
    }
    assert_eq!((served, busy), (72, 28));
    drop(held);
    // The gateway is well and serves again, once it has seen the 72 go (they close on
    // their side first: a request at once may still find every slot taken).
    testkit::wait_until("a slot free again", || {
        svc.request(serde_json::json!({"cmd": "ls"}))["ok"].is_array()
    });
    assert!(svc.terminate().status.success());
}
