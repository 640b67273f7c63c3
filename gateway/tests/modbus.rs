//! A Modbus card in a deployment, against a Modbus TCP server: decoded values in IO ports,
//! port writes to registers, and safe values reaching the unit when the gateway stops.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use driver_modbus::testing::TestServer;
use hwgw::config::Deployment;
use hwgw::deploy::Gateway;
use rtt::port::ConnPolicy;
use serde_json::json;
use testkit::mbpoll::Mbpoll;
use testkit::wait_until;

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
    let gw = Gateway::build(&d, "plc.toml", &text, &hwgw::types::Types::builtin()).unwrap();
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
    let diag = gw.card_status();
    let counters = &diag[0].status.counters;
    assert!(
        counters["polls"].as_u64().unwrap() > 0 && counters["timeouts"] == 0,
        "{diag:?}"
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

/// mbpoll (a libmodbus master) against `port`: table 0 coils, 1 discrete inputs, 3 input
/// registers, 4 holding registers; 0-based `address`; `write` values, if any.
fn mbpoll(port: u16, table: &str, address: u16, write: &[&str]) -> String {
    Mbpoll {
        port,
        table,
        address,
        count: None,
        write,
    }
    .run()
}

#[test]
fn mbpoll_reads_and_writes_the_gateways_registers() {
    let text = r#"
[[card]]
name = "sim0"
driver = "sim"
period_ms = 5
[card.sim]
digital_inputs = 4
digital_outputs = 4
digital_loopback = true
[[card.sim.analog_in]]
range = { lowest = -10.0, highest = 10.0, unit = "V" }
waveform = { kind = "loopback", analog_out = 0 }
[[card.sim.analog_out]]
range = { lowest = -10.0, highest = 10.0, unit = "V" }

[modbus_server]
listen = "127.0.0.1:0"
[[modbus_server.register]]       # the loopback input, in mV
table = "input_registers"
address = 0
device = "sim0"
interface = "analog_in"
channel = 0
type = "i16"
scale = 0.001
[[modbus_server.register]]       # the output, in mV
table = "holding_registers"
address = 10
device = "sim0"
interface = "analog_out"
channel = 0
type = "i16"
scale = 0.001
[[modbus_server.register]]
table = "coils"
address = 0
device = "sim0"
interface = "digital_out"
channel = 2
[[modbus_server.register]]
table = "discrete_inputs"
address = 0
device = "sim0"
interface = "digital_in"
channel = 2
"#;
    let d = Deployment::parse(text, "srv.toml").unwrap();
    let gw = Gateway::build(&d, "srv.toml", text, &hwgw::types::Types::builtin()).unwrap();
    gw.start().unwrap();
    let addr: std::net::SocketAddr = gw.server_address("modbus_server").unwrap().parse().unwrap();
    let port = addr.port();

    let w = mbpoll(port, "4", 10, &["2500"]);
    assert!(w.contains("Written 1 references"), "{w}");
    let ao = gw.runtime().registry().analog_out().lookup("sim0").unwrap();
    assert!(
        (ao.read_back(0).unwrap() - 2.5).abs() < 0.001,
        "the write reached the device"
    );
    wait_until("the loopback input follows", || {
        mbpoll(port, "3", 0, &[]).contains("[0]: \t2500")
    });
    let r = mbpoll(port, "4", 10, &[]);
    assert!(
        r.contains("[10]: \t2500"),
        "holding register reads back: {r}"
    );

    let w = mbpoll(port, "0", 0, &["1"]);
    assert!(w.contains("Written 1 references"), "{w}");
    wait_until("the coil loops back to the discrete input", || {
        mbpoll(port, "1", 0, &[]).contains("[0]: \t1")
    });

    let e = mbpoll(port, "3", 5, &[]);
    assert!(
        e.contains("Illegal data address"),
        "an unmapped address is an exception: {e}"
    );
    let e = mbpoll(port, "4", 10, &["20000"]);
    assert!(
        e.contains("Illegal data value"),
        "20 V is outside -10..10 V: {e}"
    );
    assert!(
        (ao.read_back(0).unwrap() - 2.5).abs() < 0.001,
        "a refused write changes nothing"
    );
    gw.shutdown();
}
