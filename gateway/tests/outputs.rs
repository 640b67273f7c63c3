//! The output policy, in a gateway built in this process: safe values, `keep`, the
//! default that never writes an output hwgw was not asked to write, and the output
//! watchdog (silence, a failed writer) — on the simulated card and on a Modbus unit.

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use driver_modbus::testing::TestServer;
use hwgw::config::Deployment;
use hwgw::deploy::Gateway;
use hwgw::types::Types;
use rtt::port::OutputPort;
use rtt::property::Property;
use rtt::{Component, Context, HookError, HookResult, InterfaceBuilder};
use testkit::wait_until;

fn gateway(text: &str, types: &Types) -> Gateway {
    let d = Deployment::parse(text, "o.toml").unwrap();
    Gateway::build(&d, "o.toml", text, types).unwrap_or_else(|p| {
        panic!(
            "{}",
            p.iter()
                .map(|p| p.to_string())
                .collect::<Vec<_>>()
                .join("\n")
        )
    })
}

const SIM: &str = r#"
[[card]]
name = "s"
driver = "sim"
period_ms = 5
[card.outputs]
safe = { valve = 100.0, spare = "keep", pump = true, lamp = "keep" }
watchdog_ms = 100
[card.names]
analog_out = ["valve", "spare", "touched", "untouched"]
digital_out = ["pump", "lamp", "fan", "idle"]
[card.sim]
digital_outputs = 4
[[card.sim.analog_out]]
count = 4
range = { lowest = 0.0, highest = 65535.0 }
initial = 10.0
"#;

#[test]
fn each_policy_on_the_simulated_card() {
    let gw = gateway(SIM, &Types::builtin());
    gw.start().unwrap();
    let reg = gw.runtime().registry();
    let (ao, dout) = (
        reg.analog_out().lookup("s").unwrap(),
        reg.digital_out().lookup("s").unwrap(),
    );
    // The watchdog: valve written, then silent for 100 ms, goes to its safe value.
    ao.write(0, 5.0).unwrap();
    wait_until("valve to its safe value by the watchdog", || {
        ao.read_back(0).unwrap() == 100.0
    });
    // A new write takes again, and rearms the watchdog.
    ao.write(0, 5.0).unwrap();
    assert_eq!(ao.read_back(0).unwrap(), 5.0);
    ao.write(1, 6.0).unwrap();
    ao.write(2, 7.0).unwrap();
    dout.set_bit(1, true).unwrap();
    dout.set_bit(2, true).unwrap();
    let status = gw.card_status();
    assert_eq!(status[0].outputs.written, 5, "{status:?}");
    assert!(status[0].outputs.watchdog_trips >= 1, "{status:?}");
    let lines = gw.shutdown();
    // valve: safe; spare: kept; touched: back to its value at start; untouched: as it was.
    // pump: safe on; lamp: kept on; fan: back to off; idle: untouched.
    assert_eq!(
        lines,
        vec!["card \"s\" outputs at stop: analog [100, 6, 10, 10], digital on [0, 1]"]
    );
    // Once the stop began, every write is refused.
    assert_eq!(
        ao.write(0, 1.0).unwrap_err().to_string(),
        "output held: the gateway is stopping: outputs go to their safe values"
    );
}

/// Writes `value` on `out` each step; `fail = true` makes its update fail (Exception).
struct Faulty {
    out: OutputPort<f64>,
    value: Property<f64>,
    fail: Property<bool>,
}

impl Faulty {
    fn new(
        iface: &mut InterfaceBuilder<Faulty>,
    ) -> Result<Faulty, rtt::component::IntrospectError> {
        Ok(Faulty {
            out: iface.output("out", "the value, every step")?,
            value: iface.properties().add("value", 0.0, "what to write")?,
            fail: iface
                .properties()
                .add("fail", false, "fail the next update")?,
        })
    }
}

impl Component for Faulty {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        if self.fail.get() {
            return Err(HookError::new("failing on purpose"));
        }
        self.out.write(&self.value.get());
        Ok(())
    }
}

