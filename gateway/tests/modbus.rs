//! A Modbus card in a deployment, against a Modbus TCP server: decoded values in IO ports,
//! port writes to registers, and safe values reaching the unit when the gateway stops.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use driver_modbus::testing::TestServer;
use hwgw::components::ComponentTypes;
use hwgw::config::Deployment;
use hwgw::deploy::Gateway;
use rtt::port::ConnPolicy;
use serde_json::json;
use std::time::{Duration, Instant};

fn wait_until(what: &str, mut f: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(10);
    while !f() {
        assert!(Instant::now() < deadline, "timed out: {what}");
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[test]
fn a_modbus_card_in_a_deployment() {
    let server = TestServer::start();
    {
        let mut m = server.memory().lock().unwrap();
        m.input[0] = (-215i16) as u16; // -21.5 degC
        m.discrete[2] = true;
    }
    let text = format!(
        r#"
[[card]]
name = "plc"
driver = "modbus"
sample_period_ms = 10
safe_analog_out = [1.5]
safe_digital_out_on = [1]

[card.names]
analog_in = ["temperature"]
analog_out = ["setpoint"]
digital_in = ["door"]
digital_out = ["pump", "fan"]

[card.modbus]
transport = {{ type = "tcp", address = "{}" }}
unit = 1
poll_ms = 10
timeout_ms = 200

[[card.modbus.point]]
table = "input_registers"
address = 0
type = "i16"
scale = 0.1
unit = "degC"
[[card.modbus.point]]
table = "holding_registers"
address = 10
scale = 0.1
unit = "bar"
[[card.modbus.point]]
table = "discrete_inputs"
address = 2
[[card.modbus.point]]
table = "coils"
address = 0
[[card.modbus.point]]
table = "coils"
address = 1
"#,
        server.addr()
    );
    let d = Deployment::parse(&text, "plc.toml").unwrap();
    let gw = Gateway::build(&d, "plc.toml", &text, &ComponentTypes::builtin()).unwrap();
    assert!(
        gw.summary().contains("card \"plc\" (modbus Tcp("),
        "{}",
        gw.summary()
    );
    gw.start().unwrap();
    let rt = gw.runtime();
    let temperature = rt.component("plc.ai").unwrap().port("temperature").unwrap();
    wait_until("the temperature arrives", || {
        temperature.last_value().unwrap() == Some(json!(-21.5))
    });
    let door = rt.component("plc.di").unwrap().port("door").unwrap();
    wait_until("the door arrives", || {
        door.last_value().unwrap() == Some(json!(true))
    });

    let mut setpoint = rt
        .component("plc.ao")
        .unwrap()
        .port("setpoint")
        .unwrap()
        .writer(ConnPolicy::data())
        .unwrap();
    setpoint.write(json!(4.2)).unwrap();
    let mut pump = rt
        .component("plc.do")
        .unwrap()
        .port("pump")
        .unwrap()
        .writer(ConnPolicy::data())
        .unwrap();
    pump.write(json!(true)).unwrap();
    wait_until("the unit's registers change", || {
        let m = server.memory().lock().unwrap();
        m.holding[10] == 42 && m.coils[0]
    });
    let diag = gw.card_diagnostics();
    assert!(
        diag[0]["polls"].as_u64().unwrap() > 0 && diag[0]["timeouts"] == 0,
        "{diag}"
    );

    // Stopping drives the outputs to their safe values *on the unit*: 1.5 bar, pump off,
    // fan on.
    let lines = gw.shutdown();
    assert_eq!(
        lines,
        vec!["card \"plc\" outputs at stop: analog [1.5], digital on [1]"]
    );
    let m = server.memory().lock().unwrap();
    assert_eq!(
        (m.holding[10], m.coils[0], m.coils[1]),
        (15, false, true),
        "the unit holds the safe values"
    );
}
