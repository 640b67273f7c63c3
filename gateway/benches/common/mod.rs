//! What the real-time benches share: a Modbus TCP unit on loopback (a second hwgw serving
//! a simulated card) and the card of a gateway polling it.

/// The Modbus unit: a simulated card served on loopback (`[modbus_server]`), a sine around
/// 230 V on input register 0 and a setpoint in holding register 0.
pub const UNIT: &str = r#"
[[card]]
name = "unit"
driver = "sim"
period_ms = 10
[card.sim]
analog_in = [{ range = { lowest = 0.0, highest = 400.0, unit = "V" }, waveform = { kind = "sine", amplitude = 10.0, frequency = 1.0, offset = 230.0 } }]
analog_out = [{ range = { lowest = 0.0, highest = 400.0, unit = "V" } }]

[modbus_server]
listen = "127.0.0.1:0"

[[modbus_server.register]]
table = "input_registers"
address = 0
device = "unit"
interface = "analog_in"
channel = 0
scale = 0.1

[[modbus_server.register]]
table = "holding_registers"
address = 0
device = "unit"
interface = "analog_out"
channel = 0
scale = 0.1
"#;

/// Card `meter` polling [`UNIT`] at `port` every `poll_ms` on a SCHED_FIFO line at
/// `priority`: analog input `voltage`, analog output `setpoint`.
pub fn meter(port: u16, poll_ms: u32, priority: i32) -> String {
    format!(
        r#"
[[card]]
name = "meter"
driver = "modbus"
sample_period_ms = {poll_ms}
thread = {{ policy = "fifo", priority = {priority} }}
safe_analog_out = [0.0]
[card.names]
analog_in = ["voltage"]
analog_out = ["setpoint"]
[card.modbus]
transport = {{ type = "tcp", address = "127.0.0.1:{port}" }}
unit = 1
poll_ms = {poll_ms}
timeout_ms = 300
[[card.modbus.point]]
table = "input_registers"
address = 0
type = "u16"
scale = 0.1
[[card.modbus.point]]
table = "holding_registers"
address = 0
type = "u16"
scale = 0.1
"#
    )
}
