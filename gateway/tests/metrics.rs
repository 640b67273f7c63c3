//! `[server.metrics]` with the real binary, read by tools we did not write: `promtool
//! check metrics` (Debian's `prometheus`) passes the exposition of the demo and of a
//! Modbus deployment against pymodbus; a real Prometheus server scrapes the gateway and
//! answers, over its HTTP API, `hwgw_device_up` and a step-time histogram quantile equal
//! to what `hwgw status --json` says; `/health` is 503 with the reason while a component
//! that should run is stopped, 200 once it runs again.
#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use serde_json::{Value, json};
use std::net::SocketAddr;
use testkit::http::{get, request};
use testkit::prometheus::{Prometheus, check_metrics};
use testkit::pymodbus::PyModbus;
use testkit::{Service, wait_until};

const HWGW: &str = env!("CARGO_BIN_EXE_hwgw");
const DEMO: &str = include_str!("../../config/demo.toml");

/// Both expositions of `addr`: Prometheus' text format passes promtool; OpenMetrics is
/// served to who asks for it, and ends as the format says.
fn check_both(addr: SocketAddr) -> String {
    let plain = get(addr, "/metrics");
    assert_eq!(plain.status, 200, "{}", plain.text());
    assert_eq!(
        plain.header("content-type"),
        Some("text/plain; version=0.0.4; charset=utf-8")
    );
    check_metrics(&plain.text()).unwrap_or_else(|e| panic!("{e}\n{}", plain.text()));
    let accept = [("accept", "application/openmetrics-text;version=1.0.0")];
    let om = request(addr, "GET", "/metrics", &accept, b"").unwrap();
    assert_eq!(om.status, 200);
    assert!(
        om.header("content-type")
            .unwrap()
            .starts_with("application/openmetrics-text; version=1.0.0"),
        "{:?}",
        om.headers
    );
    assert!(om.text().ends_with("# EOF\n"));
    plain.text()
}

/// The upper bound of bucket `i` of an activity histogram (`2^i..2^(i+1)` ns), s, as the
/// exposition writes its `le`: buckets below 2^14 ns fold into the first, above 2^27 ns
/// into `+Inf`.
fn quantile_of(histogram: &[u64], q: f64) -> f64 {
    // The exposition's buckets: (upper bound, count in it), as Prometheus reads them.
    let at = |i: usize| histogram.get(i).copied().unwrap_or(0);
    let bound = |k: usize| (1u64 << k) as f64 * 1e-9;
    let mut buckets = vec![(bound(14), (0..14).map(at).sum::<u64>())];
    buckets.extend((15..=27).map(|k| (bound(k), at(k - 1))));
    buckets.push((f64::INFINITY, histogram.iter().skip(27).sum()));
    // Prometheus' histogram_quantile: the rank's bucket, linearly within it.
    let total: u64 = buckets.iter().map(|b| b.1).sum();
    let rank = q * total as f64;
    let mut below = 0u64;
    let mut lower = 0.0;
    for (i, &(upper, n)) in buckets.iter().enumerate() {
        if (below + n) as f64 >= rank {
            if upper.is_infinite() {
                return buckets[i - 1].0;
            }
            if i == 0 && upper <= 0.0 {
                return upper;
            }
            return lower + (upper - lower) * ((rank - below as f64) / n as f64);
        }
        below += n;
        lower = upper;
    }
    f64::NAN
}

fn component(status: &Value, name: &str) -> Value {
    status["components"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == name)
        .unwrap_or_else(|| panic!("no component {name}"))
        .clone()
}

