//! The `scan` component: at every step, analog inputs of any cards read straight from
//! their devices and analog outputs written from them; a channel that does not exist is a
//! configure error naming it.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use hwgw::config::Deployment;
use hwgw::deploy::Gateway;
use hwgw::types::Types;
use testkit::wait_until;

fn build(text: &str) -> Result<Gateway, String> {
    let d = Deployment::parse(text, "scan.toml").unwrap();
    Gateway::build(&d, "scan.toml", text, &Types::builtin()).map_err(|p| {
        p.iter()
            .map(|p| p.to_string())
            .collect::<Vec<_>>()
            .join("\n")
    })
}

fn deployment(scan: &str) -> String {
    format!(
        r#"
[[card]]
name = "a"
driver = "sim"
period_ms = 5
[card.sim]
analog_in = [{{ range = {{ lowest = 0.0, highest = 65535.0, unit = "V" }}, waveform = {{ kind = "constant", value = 2.0 }} }}, {{ range = {{ lowest = 0.0, highest = 65535.0, unit = "V" }}, waveform = {{ kind = "constant", value = 4.0 }} }}]
[[card]]
name = "b"
driver = "sim"
period_ms = 5
[card.sim]
analog_in = [{{ range = {{ lowest = 0.0, highest = 65535.0, unit = "V" }}, waveform = {{ kind = "constant", value = 9.0 }} }}]
analog_out = [{{ range = {{ lowest = 0.0, highest = 65535.0, unit = "V" }} }}, {{ range = {{ lowest = 0.0, highest = 65535.0, unit = "V" }} }}]

[[component]]
name = "loop"
type = "scan"
activity = {{ type = "periodic", period_ms = 1 }}
properties = {{ {scan} }}
"#
    )
}

#[test]
fn each_step_reads_the_inputs_and_writes_the_outputs() {
    let gw = build(&deployment(
        r#"inputs = ["a:0", "a:1", "b:0"], outputs = ["b:1", "b:0"], gain = 2.0, offset = 1.0"#,
    ))
    .unwrap();
    gw.start().unwrap();
    let b = gw.runtime().registry().analog_out().lookup("b").unwrap();
    // (2 + 4 + 9) / 3 = 5; 2 × 5 + 1 = 11 on both outputs (one volt a step of the raw
    // range: exact).
    wait_until("the scan's writes", || {
        b.read_back(0).ok() == Some(11.0) && b.read_back(1).ok() == Some(11.0)
    });
    let t = gw.runtime().component("loop").unwrap();
    let out = t.port("out").unwrap().last_value().unwrap();
    assert_eq!(out, Some(serde_json::json!(11.0)));
    assert_eq!(t.state(), rtt::TaskState::Running);
}

#[test]
fn channels_that_do_not_exist_are_configure_errors_that_name_them() {
    for (scan, want) in [
        (r#"inputs = ["a:7"]"#, r#"input "a:7": "a" has 2 channels"#),
        (
            r#"outputs = ["b:2"]"#,
            r#"output "b:2": "b" has 2 channels"#,
        ),
        (
            r#"inputs = ["a"]"#,
            r#"input "a": expected "device:channel" with a channel number ("sim0:0")"#,
        ),
        (r#"inputs = ["nosuch:0"]"#, "nosuch"),
        (
            r#"gain = 2.0"#,
            "properties inputs and outputs are both empty: name the channels to scan",
        ),
    ] {
        let e = build(&deployment(scan))
            .err()
            .unwrap_or_else(|| panic!("{scan}: built"));
        assert!(e.contains(want), "{scan}: {e}");
        assert!(e.contains("loop"), "{scan}: {e}");
    }
}
