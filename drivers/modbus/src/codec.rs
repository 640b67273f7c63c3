//! Values in Modbus registers: how 16-bit registers become numbers and back.
//!
//! Modbus only defines 16-bit registers, sent high byte first. Wider values span
//! consecutive registers, and devices disagree on the order: [`WordOrder`] says which
//! register holds the most significant word, [`ByteOrder`] whether the two bytes inside each
//! register are swapped. The four classic layouts of a 32-bit value `0xAABBCCDD`:
//!
//! | word order | byte order | registers |
//! |---|---|---|
//! | high first | normal | `AABB CCDD` ("ABCD", the default) |
//! | low first  | normal | `CCDD AABB` ("CDAB") |
//! | high first | swapped | `BBAA DDCC` ("BADC") |
//! | low first  | swapped | `DDCC BBAA` ("DCBA") |
//!
//! ```
//! use driver_modbus::codec::{ByteOrder, Layout, Number, ValueType, WordOrder};
//!
//! let f = Layout { ty: ValueType::F32, words: WordOrder::LowFirst, bytes: ByteOrder::Normal };
//! let regs = f.encode(Number::Float(1.5)).unwrap();
//! assert_eq!(regs.as_slice(), &[0x0000, 0x3FC0]);
//! assert_eq!(f.decode(regs.as_slice()).unwrap(), Number::Float(1.5));
//! ```

use serde::Deserialize;

/// The type of a value held in registers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ValueType {
    /// One register, unsigned (the default).
    #[default]
    U16,
    /// One register, two's complement.
    I16,
    /// Two registers, unsigned.
    U32,
    /// Two registers, two's complement.
    I32,
    /// Two registers, IEEE 754 single precision.
    F32,
    /// Four registers, unsigned.
    U64,
    /// Four registers, two's complement.
    I64,
    /// Four registers, IEEE 754 double precision.
    F64,
}

impl std::fmt::Display for ValueType {
    /// The type's name as a configuration writes it (`f32`).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            ValueType::U16 => "u16",
            ValueType::I16 => "i16",
            ValueType::U32 => "u32",
            ValueType::I32 => "i32",
            ValueType::F32 => "f32",
            ValueType::U64 => "u64",
            ValueType::I64 => "i64",
            ValueType::F64 => "f64",
        })
    }
}

impl ValueType {
    /// How many registers a value takes.
    pub fn registers(self) -> usize {
        match self {
            ValueType::U16 | ValueType::I16 => 1,
            ValueType::U32 | ValueType::I32 | ValueType::F32 => 2,
            ValueType::U64 | ValueType::I64 | ValueType::F64 => 4,
        }
    }

    /// True for the floating-point types.
    pub fn is_float(self) -> bool {
        matches!(self, ValueType::F32 | ValueType::F64)
    }
}

/// Which register of a multi-register value holds the most significant word.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WordOrder {
    /// The first register is the most significant (the usual order).
    #[default]
    HighFirst,
    /// The first register is the least significant.
    LowFirst,
}

/// Whether the two bytes inside each register are swapped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ByteOrder {
    /// High byte first, as Modbus sends a register.
    #[default]
    Normal,
    /// Low byte first inside each register.
    Swapped,
}

/// A decoded value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Number {
    /// From a signed type.
    Int(i64),
    /// From an unsigned type.
    UInt(u64),
    /// From a floating-point type.
    Float(f64),
}

impl Number {
    /// The value as an f64 (integers beyond 2^53 round).
    pub fn as_f64(self) -> f64 {
        match self {
            Number::Int(v) => v as f64,
            Number::UInt(v) => v as f64,
            Number::Float(v) => v,
        }
    }
}

/// Why registers and a value did not fit.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum CodecError {
    /// A reply with fewer registers than the type needs.
    #[error("{ty} needs {need} registers, {got} given")]
    Short {
        /// The type.
        ty: ValueType,
        /// Registers it takes.
        need: usize,
        /// Registers there were.
        got: usize,
    },
    /// A value outside what the type can hold (or NaN for an integer type).
    #[error("{} does not fit a {ty} register value", device_interface::text::Number(*.value))]
    OutOfRange {
        /// The type.
        ty: ValueType,
        /// The value.
        value: f64,
    },
}

/// Registers of one value: at most four.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Registers {
    regs: [u16; 4],
    len: usize,
}

impl Registers {
    /// The registers, first address first.
    pub fn as_slice(&self) -> &[u16] {
        &self.regs[..self.len]
    }
}

