//! The reporter records chosen ports of other components to CSV.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use hwgw::config::Deployment;
use hwgw::deploy::Gateway;

fn deployment(file: &std::path::Path, extra: &str) -> String {
    format!(
        r#"
[[card]]
name = "sim0"
driver = "sim"
period_ms = 2
[card.sim]
digital_inputs = 2
digital_outputs = 2
digital_loopback = true
[[card.sim.analog_in]]
range = {{ lowest = -10.0, highest = 10.0, unit = "V" }}
waveform = {{ kind = "ramp", from = -10.0, to = 10.0, period = 1.0 }}

[[component]]
name = "rec"
type = "reporter"
activity = {{ type = "periodic", period_ms = 10 }}
properties = {{ ports = ["sim0.ai.ch0", "sim0.di.bit1"], file = "{}"{extra} }}
"#,
        file.display()
    )
}

#[test]
fn records_ports_to_csv() {
    let dir = std::env::temp_dir().join(format!("hwgw-reporter-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let csv = dir.join("rec.csv");
    let text = deployment(&csv, "");
    let d = Deployment::parse(&text, "r.toml").unwrap();
    let gw = Gateway::build(&d, "r.toml", &text, &hwgw::types::Types::builtin()).unwrap();
    gw.start().unwrap();
    let rec = gw.runtime().component("rec").unwrap();
    testkit::wait_until("a dozen reporter steps", || rec.stats().steps >= 12);
    gw.shutdown();
    let content = std::fs::read_to_string(&csv).unwrap();
    let mut lines = content.lines();
    assert_eq!(lines.next(), Some("time_s,sim0.ai.ch0,sim0.di.bit1"));
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert!(rows.len() >= 10, "{} rows after 12 steps", rows.len());
    let mut times = Vec::new();
    let mut ramp = Vec::new();
    // A port that has not delivered yet leaves its cell empty; after that, every row is full.
    let full: Vec<&Vec<&str>> = rows
        .iter()
        .filter(|r| r.iter().all(|c| !c.is_empty()))
        .collect();
    assert!(
        full.len() + 3 >= rows.len(),
        "only the first rows may have gaps: {rows:?}"
    );
    for r in full {
        assert_eq!(r.len(), 3, "{r:?}");
        times.push(r[0].parse::<f64>().unwrap());
        ramp.push(r[1].parse::<f64>().unwrap());
        assert_eq!(r[2], "false");
    }
    assert!(
        times.windows(2).all(|w| w[1] > w[0]),
        "time stamps increase"
    );
    assert!(ramp.iter().all(|v| (-10.0..=10.0).contains(v)));
    assert!(ramp.windows(2).any(|w| w[1] != w[0]), "the ramp moves");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_reporter_naming_a_missing_port_fails_to_configure() {
    let dir = std::env::temp_dir();
    let text = deployment(&dir.join("never.csv"), "").replace("sim0.di.bit1", "sim0.di.bit9");
    let d = Deployment::parse(&text, "r.toml").unwrap();
    let problems = Gateway::build(&d, "r.toml", &text, &hwgw::types::Types::builtin())
        .err()
        .unwrap();
    assert_eq!(problems.len(), 1);
    assert_eq!(
        problems[0].to_string(),
        "r.toml:14:1: component[0]: component \"rec\": configure_hook failed: \"sim0.di\" has no port \"bit9\"; it has: bit0, bit1"
    );
}
