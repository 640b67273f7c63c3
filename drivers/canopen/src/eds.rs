//! A CANopen node's object dictionary from its EDS (electronic data sheet, CiA 306): the
//! INI file a vendor ships with a device.
//!
//! - Sections `[XXXX]` (four hex digits) are objects; `[XXXXsubY]` their sub-indices
//!   (`Y` hex). `ObjectType` 0x7 (VAR, the default when missing) and 0x2 (DOMAIN) are one
//!   variable at sub-index 0; 0x8 (ARRAY) and 0x9 (RECORD) gather their sub-sections.
//! - A variable: `ParameterName`, `DataType` (a CiA 301 basic type, 0x01-0x1B),
//!   `AccessType` (ro, wo, rw, rwr, rww, const), `PDOMapping`, `LowLimit`, `HighLimit`,
//!   `DefaultValue`. Integer values are C-style (`0x1A`, `017` octal, decimal); a
//!   `$NODEID` in an integer value adds the node id (`$NODEID+0x180`), as COB-IDs are
//!   written. Floats are decimal; strings as written; octet strings and domains hex.
//! - Keys are case-insensitive (CiA 306); `;` starts a comment at a line's start or after
//!   a blank, `#` at a line's start.
//! - Every problem names its line: a value that does not parse, an unknown access type,
//!   a sub-index without its object, an object defined twice. Files over
//!   [`MAX_EDS_BYTES`] are refused unread.
//! - Not read yet: `CompactSubObj`, `[XXXXName]` sections, `[DummyUsage]`, data types
//!   defined in the file (above 0x1B), `ParameterValue`.

use std::collections::BTreeMap;

/// The largest EDS read (real ones are tens of kilobytes).
pub const MAX_EDS_BYTES: usize = 4 << 20;

/// Why an EDS was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("line {line}: {message}")]
pub struct EdsError {
    /// 1-based line (0: the file as a whole).
    pub line: usize,
    /// What is wrong.
    pub message: String,
}

fn error(line: usize, message: impl Into<String>) -> EdsError {
    EdsError {
        line,
        message: message.into(),
    }
}

/// How a variable may be accessed over SDO.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// Read only.
    Ro,
    /// Write only.
    Wo,
    /// Read and write.
    Rw,
    /// Read and write, mapped into TPDOs (read by the process).
    Rwr,
    /// Read and write, mapped into RPDOs (written by the process).
    Rww,
    /// Constant.
    Const,
}

impl Access {
    /// Its EDS spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Access::Ro => "ro",
            Access::Wo => "wo",
            Access::Rw => "rw",
            Access::Rwr => "rwr",
            Access::Rww => "rww",
            Access::Const => "const",
        }
    }
}

/// A value from the file, as its data type reads it.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    /// Booleans and integers.
    Int(i128),
    /// REAL32 and REAL64.
    Float(f64),
    /// VISIBLE_STRING and UNICODE_STRING.
    Text(String),
    /// OCTET_STRING and DOMAIN.
    Bytes(Vec<u8>),
}

/// CiA 301 basic data types, by code.
pub mod data_type {
    /// BOOLEAN.
    pub const BOOLEAN: u16 = 0x01;
    /// INTEGER8.
    pub const INTEGER8: u16 = 0x02;
    /// INTEGER16.
    pub const INTEGER16: u16 = 0x03;
    /// INTEGER32.
    pub const INTEGER32: u16 = 0x04;
    /// UNSIGNED8.
    pub const UNSIGNED8: u16 = 0x05;
    /// UNSIGNED16.
    pub const UNSIGNED16: u16 = 0x06;
    /// UNSIGNED32.
    pub const UNSIGNED32: u16 = 0x07;
    /// REAL32.
    pub const REAL32: u16 = 0x08;
    /// VISIBLE_STRING.
    pub const VISIBLE_STRING: u16 = 0x09;
    /// OCTET_STRING.
    pub const OCTET_STRING: u16 = 0x0A;
    /// UNICODE_STRING.
    pub const UNICODE_STRING: u16 = 0x0B;
    /// DOMAIN.
    pub const DOMAIN: u16 = 0x0F;
    /// REAL64.
    pub const REAL64: u16 = 0x11;
    /// INTEGER64.
    pub const INTEGER64: u16 = 0x15;
    /// UNSIGNED64.
    pub const UNSIGNED64: u16 = 0x1B;

    /// The bits of a signed integer type (INTEGER8 to INTEGER64, with 24, 40, 48, 56).
    pub fn signed_bits(t: u16) -> Option<u32> {
        match t {
            INTEGER8 => Some(8),
            INTEGER16 => Some(16),
            0x10 => Some(24),
            INTEGER32 => Some(32),
            0x12 => Some(40),
            0x13 => Some(48),
            0x14 => Some(56),
            INTEGER64 => Some(64),
            _ => None,
        }
    }
}