/// A type and its layout in registers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct Layout {
    /// The value type.
    pub ty: ValueType,
    /// Word order of multi-register values.
    pub words: WordOrder,
    /// Byte order inside each register.
    pub bytes: ByteOrder,
}

impl Layout {
    /// The value's bits from `regs` (at least `ty.registers()` of them), most significant
    /// word first, bytes in their natural order.
    fn bits(&self, regs: &[u16]) -> Result<u64, CodecError> {
        let n = self.ty.registers();
        if regs.len() < n {
            return Err(CodecError::Short {
                ty: self.ty,
                need: n,
                got: regs.len(),
            });
        }
        let mut v: u64 = 0;
        for i in 0..n {
            let r = match self.words {
                WordOrder::HighFirst => regs[i],
                WordOrder::LowFirst => regs[n - 1 - i],
            };
            let r = match self.bytes {
                ByteOrder::Normal => r,
                ByteOrder::Swapped => r.swap_bytes(),
            };
            v = (v << 16) | u64::from(r);
        }
        Ok(v)
    }

    fn registers(&self, bits: u64) -> Registers {
        let n = self.ty.registers();
        let mut regs = [0u16; 4];
        for i in 0..n {
            // Word i counted from the most significant.
            let word = (bits >> (16 * (n - 1 - i))) as u16;
            let word = match self.bytes {
                ByteOrder::Normal => word,
                ByteOrder::Swapped => word.swap_bytes(),
            };
            let at = match self.words {
                WordOrder::HighFirst => i,
                WordOrder::LowFirst => n - 1 - i,
            };
            regs[at] = word;
        }
        Registers { regs, len: n }
    }

    /// Decodes the value at the start of `regs`.
    pub fn decode(&self, regs: &[u16]) -> Result<Number, CodecError> {
        let b = self.bits(regs)?;
        Ok(match self.ty {
            ValueType::U16 | ValueType::U32 | ValueType::U64 => Number::UInt(b),
            ValueType::I16 => Number::Int(i64::from(b as u16 as i16)),
            ValueType::I32 => Number::Int(i64::from(b as u32 as i32)),
            ValueType::I64 => Number::Int(b as i64),
            ValueType::F32 => Number::Float(f64::from(f32::from_bits(b as u32))),
            ValueType::F64 => Number::Float(f64::from_bits(b)),
        })
    }

