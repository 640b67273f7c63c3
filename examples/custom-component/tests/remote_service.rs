//! A required service bound to a component of another gateway on Zenoh: two gateways in
//! network namespaces of the test's own, B running `threshold` (which provides `limit`),
//! A running `supervisor` with `requires = { limit = "B/thr.limit" }`. A starts first:
//! the binding waits, not ready; B comes and the supervisor imposes its limit on B's
//! threshold through the binding; B's threshold stopped is a lost service on A, seen and
//! counted, started again it is back; a cut link is a loss too, and the restored link a
//! return.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::{Value, json};
use testkit::netns::{ADDR_B, Pair};
use testkit::{Service, TempDir, wait_until};

const BIN: &str = env!("CARGO_BIN_EXE_hwgw-example-custom");

fn b_config(listen: &str) -> String {
    format!(
        "[zenoh]\nname = \"B\"\nlisten = [\"{listen}\"]\n\n\
         [[component]]\nname = \"thr\"\ntype = \"threshold\"\n\
         activity = {{ type = \"non_periodic\" }}\nproperties = {{ above = 5.0 }}\n"
    )
}

fn a_config(connect: &str) -> String {
    format!(
        "[zenoh]\nname = \"A\"\nconnect = [\"{connect}\"]\n\n\
         [[component]]\nname = \"supervisor\"\ntype = \"supervisor\"\n\
         activity = {{ type = \"periodic\", period_ms = 20 }}\nproperties = {{ above = 1.5 }}\n\
         requires = {{ limit = \"B/thr.limit\" }}\n"
    )
}

/// The supervisor's counter `name` in A's status.
fn counter(a: &Service, name: &str) -> Value {
    let s = a.ok(json!({"cmd": "status"}));
    s["components"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == json!("supervisor"))
        .unwrap()["counters"][name]
        .clone()
}

fn above(b: &Service) -> Option<String> {
    b.out(&["get", "thr", "property:above"]).ok()
}

#[test]
fn a_service_of_another_gateway_is_bound_lost_and_back() {
    let net = Pair::new("svc").unwrap_or_else(|e| panic!("{e}"));
    let dir = TempDir::new("remote-service");
    let endpoint = format!("tcp/{ADDR_B}:7451");
    let write = |name: &str, text: &str| {
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        p
    };
    let (a_file, b_file) = (
        write("a.toml", &a_config(&endpoint)),
        write("b.toml", &b_config(&endpoint)),
    );
    let check = testkit::service::check(BIN, &a_file);
    let summary = String::from_utf8_lossy(&check.stdout).to_string();
    assert!(check.status.success(), "{summary}");
    assert!(
        summary.contains("requires limit -> B/thr.limit"),
        "{summary}"
    );

    // A alone: bound, not ready.
    let a = Service::start_in(&net.exec_a(), BIN, "svc-a", &[&a_file], &[])
        .unwrap_or_else(|e| panic!("{e}"));
    let ls = a.out(&["ls", "supervisor"]).unwrap();
    assert!(ls.contains("limit  -> B/thr.limit (not ready)"), "{ls}");

    // B comes: the supervisor's limit reaches B's threshold through the binding.
    let b = Service::start_in(&net.exec_b(), BIN, "svc-b", &[&b_file], &[])
        .unwrap_or_else(|e| panic!("{e}"));
    wait_until("A's limit applied on B", || {
        above(&b).as_deref() == Some("1.5")
    });
    wait_until("the binding ready on A", || {
        a.out(&["ls", "supervisor"])
            .is_ok_and(|ls| ls.contains("limit  -> B/thr.limit (ready)"))
    });
    // (A's first look, before B was there, counted a loss already.)
    let (lost, back) = (
        counter(&a, "services_lost").as_u64().unwrap(),
        counter(&a, "services_back").as_u64().unwrap(),
    );

    // B's threshold stopped: lost on A, counted; B changes the limit meanwhile.
    b.out(&["lifecycle", "stop", "thr"]).unwrap();
    wait_until("the loss counted on A", || {
        counter(&a, "services_lost").as_u64() == Some(lost + 1)
    });
    b.out(&["set", "thr", "property:above", "7"]).unwrap();
    b.out(&["lifecycle", "start", "thr"]).unwrap();
    wait_until("the return counted on A", || {
        counter(&a, "services_back").as_u64() == Some(back + 1)
    });
    wait_until("A's limit applied on B again", || {
        above(&b).as_deref() == Some("1.5")
    });

    // The link cut: B is not heard from, the binding is lost; restored, it is back.
    net.link(false).unwrap();
    wait_until("the cut link a loss on A", || {
        counter(&a, "services_lost").as_u64() == Some(lost + 2)
    });
    let ls = a.out(&["ls", "supervisor"]).unwrap();
    assert!(ls.contains("limit  -> B/thr.limit (not ready)"), "{ls}");
    net.link(true).unwrap();
    wait_until("the restored link a return on A", || {
        counter(&a, "services_back").as_u64() == Some(back + 2)
    });

    let out = a.terminate();
    assert!(out.status.success(), "{}", out.log);
    assert!(
        out.log
            .contains("supervisor: B/thr.limit: the provider is Running"),
        "{}",
        out.log
    );
    drop(b);
}