#[test]
fn a_failed_writer_sends_its_output_to_the_safe_value() {
    let mut types = Types::builtin();
    types.components.register("faulty", |rt, name, spec| {
        rt.add(name, spec, rtt::InitialState::Stopped, Faulty::new)
    });
    let text = format!(
        "{}\n[[component]]\nname = \"w\"\ntype = \"faulty\"\nactivity = {{ type = \"periodic\", period_ms = 5 }}\nproperties = {{ value = 5.0 }}\n[[connection]]\nfrom = \"w.out\"\nto = \"s.ao.valve\"\n",
        SIM.replace("watchdog_ms = 100\n", "")
    );
    let gw = gateway(&text, &types);
    gw.start().unwrap();
    let ao = gw.runtime().registry().analog_out().lookup("s").unwrap();
    wait_until("the writer's value on the valve", || {
        ao.read_back(0).unwrap() == 5.0
    });
    let w = gw.runtime().component("w").unwrap();
    w.properties()
        .set_value("fail", serde_json::json!(true))
        .unwrap();
    wait_until("the writer in Exception", || {
        w.state() == rtt::TaskState::Exception
    });
    wait_until("the valve at its safe value", || {
        ao.read_back(0).unwrap() == 100.0
    });
    gw.shutdown();
}

/// A Modbus unit holding setpoint 3.0 (30), limit 7, spare 777, fan on, horn on; hwgw
/// (`read_back` as given) writes setpoint 4.2, limit 33 and the fan off, then stops.
/// Returns (setpoint, limit, spare, fan, horn) on the unit afterwards, and the log of the
/// stop.
fn modbus_stop(read_back: bool) -> ((u16, u16, u16, bool, bool), Vec<String>) {
    let server = TestServer::start();
    {
        let mut m = server.memory().lock().unwrap();
        (m.holding[10], m.holding[11], m.holding[12]) = (30, 7, 777);
        (m.coils[0], m.coils[1]) = (true, true);
    }
    let text = format!(
        r#"
[[card]]
name = "plc"
driver = "modbus"
[card.outputs]
safe = {{ setpoint = 1.5, limit = "keep" }}
[card.names]
analog_out = ["setpoint", "limit", "spare"]
digital_out = ["fan", "horn"]
[card.modbus]
transport = {{ type = "tcp", address = "{}" }}
poll_ms = 10
timeout_ms = 200
read_back = {read_back}
[[card.modbus.point]]
table = "holding_registers"
address = 10
scale = 0.1
[[card.modbus.point]]
table = "holding_registers"
address = 11
[[card.modbus.point]]
table = "holding_registers"
address = 12
[[card.modbus.point]]
table = "coils"
address = 0
[[card.modbus.point]]
table = "coils"
address = 1
"#,
        server.addr()
    );
    let gw = gateway(&text, &Types::builtin());
    let log = testkit::LogCapture::start();
    gw.start().unwrap();
    let reg = gw.runtime().registry();
    let (ao, dout) = (
        reg.analog_out().lookup("plc").unwrap(),
        reg.digital_out().lookup("plc").unwrap(),
    );
    wait_until("the unit online", || {
        ao.health().status == device_interface::Status::Online
    });
    ao.write(0, 4.2).unwrap();
    ao.write(1, 33.0).unwrap();
    dout.set_bit(0, false).unwrap();
    wait_until("the writes on the unit", || {
        let m = server.memory().lock().unwrap();
        (m.holding[10], m.holding[11], m.coils[0]) == (42, 33, false)
    });
    gw.shutdown();
    let m = server.memory().lock().unwrap();
    let unit = (
        m.holding[10],
        m.holding[11],
        m.holding[12],
        m.coils[0],
        m.coils[1],
    );
    (unit, log.lines())
}

#[test]
fn a_stop_writes_to_a_modbus_unit_only_what_the_policy_asks() {
    // Without read-back hwgw cannot know the fan was on before it wrote it: it leaves it
    // as written and says so, rather than "restore" a value the unit never had.
    let (unit, log) = modbus_stop(false);
    assert_eq!(
        unit,
        (15, 33, 777, false, true),
        "setpoint safe, limit kept, spare and horn never written, fan left as written"
    );
    assert!(
        log.iter().any(|l| l.contains(
            "card \"plc\": output \"fan\" left as hwgw last wrote it: its value before that is unknown"
        )),
        "{log:#?}"
    );
    // With read-back the outputs are polled: the fan goes back on, as hwgw found it.
    let (unit, _) = modbus_stop(true);
    assert_eq!(
        unit,
        (15, 33, 777, true, true),
        "setpoint safe, limit kept, spare and horn never written, fan back on"
    );
}