    /// Encodes `value` into registers; integers must fit the type exactly, floats are
    /// converted (f32 rounds).
    pub fn encode(&self, value: Number) -> Result<Registers, CodecError> {
        let out_of_range = || CodecError::OutOfRange {
            ty: self.ty,
            value: value.as_f64(),
        };
        let int = |min: i128, max: i128| -> Result<i128, CodecError> {
            let v: i128 = match value {
                Number::Int(v) => i128::from(v),
                Number::UInt(v) => i128::from(v),
                Number::Float(f) if f.fract() == 0.0 && f.is_finite() && f.abs() < 1.8e19 => {
                    f as i128
                }
                Number::Float(_) => return Err(out_of_range()),
            };
            if (min..=max).contains(&v) {
                Ok(v)
            } else {
                Err(out_of_range())
            }
        };
        let bits: u64 = match self.ty {
            ValueType::U16 => int(0, i128::from(u16::MAX))? as u64,
            ValueType::I16 => int(i128::from(i16::MIN), i128::from(i16::MAX))? as i16 as u16 as u64,
            ValueType::U32 => int(0, i128::from(u32::MAX))? as u64,
            ValueType::I32 => int(i128::from(i32::MIN), i128::from(i32::MAX))? as i32 as u32 as u64,
            ValueType::U64 => int(0, i128::from(u64::MAX))? as u64,
            ValueType::I64 => int(i128::from(i64::MIN), i128::from(i64::MAX))? as i64 as u64,
            ValueType::F32 => {
                let f = value.as_f64();
                if f.is_finite() && f.abs() > f64::from(f32::MAX) {
                    return Err(out_of_range());
                }
                u64::from((f as f32).to_bits())
            }
            ValueType::F64 => value.as_f64().to_bits(),
        };
        Ok(self.registers(bits))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout(ty: ValueType, words: WordOrder, bytes: ByteOrder) -> Layout {
        Layout { ty, words, bytes }
    }

    #[test]
    fn the_four_32_bit_layouts() {
        use ByteOrder::*;
        use WordOrder::*;
        let v = Number::UInt(0xAABB_CCDD);
        for (w, b, regs) in [
            (HighFirst, Normal, [0xAABB, 0xCCDD]),
            (LowFirst, Normal, [0xCCDD, 0xAABB]),
            (HighFirst, Swapped, [0xBBAA, 0xDDCC]),
            (LowFirst, Swapped, [0xDDCC, 0xBBAA]),
        ] {
            let l = layout(ValueType::U32, w, b);
            assert_eq!(l.encode(v).unwrap().as_slice(), &regs, "{w:?} {b:?}");
            assert_eq!(l.decode(&regs).unwrap(), v, "{w:?} {b:?}");
        }
    }

    #[test]
    fn signed_and_float_values() {
        let d = |ty, regs: &[u16]| {
            layout(ty, WordOrder::HighFirst, ByteOrder::Normal)
                .decode(regs)
                .unwrap()
        };
        assert_eq!(d(ValueType::I16, &[0xFFFE]), Number::Int(-2));
        assert_eq!(d(ValueType::U16, &[0xFFFE]), Number::UInt(65534));
        assert_eq!(d(ValueType::I32, &[0xFFFF, 0xFFFF]), Number::Int(-1));
        assert_eq!(
            d(ValueType::F32, &[0x4049, 0x0FDB]),
            Number::Float(f64::from(std::f32::consts::PI))
        );
        assert_eq!(d(ValueType::I64, &[0x8000, 0, 0, 0]), Number::Int(i64::MIN));
        assert_eq!(d(ValueType::F64, &[0x3FF0, 0, 0, 0]), Number::Float(1.0));
        assert_eq!(d(ValueType::U64, &[0, 0, 0, 7]), Number::UInt(7));
    }

    #[test]
    fn every_type_and_layout_round_trips() {
        use ByteOrder::*;
        use WordOrder::*;
        let samples: [(ValueType, &[Number]); 8] = [
            (
                ValueType::U16,
                &[Number::UInt(0), Number::UInt(65535), Number::UInt(258)],
            ),
            (
                ValueType::I16,
                &[Number::Int(-32768), Number::Int(32767), Number::Int(-1)],
            ),
            (
                ValueType::U32,
                &[Number::UInt(u64::from(u32::MAX)), Number::UInt(65536)],
            ),
            (
                ValueType::I32,
                &[Number::Int(i64::from(i32::MIN)), Number::Int(-65536)],
            ),
            (
                ValueType::F32,
                &[
                    Number::Float(-0.15625),
                    Number::Float(f64::from(f32::MAX)),
                    Number::Float(0.0),
                ],
            ),
            (
                ValueType::U64,
                &[Number::UInt(u64::MAX), Number::UInt(0x0102_0304_0506_0708)],
            ),
            (ValueType::I64, &[Number::Int(i64::MIN), Number::Int(-2)]),
            (
                ValueType::F64,
                &[Number::Float(-1.0e-300), Number::Float(123456.789)],
            ),
        ];
        for (ty, values) in samples {
            for w in [HighFirst, LowFirst] {
                for b in [Normal, Swapped] {
                    let l = layout(ty, w, b);
                    for v in values {
                        let regs = l.encode(*v).unwrap();
                        assert_eq!(regs.as_slice().len(), ty.registers());
                        assert_eq!(l.decode(regs.as_slice()).unwrap(), *v, "{ty:?} {w:?} {b:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn refusals() {
        let l = |ty| layout(ty, WordOrder::HighFirst, ByteOrder::Normal);
        assert!(matches!(
            l(ValueType::U32).decode(&[1]),
            Err(CodecError::Short {
                need: 2,
                got: 1,
                ..
            })
        ));
        assert!(l(ValueType::U16).encode(Number::Int(-1)).is_err());
        assert!(l(ValueType::U16).encode(Number::UInt(65536)).is_err());
        assert!(
            l(ValueType::I16).encode(Number::Float(1.5)).is_err(),
            "integer registers take whole numbers"
        );
        assert!(l(ValueType::I16).encode(Number::Float(f64::NAN)).is_err());
        assert!(l(ValueType::F32).encode(Number::Float(1e39)).is_err());
        assert_eq!(
            l(ValueType::I16)
                .encode(Number::Float(-7.0))
                .unwrap()
                .as_slice(),
            &[0xFFF9]
        );
        assert_eq!(
            CodecError::Short {
                ty: ValueType::F64,
                need: 4,
                got: 2
            }
            .to_string(),
            "f64 needs 4 registers, 2 given"
        );
    }
}
