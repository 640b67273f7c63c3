//! Every write to another gateway's output reaches it or its writer hears that it failed:
//! A sets B's analog output while B is not up yet, while B comes up, while B is killed,
//! and after B is started again. Each `set` answers `ok` only once B has the value (then
//! B's output holds it), or an error; none is left unanswered and none is lost silently —
//! A's status counts every failed write and has none pending once the dust settles.

use serde_json::{Value, json};
use std::time::{Duration, Instant};
use testkit::service::{Service, TempDir};
use testkit::wait::{PATIENCE, wait_for, wait_until};

const BIN: &str = env!("CARGO_BIN_EXE_hwgw");

/// B: the example listening on `endpoint`, its output watchdog long enough that a value A
/// set is still there when the test looks.
fn config_b(endpoint: &str) -> String {
    include_str!("../../config/zenoh-b.toml")
        .replace("tcp/127.0.0.1:7448", endpoint)
        .replace("watchdog_ms = 1000", "watchdog_ms = 600000")
}

/// A: the example connecting to `endpoint`, a write failing after 1 s without an
/// acknowledgement.
fn config_a(endpoint: &str) -> String {
    include_str!("../../config/zenoh-a.toml")
        .replace("tcp/127.0.0.1:7448", endpoint)
        .replace(
            "offline_ms = 1000",
            "offline_ms = 1000\nrequest_timeout_ms = 1000",
        )
}

/// The outcome of one `set` of B's analog output 1 from A.
fn set(a: &Service, v: f64) -> Result<(), String> {
    let r = a.request(json!({"cmd": "set", "component": "B/sim0.ao", "port": "ch1", "value": v}));
    match (r.get("ok"), r.get("error")) {
        (Some(_), _) => Ok(()),
        (_, Some(e)) => Err(e["message"].as_str().unwrap_or_default().to_string()),
        _ => panic!("neither ok nor error: {r}"),
    }
}

/// True when B's output reads `v` back (within half of its 16-bit raw step over 20 V; the
/// values set are 0.125 V apart or more).
fn holds(b: &Service, v: f64) -> bool {
    (on_b(b) - v).abs() < 0.0002
}

/// B's analog output 1 now.
fn on_b(b: &Service) -> f64 {
    let v = b.ok(json!({"cmd": "get", "component": "sim0.ao", "port": "ch1"}));
    v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"))
}

/// A's Zenoh counters (its imports summed: it imports B/sim0 alone).
fn import(a: &Service) -> Value {
    let s = a.ok(json!({"cmd": "status"}));
    s["servers"]
        .as_array()
        .and_then(|v| {
            v.iter()
                .find(|s| s["counters"].get("writes_pending").is_some())
        })
        .map(|s| s["counters"].clone())
        .unwrap_or_else(|| panic!("no Zenoh counters in {s}"))
}