/// One entry: an object's variable, or a sub-index of an array or record.
#[derive(Debug, Clone, PartialEq)]
pub struct Variable {
    /// Object index.
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
    /// `ParameterName`.
    pub name: String,
    /// `DataType` ([`data_type`]).
    pub data_type: u16,
    /// `AccessType`.
    pub access: Access,
    /// `PDOMapping`: may be mapped into a PDO.
    pub pdo_mappable: bool,
    /// `DefaultValue`, read by its type (the node id added where it says `$NODEID`).
    pub default: Option<Value>,
    /// The default depends on the node id (`$NODEID`).
    pub relative: bool,
    /// `LowLimit`.
    pub min: Option<Value>,
    /// `HighLimit`.
    pub max: Option<Value>,
}

/// What kind of object.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// One variable (VAR or DOMAIN), at sub-index 0.
    Variable,
    /// An ARRAY: sub-index 0 the count, the entries of one type.
    Array,
    /// A RECORD: sub-indices of their own types.
    Record,
}

/// An object of the dictionary.
#[derive(Debug, Clone, PartialEq)]
pub struct Object {
    /// Index.
    pub index: u16,
    /// `ParameterName`.
    pub name: String,
    /// Variable, array or record.
    pub kind: Kind,
    /// Its variables by sub-index (one at 0 for a variable).
    pub subs: BTreeMap<u8, Variable>,
}

/// A node's object dictionary.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ObjectDictionary {
    /// Objects by index.
    pub objects: BTreeMap<u16, Object>,
}

impl ObjectDictionary {
    /// The variable at `index`, `sub`.
    pub fn variable(&self, index: u16, sub: u8) -> Option<&Variable> {
        self.objects.get(&index)?.subs.get(&sub)
    }
}

/// One `[section]` of the file: its name, line, and keys (lower-cased) with values and
/// lines.
struct Section<'a> {
    name: &'a str,
    line: usize,
    keys: BTreeMap<String, (&'a str, usize)>,
}

impl<'a> Section<'a> {
    fn get(&self, key: &str) -> Option<(&'a str, usize)> {
        self.keys.get(key).copied()
    }

    fn need(&self, key: &str) -> Result<(&'a str, usize), EdsError> {
        self.get(&key.to_ascii_lowercase())
            .ok_or_else(|| error(self.line, format!("[{}] has no {key}", self.name)))
    }
}

/// The sections of an INI text, in order. A key repeated in a section: the last holds.
fn sections(text: &str) -> Result<Vec<Section<'_>>, EdsError> {
    let mut out: Vec<Section<'_>> = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = i + 1;
        let l = strip_comment(raw).trim();
        if l.is_empty() {
            continue;
        }
        if let Some(name) = l.strip_prefix('[') {
            let name = name
                .strip_suffix(']')
                .ok_or_else(|| error(line, format!("{l:?}: a section name without its ]")))?;
            out.push(Section {
                name: name.trim(),
                line,
                keys: BTreeMap::new(),
            });
            continue;
        }
        let Some((key, value)) = l.split_once('=') else {
            return Err(error(
                line,
                format!("{l:?}: expected key=value or [section]"),
            ));
        };
        let Some(section) = out.last_mut() else {
            return Err(error(line, format!("{l:?} comes before any [section]")));
        };
        section
            .keys
            .insert(key.trim().to_ascii_lowercase(), (value.trim(), line));
    }
    Ok(out)
}

/// The line without its comment: `;` at its start or after a blank.
fn strip_comment(l: &str) -> &str {
    if l.trim_start().starts_with([';', '#']) {
        return "";
    }
    let b = l.as_bytes();
    (1..b.len())
        .find(|&i| b[i] == b';' && b[i - 1].is_ascii_whitespace())
        .map_or(l, |i| &l[..i])
}

/// A C-style integer: `0x`/`0X` hex, a leading `0` octal, else decimal, with a sign.
fn c_int(s: &str) -> Option<i128> {
    let s = s.trim();
    let (neg, digits) = match s.strip_prefix('-') {
        Some(d) => (true, d),
        None => (false, s.strip_prefix('+').unwrap_or(s)),
    };
    let v = if let Some(h) = digits
        .strip_prefix("0x")
        .or_else(|| digits.strip_prefix("0X"))
    {
        i128::from_str_radix(h, 16).ok()?
    } else if digits.len() > 1 && digits.starts_with('0') {
        i128::from_str_radix(&digits[1..], 8).ok()?
    } else {
        digits.parse::<i128>().ok()?
    };
    Some(if neg { -v } else { v })
}

