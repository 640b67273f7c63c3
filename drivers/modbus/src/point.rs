//! A point of a register map checked on its own and against the points before it: which
//! fields go together, the overlaps that cannot be meant, the interface it serves and the
//! register value one raw count stands for (the [`map`](crate::map)'s building blocks).

use crate::codec::{ByteOrder, ValueType, WordOrder};
use crate::plan::Table;
use device_interface::RawRange;
use serde::Deserialize;

/// One point of a register map, as configured.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PointConfig {
    /// The table.
    pub table: Table,
    /// The address, 0-based as on the wire (register 40001 of the old notation is
    /// holding register 0).
    pub address: u16,
    /// Value type of a register point (default u16).
    #[serde(default, rename = "type")]
    pub ty: ValueType,
    /// Word order of a multi-register value.
    #[serde(default)]
    pub words: WordOrder,
    /// Byte order inside each register.
    #[serde(default)]
    pub bytes: ByteOrder,
    /// Physical value = register value * scale + offset.
    #[serde(default = "one")]
    pub scale: f64,
    /// Added after the scale.
    #[serde(default)]
    pub offset: f64,
    /// Unit of the physical value.
    #[serde(default)]
    pub unit: String,
    /// Make this point one bit (0..=15) of a 16-bit register: a DigitalIn.
    #[serde(default)]
    pub bit: Option<u8>,
    /// A holding register read as an input instead of written as an output.
    #[serde(default)]
    pub read_only: bool,
    /// For f32/f64 points: the register-value step one raw count stands for (the raw grid
    /// and the writable range; reads are exact).
    #[serde(default)]
    pub resolution: Option<f64>,
    /// Make this counter register an Encoder: counts per turn and direction. Turns are
    /// counted on the counter's wrap at its register width.
    #[serde(default)]
    pub encoder: Option<EncoderPoint>,
}

/// A counter register read as an encoder.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderPoint {
    /// Counts per turn (negative: positions run from resolution+1 to 0).
    pub resolution: i64,
    /// True when counting up is the positive direction (default true).
    #[serde(default = "yes")]
    pub upcounting: bool,
}

fn yes() -> bool {
    true
}

fn one() -> f64 {
    1.0
}

/// The device interface a point serves.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Role {
    /// An AnalogIn channel.
    AnalogIn,
    /// An AnalogOut channel.
    AnalogOut,
    /// A DigitalIn bit.
    DigitalIn,
    /// A DigitalOut bit.
    DigitalOut,
    /// An Encoder (one per point).
    Encoder,
}

/// Checks point `i` of `configs`; its role and its raw step, or the key at fault and why.
pub(crate) fn check(
    configs: &[PointConfig],
    i: usize,
) -> Result<(Role, f64), (&'static str, String)> {
    let c = &configs[i];
    let bad = |key: &'static str, problem: String| (key, problem);
    let bit_table = c.table.is_bits();
    if bit_table && (c.ty != ValueType::U16 || c.bit.is_some() || c.scale != 1.0 || c.offset != 0.0)
    {
        return Err(bad(
            "table",
            format!(
                "{} hold single bits: no type, bit, scale or offset",
                c.table
            ),
        ));
    }
    if let Some(b) = c.bit {
        if b > 15 {
            return Err(bad("bit", format!("{b}: a register has bits 0..=15")));
        }
        if c.ty.registers() != 1 {
            return Err(bad(
                "bit",
                format!("a bit field needs a 16-bit type, not {}", c.ty),
            ));
        }
    }
    // Every point, read or only written, must fit the 65536 addresses of its table.
    let width = if bit_table {
        1
    } else {
        c.ty.registers() as u32
    };
    if u32::from(c.address) + width > 65_536 {
        return Err(bad(
            "address",
            format!(
                "{}: a {} point of {width} {} runs past address 65535",
                c.address,
                c.ty,
                if bit_table { "bit" } else { "registers" }
            ),
        ));
    }
    if c.read_only && matches!(c.table, Table::InputRegisters | Table::DiscreteInputs) {
        return Err(bad(
            "read_only",
            format!(
                "{} are read-only already; read_only makes a coil or a holding register an input",
                c.table.name()
            ),
        ));
    }
    overlap(configs, i, bit_table).map_err(|m| bad("address", m))?;
    if let Some(e) = c.encoder {
        if c.table.is_bits() || c.bit.is_some() || c.ty.is_float() {
            return Err(bad(
                "encoder",
                "an encoder is an integer counter register: no bit table, bit field or float"
                    .into(),
            ));
        }
        if e.resolution == 0 || e.resolution == i64::MIN {
            return Err(bad(
                "encoder",
                format!(
                    "resolution {}: expected counts per turn, not 0",
                    e.resolution
                ),
            ));
        }
    }
    let role = match (c.table, c.bit, c.read_only) {
        _ if c.encoder.is_some() => Role::Encoder,
        (Table::Coils, _, true) => Role::DigitalIn,
        (Table::Coils, _, false) => Role::DigitalOut,
        (Table::DiscreteInputs, _, _) | (_, Some(_), _) => Role::DigitalIn,
        (Table::InputRegisters, None, _) | (Table::HoldingRegisters, None, true) => Role::AnalogIn,
        (Table::HoldingRegisters, None, false) => Role::AnalogOut,
    };
    let step = match (c.resolution, c.ty.is_float()) {
        (None, false) => 1.0,
        (None, true) => default_float_step(c.ty),
        (Some(r), true) if r.is_finite() && r > 0.0 => r,
        (Some(r), true) => {
            return Err(bad("resolution", format!("{r}: expected a step above 0")));
        }
        (Some(_), false) => {
            return Err(bad(
                "resolution",
                format!(
                    "only float points have a resolution; {} counts whole units",
                    c.ty
                ),
            ));
        }
    };
    Ok((role, step))
}