/// Sets distinct values until one is acknowledged; every acknowledged value is on B at
/// once; returns how many failed first.
fn set_until_acknowledged(a: &Service, b: &Service, base: f64) -> usize {
    let mut failed = 0;
    let end = Instant::now() + PATIENCE * 2;
    for k in 0.. {
        let v = base + 0.125 * f64::from(k % 16);
        match set(a, v) {
            Ok(()) => {
                assert!(holds(b, v), "acknowledged, so B has {v}: {}", on_b(b));
                return failed;
            }
            Err(e) => {
                assert!(
                    e.contains("offline") || e.contains("not delivered"),
                    "a failed write says why: {e}"
                );
                failed += 1;
            }
        }
        assert!(
            Instant::now() < end,
            "no write acknowledged in {:?}",
            PATIENCE * 2
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    unreachable!()
}

#[test]
fn every_write_reaches_the_other_gateway_or_its_writer_hears_it_failed() {
    let dir = TempDir::new("zenoh-writes");
    let endpoint = format!("tcp/127.0.0.1:{}", testkit::free_port());
    let a_file = dir.path().join("a.toml");
    let b_file = dir.path().join("b.toml");
    std::fs::write(&a_file, config_a(&endpoint)).unwrap_or_else(|e| panic!("{e}"));
    std::fs::write(&b_file, config_b(&endpoint)).unwrap_or_else(|e| panic!("{e}"));

    // B not up: every write is refused at once (the device is offline), never taken.
    let a = Service::start(BIN, "zw-a", &[&a_file], &[]).unwrap_or_else(|e| panic!("{e}"));
    for k in 0..5 {
        let e = set(&a, 1.0 + f64::from(k)).expect_err("B is not up");
        assert!(e.contains("offline"), "{e}");
    }

    // B comes up: writes fail until B/sim0 is online in A, then each acknowledged one is
    // on B; a run of them, each checked.
    let b = Service::start(BIN, "zw-b", &[&b_file], &[]).unwrap_or_else(|e| panic!("{e}"));
    set_until_acknowledged(&a, &b, 2.0);
    for k in 0..10 {
        let v = -3.0 + 0.25 * f64::from(k);
        match set(&a, v) {
            Ok(()) => assert!(holds(&b, v), "acknowledged, so B has {v}: {}", on_b(&b)),
            Err(e) => assert!(e.contains("not delivered"), "{e}"),
        }
    }

    // An operation writing the output answers the same way: once B has the value.
    let r = a.ok(
        json!({"cmd": "call", "component": "B/sim0.ao", "operation": "write", "args": [1, 1.25]}),
    );
    match (r.get("Ok"), r["Err"].as_str()) {
        (Some(_), _) => assert!(holds(&b, 1.25), "acknowledged, so B has 1.25: {}", on_b(&b)),
        (_, Some(e)) => assert!(e.contains("not delivered"), "{e}"),
        _ => panic!("neither Ok nor Err: {r}"),
    }

    // B killed: the writes on their way and those made while A still sees B are failed
    // and said so (none answered ok), then refused as offline.
    let before = import(&a);
    drop(b.stop_with(nix::sys::signal::Signal::SIGKILL));
    let mut outcomes = Vec::new();
    wait_until("A sees B offline after the kill", || {
        outcomes.push(set(&a, 4.5));
        matches!(outcomes.last(), Some(Err(e)) if e.contains("offline"))
    });
    assert!(
        outcomes.iter().all(Result::is_err),
        "a write after B was killed answered ok: {outcomes:?}"
    );
    let r = a.ok(
        json!({"cmd": "call", "component": "B/sim0.ao", "operation": "write", "args": [1, 4.75]}),
    );
    assert!(
        r["Err"].as_str().is_some_and(|e| e.contains("offline")),
        "a write operation after B was killed: {r}"
    );
    let undelivered = outcomes
        .iter()
        .filter(|o| matches!(o, Err(e) if e.contains("not delivered")))
        .count() as u64;
    wait_until("A has no write to B pending", || {
        import(&a)["writes_pending"] == json!(0)
    });
    let after = import(&a);
    eprintln!("after the kill: {outcomes:?}; counters {after}");
    let failed = after["writes_failed"].as_u64().unwrap_or(0)
        - before["writes_failed"].as_u64().unwrap_or(0);
    assert!(
        failed >= undelivered,
        "{undelivered} sets were told 'not delivered' but A counts {failed} failed: {after}"
    );

    // B again: writes reach it once it is back.
    let b = Service::start(BIN, "zw-b2", &[&b_file], &[]).unwrap_or_else(|e| panic!("{e}"));
    set_until_acknowledged(&a, &b, 6.0);
    let done = wait_for("A's write counters settled", PATIENCE, || {
        import(&a)["writes_pending"] == json!(0)
    });
    if let Err(e) = done {
        panic!("{e}: {}", import(&a));
    }
}

/// The problems A's Zenoh node lists in its status.
fn problems(svc: &Service) -> String {
    let s = svc.ok(json!({"cmd": "status"}));
    s["servers"]
        .as_array()
        .and_then(|v| v.iter().find(|s| s["counters"].get("problems").is_some()))
        .map(|s| s["counters"]["problems"].to_string())
        .unwrap_or_else(|| panic!("no Zenoh problems in {s}"))
}

#[test]
fn two_gateways_with_one_name_both_say_so() {
    let dir = TempDir::new("zenoh-twins");
    let (p1, p2) = (testkit::free_port(), testkit::free_port());
    let first = config_b(&format!("tcp/127.0.0.1:{p1}"));
    let second = config_b(&format!("tcp/127.0.0.1:{p2}")).replace(
        "[zenoh]\n",
        &format!("[zenoh]\nconnect = [\"tcp/127.0.0.1:{p1}\"]\n"),
    );
    let (f1, f2) = (dir.path().join("b1.toml"), dir.path().join("b2.toml"));
    std::fs::write(&f1, first).unwrap_or_else(|e| panic!("{e}"));
    std::fs::write(&f2, second).unwrap_or_else(|e| panic!("{e}"));
    let b1 = Service::start(BIN, "zt-b1", &[&f1], &[]).unwrap_or_else(|e| panic!("{e}"));
    let b2 = Service::start(BIN, "zt-b2", &[&f2], &[]).unwrap_or_else(|e| panic!("{e}"));
    for b in [&b1, &b2] {
        wait_until("the other gateway named B noticed", || {
            problems(b).contains("another gateway answers to the name \\\"B\\\"")
        });
        assert!(b.log_text().contains("another gateway answers to the name"));
    }
}
