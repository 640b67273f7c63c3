//! One `sdo` setting of a node (`{ object = "0x6423:0", value = 1 }`) as the SDO write
//! that stores it: the value checked against the object's type in the node's dictionary
//! and laid out as CiA 301 stores it (little endian, its size).

use crate::eds::{ObjectDictionary, data_type};
use crate::pdo::{Write, type_bits};

/// The write of one `sdo` setting: the value as the object's type stores it.
pub fn write(
    od: &ObjectDictionary,
    object: &str,
    value: crate::section::toml_value::Number,
) -> Result<Write, String> {
    use crate::section::toml_value::Number;
    let (index, sub) = crate::section::parse_object(object)
        .ok_or_else(|| format!("{object:?}: expected 0xINDEX:SUB"))?;
    let v = od
        .variable(index, sub)
        .ok_or_else(|| format!("{index:#06x} sub {sub} is not in the node's dictionary"))?;
    let bits = type_bits(v.data_type)
        .ok_or_else(|| format!("{index:#06x} sub {sub} ({}) is not a number", v.name))?;
    let bytes = usize::from(bits).div_ceil(8);
    let data = match (v.data_type, value) {
        (data_type::REAL32, Number::Float(f)) => (f as f32).to_le_bytes().to_vec(),
        (data_type::REAL32, Number::Int(i)) => (i as f32).to_le_bytes().to_vec(),
        (data_type::REAL64, Number::Float(f)) => f.to_le_bytes().to_vec(),
        (data_type::REAL64, Number::Int(i)) => (i as f64).to_le_bytes().to_vec(),
        (_, Number::Float(f)) => {
            return Err(format!(
                "{f}: {index:#06x} sub {sub} ({}) is an integer",
                v.name
            ));
        }
        (t, Number::Int(i)) => {
            let signed = data_type::signed_bits(t).is_some();
            let fits = if bits >= 64 {
                signed || i >= 0
            } else if signed {
                let half = 1i64 << (bits - 1);
                (-half..half).contains(&i)
            } else {
                (0..1i64 << bits).contains(&i)
            };
            if !fits {
                return Err(format!(
                    "{i} does not fit {index:#06x} sub {sub} ({}, {bits} bits{})",
                    v.name,
                    if signed { ", signed" } else { "" }
                ));
            }
            i.to_le_bytes()[..bytes].to_vec()
        }
    };
    Ok(Write { index, sub, data })
}