/// Refuses point `i` where it shares an address with an earlier point of the same table
/// in a way that cannot be meant: two outputs on one coil, values that overlap in part
/// (a u32 at 10 and a u16 at 11), two outputs on one register, the same bit of a register
/// twice, or a bit of a register an output value covers (writing the value would change
/// the bit). Several read-only views of one address may share it (an output's value read
/// back as an input, a counter as an encoder and as a value), as may bits of one register.
fn overlap(configs: &[PointConfig], i: usize, bit_table: bool) -> Result<(), String> {
    let c = &configs[i];
    let span = |p: &PointConfig| {
        let w = if bit_table {
            1
        } else {
            p.ty.registers() as u32
        };
        (u32::from(p.address), u32::from(p.address) + w)
    };
    let writable = |p: &PointConfig| {
        matches!(p.table, Table::HoldingRegisters | Table::Coils)
            && !p.read_only
            && p.bit.is_none()
            && p.encoder.is_none()
    };
    let (s, e) = span(c);
    for (j, o) in configs[..i].iter().enumerate() {
        let (os, oe) = span(o);
        if o.table != c.table || s >= oe || os >= e {
            continue;
        }
        let clash = match (c.bit, o.bit) {
            _ if bit_table => writable(c) || writable(o),
            (Some(a), Some(b)) => a == b,
            (Some(_), None) => writable(o),
            (None, Some(_)) => writable(c),
            (None, None) => (s, e) != (os, oe) || (writable(c) && writable(o)),
        };
        if clash {
            return Err(format!(
                "{} {}: point[{j}] is there already ({} {}{})",
                c.table.name(),
                c.address,
                o.table.name(),
                o.address,
                o.bit.map(|b| format!(", bit {b}")).unwrap_or_default()
            ));
        }
    }
    Ok(())
}

/// The step of a float point without `resolution`: its raw range (±2^23 or ±2^52 steps)
/// then spans ±2^127 register units for `f32` (f32::MAX is just under 2^128) and ±2^1000
/// for `f64` (far enough below f64::MAX to stay finite when scaled).
pub fn default_float_step(ty: ValueType) -> f64 {
    match ty {
        ValueType::F64 => 2f64.powi(1000 - 52),
        _ => 2f64.powi(127 - 23),
    }
}

pub(crate) fn raw_range(ty: ValueType) -> RawRange {
    // The bounds below are all valid ranges; RawRange::new only refuses min >= max.
    let r = |min: i64, max: i64| RawRange { min, max };
    match ty {
        ValueType::U16 => r(0, i64::from(u16::MAX)),
        ValueType::I16 => r(i64::from(i16::MIN), i64::from(i16::MAX)),
        ValueType::U32 => r(0, i64::from(u32::MAX)),
        ValueType::I32 => r(i64::from(i32::MIN), i64::from(i32::MAX)),
        ValueType::U64 => r(0, i64::MAX),
        ValueType::I64 => r(i64::MIN, i64::MAX),
        // Steps the type represents exactly: every multiple of the step up to there
        // survives the round trip through the register (half an ulp < half a step).
        ValueType::F32 => r(-(1 << 23), 1 << 23),
        ValueType::F64 => r(-(1 << 52), 1 << 52),
    }
}