/// An integer value, `$NODEID` added where it stands.
fn int_value(s: &str, node_id: Option<u8>) -> Option<(i128, bool)> {
    let compact: String = s.chars().filter(|c| !c.is_whitespace()).collect();
    let upper = compact.to_ascii_uppercase();
    if let Some(at) = upper.find("$NODEID") {
        let rest = format!("{}{}", &compact[..at], &compact[at + "$NODEID".len()..]);
        let rest = rest.trim_matches('+');
        let base = if rest.is_empty() { 0 } else { c_int(rest)? };
        return Some((base + i128::from(node_id.unwrap_or(0)), true));
    }
    Some((c_int(&compact)?, false))
}

/// `text` as a value of `data_type`; `relative` when it named the node id.
fn value(data_type: u16, text: &str, node_id: Option<u8>) -> Option<(Value, bool)> {
    use data_type::*;
    match data_type {
        VISIBLE_STRING | UNICODE_STRING => Some((Value::Text(text.to_string()), false)),
        OCTET_STRING | DOMAIN => {
            let hex: String = text.chars().filter(|c| !c.is_whitespace()).collect();
            if !hex.len().is_multiple_of(2) {
                return None;
            }
            let bytes = (0..hex.len())
                .step_by(2)
                .map(|i| u8::from_str_radix(hex.get(i..i + 2)?, 16).ok())
                .collect::<Option<Vec<u8>>>()?;
            Some((Value::Bytes(bytes), false))
        }
        REAL32 | REAL64 => Some((Value::Float(text.trim().parse().ok()?), false)),
        _ => {
            let (v, relative) = int_value(text, node_id)?;
            Some((Value::Int(v), relative))
        }
    }
}

/// A limit of `data_type`: a signed type's hex limit is its two's complement.
fn limit(data_type: u16, text: &str) -> Option<Value> {
    let v = c_int(text)?;
    Some(Value::Int(match data_type::signed_bits(data_type) {
        Some(bits) if v >= 1i128 << (bits - 1) => v - (1i128 << bits),
        _ => v,
    }))
}

fn variable(
    s: &Section<'_>,
    index: u16,
    sub: u8,
    node_id: Option<u8>,
) -> Result<Variable, EdsError> {
    let (name, _) = s.need("ParameterName")?;
    let (t, tl) = s.need("DataType")?;
    let data_type = c_int(t)
        .and_then(|v| u16::try_from(v).ok())
        .filter(|v| (1..=0x1B).contains(v))
        .ok_or_else(|| {
            error(
                tl,
                format!("DataType {t:?}: expected a CiA 301 basic type, 0x0001 to 0x001B"),
            )
        })?;
    let (a, al) = s.need("AccessType")?;
    let access = match a.to_ascii_lowercase().as_str() {
        "ro" => Access::Ro,
        "wo" => Access::Wo,
        "rw" => Access::Rw,
        "rwr" => Access::Rwr,
        "rww" => Access::Rww,
        "const" => Access::Const,
        other => {
            return Err(error(
                al,
                format!("AccessType {other:?}: expected ro, wo, rw, rwr, rww or const"),
            ));
        }
    };
    let pdo_mappable = match s.get("pdomapping") {
        None => false,
        Some((m, ml)) => {
            c_int(m).ok_or_else(|| error(ml, format!("PDOMapping {m:?}: expected 0 or 1")))? != 0
        }
    };
    let (mut default, mut relative) = (None, false);
    if let Some((d, dl)) = s.get("defaultvalue")
        && !d.is_empty()
    {
        let (v, r) = value(data_type, d, node_id).ok_or_else(|| {
            error(
                dl,
                format!("DefaultValue {d:?} is not a value of data type {data_type:#06x}"),
            )
        })?;
        (default, relative) = (Some(v), r);
    }
    let bound = |key: &str| -> Result<Option<Value>, EdsError> {
        match s.get(key) {
            Some(("", _)) => Ok(None),
            Some((v, l)) => limit(data_type, v)
                .map(Some)
                .ok_or_else(|| error(l, format!("{v:?} is not an integer limit"))),
            None => Ok(None),
        }
    };
    Ok(Variable {
        index,
        sub,
        name: name.to_string(),
        data_type,
        access,
        pdo_mappable,
        default,
        relative,
        min: bound("lowlimit")?,
        max: bound("highlimit")?,
    })
}

