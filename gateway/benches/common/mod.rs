//! What the real-time benches share: a Modbus TCP unit on loopback (a second hwgw serving
//! a simulated card), the card of a gateway polling it, and a 1 kHz `scan` loop over that
//! card and a simulated one.

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

/// A `scan` component `loop` every 1 ms at SCHED_FIFO `priority`, reading analog input 0
/// of a simulated card `sim0` and of [`meter`] (polling the unit at `port` every 1 ms at
/// SCHED_FIFO `priority - 10`) and writing analog output 0 of both at every step.
pub fn scan_loop(port: u16, priority: i32) -> String {
    format!(
        r#"
cpu_dma_latency_us = 0

[[card]]
name = "sim0"
driver = "sim"
period_ms = 10
safe_analog_out = [0.0]
[card.sim]
analog_in = [{{ range = {{ lowest = -10.0, highest = 10.0, unit = "V" }}, waveform = {{ kind = "sine", amplitude = 5.0, frequency = 0.5 }} }}]
analog_out = [{{ range = {{ lowest = -10.0, highest = 10.0, unit = "V" }} }}]
{meter}
[[component]]
name = "loop"
type = "scan"
activity = {{ type = "periodic", period_ms = 1, policy = "fifo", priority = {priority} }}
properties = {{ inputs = ["sim0:0", "meter:0"], outputs = ["meter:0", "sim0:0"], gain = 0.05 }}
"#,
        meter = meter(port, 1, priority - 10)
    )
}