#[test]
fn prometheus_scrapes_the_demo_and_reads_what_status_says() {
    let text =
        format!("{DEMO}\n[server.metrics]\nlisten = \"127.0.0.1:0\"\nports = [\"sim0.ai.ch3\"]\n");
    let svc = Service::run_text(HWGW, "metrics-demo", &text).unwrap();
    let addr = svc.server_address("server.metrics");
    let exposition = check_both(addr);
    assert!(exposition.contains("hwgw_port_value{component=\"sim0.ai\",port=\"ch3\"}"));
    assert_eq!(get(addr, "/health").status, 200);

    let prom = Prometheus::start(addr);
    wait_until("Prometheus scraped hwgw", || {
        prom.query("up{job=\"hwgw\"}").first().map(|s| s.1) == Some(1.0)
    });
    let status = svc.ok(json!({"cmd": "status"}));
    for d in status["devices"].as_array().unwrap() {
        let q = format!(
            "hwgw_device_up{{device={},interface={}}}",
            d["name"], d["interface"]
        );
        let got = prom.query(&q);
        assert_eq!(got.len(), 1, "{q}: {got:?}");
        let want = if d["status"] == "online" { 1.0 } else { 0.0 };
        assert_eq!(got[0].1, want, "{q} against {d}");
    }

    // A component that should run, stopped: unhealthy, and its histogram stands still.
    svc.ok(json!({"cmd": "stop", "component": "blink"}));
    let h = get(addr, "/health");
    assert_eq!(h.status, 503, "{}", h.text());
    let reasons = h.json()["reasons"].clone();
    assert!(
        reasons
            .as_array()
            .unwrap()
            .iter()
            .any(|r| r == "blink is Stopped"),
        "{reasons}"
    );
    wait_until("Prometheus saw blink stopped", || {
        let q = "hwgw_component_state{component=\"blink\",state=\"stopped\"}";
        prom.query(q).first().map(|s| s.1) == Some(1.0)
    });
    let blink = component(&svc.ok(json!({"cmd": "status"})), "blink");
    let histogram: Vec<u64> = serde_json::from_value(blink["step_histogram"].clone()).unwrap();
    assert!(histogram.iter().sum::<u64>() > 0, "{blink}");
    let want = quantile_of(&histogram, 0.99);
    let q = "histogram_quantile(0.99, hwgw_component_step_seconds_bucket{component=\"blink\"})";
    let got = prom.query(q);
    assert_eq!(got.len(), 1, "{q}: {got:?}");
    assert!(
        (got[0].1 - want).abs() <= want.abs() * 1e-9,
        "{q}: Prometheus {} against {want} from status {histogram:?}",
        got[0].1
    );
    let steps = prom.query("hwgw_component_steps_total{component=\"blink\"}");
    assert_eq!(steps.first().map(|s| s.1), blink["steps"].as_f64());
    // The watchdog's measure, in seconds, to the nanosecond status gives.
    let unhealthy = prom.query("hwgw_component_unhealthy_seconds_total{component=\"blink\"}");
    let want = blink["unhealthy_ns"].as_u64().unwrap() as f64 * 1e-9;
    assert_eq!(unhealthy.first().map(|s| s.1), Some(want), "{blink}");
    let spells = prom.query("hwgw_component_unhealthy_spells_total{component=\"blink\"}");
    assert_eq!(
        spells.first().map(|s| s.1),
        blink["unhealthy_spells"].as_f64()
    );
    // Count and sum, independent of how the buckets are laid out.
    let count = prom.query("hwgw_component_step_seconds_count{component=\"blink\"}");
    assert_eq!(count[0].1, histogram.iter().sum::<u64>() as f64);
    let sum = prom.query("hwgw_component_step_seconds_sum{component=\"blink\"}");
    let want_sum = blink["step_total_ns"].as_u64().unwrap() as f64 * 1e-9;
    assert!(
        (sum[0].1 - want_sum).abs() <= want_sum * 1e-12,
        "{} against {want_sum}",
        sum[0].1
    );

    svc.ok(json!({"cmd": "start", "component": "blink"}));
    wait_until("healthy again", || get(addr, "/health").status == 200);
}

#[test]
fn a_modbus_deployment_passes_promtool() {
    let modbus = PyModbus::start("tcp");
    let text = format!(
        r#"
[[card]]
name = "plc"
driver = "modbus"
sample_period_ms = 10

[card.modbus]
transport = {{ type = "tcp", address = "{}" }}
unit = 1
poll_ms = 20
timeout_ms = 500

[[card.modbus.point]]
table = "input_registers"
address = 0
type = "i16"
scale = 0.1

[[card.modbus.point]]
table = "holding_registers"
address = 10

[server.metrics]
listen = "127.0.0.1:0"
"#,
        modbus.addr
    );
    let svc = Service::run_text(HWGW, "metrics-modbus", &text).unwrap();
    let addr = svc.server_address("server.metrics");
    wait_until("the Modbus card polled", || {
        let s = svc.ok(json!({"cmd": "status"}));
        s["cards"][0]["counters"]["polls"].as_u64().unwrap_or(0) > 0
    });
    let exposition = check_both(addr);
    let polls = exposition.lines().find(|l| {
        l.starts_with("hwgw_card_status{card=\"plc\",driver=\"modbus\",field=\"polls\"}")
    });
    assert!(polls.is_some(), "{exposition}");
}
