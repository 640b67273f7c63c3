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
