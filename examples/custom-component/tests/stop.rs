//! A stop is never held up by a request waiting on a component: a call of the example's
//! own-thread operation `is_on` waits for the component's next period (ten minutes away
//! here); SIGTERM still drives the outputs to their safe values at once, and the waiting
//! client is let go.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::{Value, json};
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::time::Duration;
use testkit::{Service, TempDir, wait_until};

const BIN: &str = env!("CARGO_BIN_EXE_hwgw-example-custom");

const SLOW: &str = r#"
[[card]]
name = "sim0"
driver = "sim"
period_ms = 5
[card.outputs]
safe = { bit1 = true }
[card.sim]
digital_outputs = 4

[[component]]
name = "threshold"
type = "threshold"
activity = { type = "periodic", period_ms = 600000 }
"#;

#[test]
fn a_call_waiting_for_a_slow_component_does_not_hold_up_the_stop() {
    let dir = TempDir::new("slow-call-cfg");
    let cfg = dir.path().join("slow.toml");
    std::fs::write(&cfg, SLOW).unwrap();
    let svc = Service::start(BIN, "slow-call", &[&cfg], &[]).unwrap();
    svc.ok(json!({"cmd": "set", "component": "sim0.do", "port": "bit2", "value": true}));
    // The call waits in the component's queue for its next period.
    let mut caller = UnixStream::connect(&svc.socket).unwrap();
    caller
        .write_all(b"{\"id\":7,\"cmd\":\"call\",\"component\":\"threshold\",\"operation\":\"is_on\",\"args\":[]}\n")
        .unwrap();
    // Under way: this status request and the call.
    wait_until("the call under way", || {
        svc.ok(json!({"cmd": "status"}))["control"]["under_way"] == json!(2)
    });
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || tx.send(svc.terminate()).unwrap());
    // Ten minutes is the period: a stop waiting for it is a stop that hangs.
    let out = rx
        .recv_timeout(Duration::from_secs(60))
        .expect("the stop waited for the call");
    assert!(out.status.success(), "{}", out.log);
    for want in [
        "requests still under way after 2s",
        // bit1 safe, bit2 written by the client and back to its value before (off).
        "card \"sim0\" outputs at stop: analog [], digital on [1]",
    ] {
        assert!(out.log.contains(want), "{want:?} not in:\n{}", out.log);
    }
    // The waiting client was let go: an answer or the end of the stream, not silence.
    caller
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut line = String::new();
    BufReader::new(&caller).read_line(&mut line).unwrap();
    if !line.is_empty() {
        let v: Value = serde_json::from_str(&line).unwrap();
        assert_eq!(v["id"], json!(7), "{line}");
    }
}
