//! A required service in a running gateway, through the command line: `supervisor`
//! requires the `limit` service `threshold` provides (supervised.toml); `ls` shows the
//! binding ready; the threshold stopped is a lost service, seen and counted in `status`;
//! started again it is ready by itself, and the supervisor applies its limit again.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::{Value, json};
use testkit::{Service, wait_until};

const BIN: &str = env!("CARGO_BIN_EXE_hwgw-example-custom");

fn supervisor(status: &Value) -> Value {
    status["components"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == json!("supervisor"))
        .unwrap()
        .clone()
}

#[test]
fn a_lost_provider_is_told_counted_and_ready_again_when_it_returns() {
    let cfg = concat!(env!("CARGO_MANIFEST_DIR"), "/supervised.toml");
    let check = testkit::service::check(BIN, std::path::Path::new(cfg));
    let summary = String::from_utf8_lossy(&check.stdout).to_string();
    assert!(check.status.success(), "{summary}");
    assert!(
        summary.contains("provides limit") && summary.contains("requires limit -> threshold.limit"),
        "{summary}"
    );

    let svc = Service::start(BIN, "services", &[cfg], &[]).unwrap();
    // The supervisor imposed its limit (1.0) through the service.
    wait_until("the supervisor's limit applied", || {
        svc.out(&["get", "threshold", "property:above"])
            .ok()
            .as_deref()
            == Some("1.0")
    });
    let ls = svc.out(&["ls", "supervisor"]).unwrap();
    assert!(ls.contains("requires:"), "{ls}");
    assert!(ls.contains("limit  -> threshold.limit (ready)"), "{ls}");
    let ls = svc.out(&["ls", "threshold"]).unwrap();
    assert!(ls.contains("limit: set, is_on"), "{ls}");
    assert_eq!(
        svc.out(&["call", "threshold", "limit.is_on"])
            .map(|s| s == "true" || s == "false"),
        Ok(true)
    );

    svc.out(&["lifecycle", "stop", "threshold"]).unwrap();
    wait_until("the loss counted", || {
        supervisor(&svc.ok(json!({"cmd": "status"})))["counters"]["services_lost"] == json!(1)
    });
    let ls = svc.out(&["ls", "supervisor"]).unwrap();
    assert!(
        ls.contains("(not ready)") && ls.contains("lost 1, back 0"),
        "{ls}"
    );
    // Meanwhile somebody changes the limit; the supervisor puts its own back.
    svc.out(&["set", "threshold", "property:above", "3"])
        .unwrap();
    svc.out(&["lifecycle", "start", "threshold"]).unwrap();
    wait_until("the return counted", || {
        supervisor(&svc.ok(json!({"cmd": "status"})))["counters"]["services_back"] == json!(1)
    });
    wait_until("the supervisor's limit applied again", || {
        svc.out(&["get", "threshold", "property:above"])
            .ok()
            .as_deref()
            == Some("1.0")
    });
    let ls = svc.out(&["ls", "supervisor"]).unwrap();
    assert!(
        ls.contains("(ready)") && ls.contains("lost 1, back 1"),
        "{ls}"
    );
    let out = svc.terminate();
    assert!(out.status.success(), "{}", out.log);
    assert!(
        out.log.contains("service \"limit\" lost; waiting for it"),
        "{}",
        out.log
    );
}