/// `[XXXX]` as an index, `[XXXXsubY]` as index and sub-index.
fn section_index(name: &str) -> Option<(u16, Option<u8>)> {
    let hex4 = |s: &str| {
        (s.len() == 4)
            .then(|| u16::from_str_radix(s, 16).ok())
            .flatten()
    };
    if let Some(i) = hex4(name) {
        return Some((i, None));
    }
    let (i, sub) = (name.get(..4)?, name.get(4..)?);
    let sub = sub
        .strip_prefix("sub")
        .or_else(|| sub.strip_prefix("Sub"))?;
    if sub.is_empty() || sub.len() > 2 {
        return None;
    }
    Some((hex4(i)?, Some(u8::from_str_radix(sub, 16).ok()?)))
}

/// Reads an EDS text for the node `node_id` (which `$NODEID` values add; `None`: 0).
pub fn parse(text: &str, node_id: Option<u8>) -> Result<ObjectDictionary, EdsError> {
    if text.len() > MAX_EDS_BYTES {
        return Err(error(
            0,
            format!("{} bytes: an EDS is at most {MAX_EDS_BYTES}", text.len()),
        ));
    }
    let all = sections(text)?;
    let mut od = ObjectDictionary::default();
    // Objects first, then their sub-indices (a file may list them in any order).
    for s in &all {
        let Some((index, None)) = section_index(s.name) else {
            continue;
        };
        if od.objects.contains_key(&index) {
            return Err(error(
                s.line,
                format!("object {index:#06x} is defined twice"),
            ));
        }
        let kind = match s.get("objecttype") {
            None => 7,
            Some((t, tl)) => {
                c_int(t).ok_or_else(|| error(tl, format!("ObjectType {t:?} is not a number")))?
            }
        };
        let (name, _) = s.need("ParameterName")?;
        let (kind, subs) = match kind {
            2 | 7 => (
                Kind::Variable,
                BTreeMap::from([(0, variable(s, index, 0, node_id)?)]),
            ),
            8 | 9 => {
                if s.get("compactsubobj").is_some() {
                    return Err(error(
                        s.line,
                        format!("[{}]: CompactSubObj is not read yet", s.name),
                    ));
                }
                (
                    if kind == 8 { Kind::Array } else { Kind::Record },
                    BTreeMap::new(),
                )
            }
            other => {
                return Err(error(
                    s.line,
                    format!(
                        "ObjectType {other:#x}: expected 0x7 (VAR), 0x2 (DOMAIN), 0x8 (ARRAY) or 0x9 (RECORD)"
                    ),
                ));
            }
        };
        od.objects.insert(
            index,
            Object {
                index,
                name: name.to_string(),
                kind,
                subs,
            },
        );
    }
    for s in &all {
        let Some((index, Some(sub))) = section_index(s.name) else {
            continue;
        };
        let v = variable(s, index, sub, node_id)?;
        let Some(o) = od.objects.get_mut(&index) else {
            return Err(error(
                s.line,
                format!("[{}]: no object {index:#06x} to belong to", s.name),
            ));
        };
        if o.kind == Kind::Variable {
            return Err(error(
                s.line,
                format!(
                    "[{}]: object {index:#06x} is a variable, with no sub-indices",
                    s.name
                ),
            ));
        }
        if o.subs.insert(sub, v).is_some() {
            return Err(error(s.line, format!("[{}] is defined twice", s.name)));
        }
    }
    Ok(od)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;

    #[test]
    fn integers_comments_and_node_ids() {
        assert_eq!(c_int("0x1A"), Some(26));
        assert_eq!(c_int("017"), Some(15));
        assert_eq!(c_int("-5"), Some(-5));
        assert_eq!(c_int("0"), Some(0));
        assert_eq!(int_value("$NODEID+0x180", Some(5)), Some((0x185, true)));
        assert_eq!(int_value("0x200 + $NODEID", Some(5)), Some((0x205, true)));
        assert_eq!(strip_comment("a=1 ; note"), "a=1 ");
        assert_eq!(strip_comment("a=x;y"), "a=x;y");
        assert_eq!(limit(data_type::INTEGER16, "0xFFFF"), Some(Value::Int(-1)));
    }

    #[test]
    fn every_problem_names_its_line() {
        let e = parse(
            "[1000]\nParameterName=x\nDataType=0x7\nAccessType=rx\n",
            None,
        )
        .unwrap_err();
        assert_eq!(e.line, 4, "{e}");
        let e = parse(
            "[1018sub1]\nParameterName=x\nDataType=0x7\nAccessType=ro\n",
            None,
        )
        .unwrap_err();
        assert_eq!(
            e.to_string(),
            "line 1: [1018sub1]: no object 0x1018 to belong to"
        );
        let e = parse("junk\n", None).unwrap_err();
        assert_eq!(e.line, 1);
        let e = parse(
            "[1000]\nParameterName=x\nDataType=0x7\nAccessType=ro\nDefaultValue=zz\n",
            None,
        )
        .unwrap_err();
        assert_eq!(e.line, 5, "{e}");
    }
}
