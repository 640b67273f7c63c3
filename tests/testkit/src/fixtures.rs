//! Shared test fixtures.

/// A Modbus register map over every table and the common types: analog inputs (input
/// register 0 i16 × 0.1, input registers 1–2 f32, holding registers 20–21 u32 read only),
/// analog outputs (holding register 10 u16, holding registers 11–12 i32), a digital input
/// (discrete input 3) and digital outputs (coils 5 and 6).
pub const MODBUS_MAP: &str = r#"
[[point]]
table = "input_registers"
address = 0
type = "i16"
scale = 0.1
[[point]]
table = "input_registers"
address = 1
type = "f32"
[[point]]
table = "holding_registers"
address = 10
[[point]]
table = "holding_registers"
address = 11
type = "i32"
[[point]]
table = "holding_registers"
address = 20
type = "u32"
read_only = true
[[point]]
table = "discrete_inputs"
address = 3
[[point]]
table = "coils"
address = 5
[[point]]
table = "coils"
address = 6
"#;

/// A sim card (`sim0`) for the northbound servers' tests: two constant inputs (1.25 V),
/// an input reading analog output 0 back, two outputs, four digital outputs looped back
/// to four inputs.
pub const SIM_CARD: &str = r#"
[[card]]
name = "sim0"
driver = "sim"
period_ms = 10
sample_period_ms = 20
safe_analog_out = [0.0, 0.0]

[card.sim]
seed = 1
digital_inputs = 4
digital_outputs = 4
digital_loopback = true

[[card.sim.analog_in]]
count = 2
range = { lowest = -10.0, highest = 10.0, unit = "V" }
waveform = { kind = "constant", value = 1.25 }

[[card.sim.analog_in]]
range = { lowest = -10.0, highest = 10.0, unit = "V" }
waveform = { kind = "loopback", analog_out = 0 }

[[card.sim.analog_out]]
count = 2
range = { lowest = -10.0, highest = 10.0, unit = "V" }
"#;
