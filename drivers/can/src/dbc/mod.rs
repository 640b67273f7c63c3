//! Reading a DBC file: its messages and signals, and what the file says about them.
//!
//! The file is cut into tokens ([`lex`]) and read statement by statement, each by its
//! keyword, as the format defines them — white space between tokens is free, strings may
//! span lines. Read: `BO_` messages and their `SG_` signals (start bit, length, byte order,
//! signedness, factor, offset, range, unit, and simple multiplexing: `M` the multiplexer,
//! `m<k>` a signal present when it holds `k`), `SIG_VALTYPE_` (IEEE floats and doubles),
//! `CM_` comments of messages and signals, `VAL_` value descriptions, `BA_DEF_DEF_` and
//! `BA_` for `GenMsgCycleTime`, and `SG_MUL_VAL_` (extended multiplexing, marked). Every
//! other statement is skipped by its keyword (`VERSION`, `NS_`, `BS_`, `BU_`, `BA_DEF_`,
//! `VAL_TABLE_`, `BO_TX_BU_`, `SIG_GROUP_`, `EV_`, …), as is the pseudo-message
//! `VECTOR__INDEPENDENT_SIG_MSG` that CANdb++ writes for signals placed in no message.
//!
//! A problem in one message (a signal that does not parse or fit) is kept with that
//! message ([`Message::problems`]) and reported only when a deployment maps it: what is not
//! mapped is never a reason to refuse a file. Only text that cannot be cut into tokens (a
//! string never closed) refuses the whole file. Files are UTF-8, or Windows-1252 as CANdb++
//! writes them (taken when the bytes are not UTF-8, or when asked for).
//!
//! ```
//! use driver_can::dbc::Dbc;
//!
//! let dbc = Dbc::parse("engine.dbc", r#"
//! BO_ 291 EngineData: 8 ECU
//!  SG_ EngineTemp : 16|8@1+ (1,-40) [-40|215] "degC" Gateway
//!  SG_ Torque : 7|16@0- (0.1,0) [-3276.8|3276.7] "Nm" Gateway
//! "#)?;
//! let m = dbc.message("EngineData").unwrap();
//! assert_eq!((m.id, m.extended, m.length), (291, false, 8));
//! assert_eq!(m.signal("EngineTemp").unwrap().signal.decode(&[0, 0, 130, 0, 0, 0, 0, 0])?, 90.0);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

pub mod lex;
mod parse;

use crate::signal::Signal;
use serde::Deserialize;
use std::time::Duration;

/// How a signal takes part in its message's multiplexing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Mux {
    /// Always present.
    #[default]
    Plain,
    /// The multiplexer (`M`): its value says which multiplexed signals the frame carries.
    Multiplexer,
    /// Present when the multiplexer holds this value (`m<k>`).
    When(u64),
}

/// A signal of a message, with its name and what the file says about it.
#[derive(Debug, Clone, PartialEq)]
pub struct DbcSignal {
    /// The signal's name.
    pub name: String,
    /// Where and how it sits in the payload (its value type from `SIG_VALTYPE_`).
    pub signal: Signal,
    /// Declared physical minimum (DBC `[min|max]`; 0|0 means "not given").
    pub min: f64,
    /// Declared physical maximum.
    pub max: f64,
    /// The line it was declared on.
    pub line: usize,
    /// Its part in multiplexing.
    pub mux: Mux,
    /// Its `CM_` comment.
    pub comment: Option<String>,
    /// Its `VAL_` descriptions: raw value and name, in file order.
    pub values: Vec<(i64, String)>,
}

/// A message: a CAN id and its signals.
#[derive(Debug, Clone, PartialEq)]
pub struct Message {
    /// The CAN id (without the extended flag).
    pub id: u32,
    /// True for a 29-bit id.
    pub extended: bool,
    /// A CAN FD frame: its `VFrameFormat` says so (`StandardCAN_FD`, `ExtendedCAN_FD`, or
    /// the attribute's default), or it is longer than 8 bytes.
    pub fd: bool,
    /// The message's name.
    pub name: String,
    /// Payload length in bytes.
    pub length: usize,
    /// Its signals, in file order.
    pub signals: Vec<DbcSignal>,
    /// The line it was declared on.
    pub line: usize,
    /// Its cycle (`GenMsgCycleTime`, the message's or the attribute's default; none when
    /// 0 or not given).
    pub cycle: Option<Duration>,
    /// Its `CM_` comment.
    pub comment: Option<String>,
    /// It uses extended multiplexing (`SG_MUL_VAL_`, or a signal both multiplexed and a
    /// multiplexer), which is not decoded.
    pub extended_mux: bool,
    /// What is wrong with its definition (reported when it is mapped).
    pub problems: Vec<DbcError>,
}

impl Message {
    /// The signal named `name`.
    pub fn signal(&self, name: &str) -> Option<&DbcSignal> {
        self.signals.iter().find(|s| s.name == name)
    }

    /// Its multiplexer signal, if it has one.
    pub fn multiplexer(&self) -> Option<&DbcSignal> {
        self.signals.iter().find(|s| s.mux == Mux::Multiplexer)
    }
}

/// Why a DBC file, or a message of it, was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{file}{}: {}{problem}", if *.line > 0 { format!(":{line}") } else { String::new() }, .signal.as_ref().map(|s| format!("signal {s}: ")).unwrap_or_default())]
pub struct DbcError {
    /// The file.
    pub file: String,
    /// The line, from 1 (0: the file as a whole).
    pub line: usize,
    /// The signal concerned, if any.
    pub signal: Option<String>,
    /// What is wrong.
    pub problem: String,
}

/// A DBC file's text encoding.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Encoding {
    /// UTF-8 when the bytes are, else Windows-1252 (the default).
    #[default]
    Auto,
    /// UTF-8 (a byte sequence that is not is an error naming its line).
    Utf8,
    /// Windows-1252, as CANdb++ writes.
    Cp1252,
}

/// The largest DBC file read, bytes (16 MiB; real ones are well under a megabyte).
pub const MAX_DBC_BYTES: u64 = 16 << 20;

/// The messages of a DBC file.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Dbc {
    /// In file order (pseudo-messages left out).
    pub messages: Vec<Message>,
    /// What the file's text was read as.
    pub encoding: &'static str,
}

impl Dbc {
    /// Reads `path`, its text UTF-8 or Windows-1252 as `encoding` says.
    pub fn load(path: &std::path::Path, encoding: Encoding) -> Result<Dbc, DbcError> {
        let file = path.display().to_string();
        let fail = |line: usize, problem: String| DbcError {
            file: file.clone(),
            line,
            signal: None,
            problem,
        };
        // A DBC file is text of bounded size: not a device, a pipe or a directory.
        let meta = std::fs::metadata(path).map_err(|e| fail(0, format!("cannot read: {e}")))?;
        if !meta.is_file() {
            return Err(fail(0, "not a regular file (a DBC file is text)".into()));
        }
        if meta.len() > MAX_DBC_BYTES {
            return Err(fail(
                0,
                format!(
                    "{} bytes: a DBC file is at most {MAX_DBC_BYTES} bytes",
                    meta.len()
                ),
            ));
        }
        let mut bytes = Vec::new();
        std::io::Read::read_to_end(
            &mut std::io::Read::take(
                std::fs::File::open(path).map_err(|e| fail(0, format!("cannot read: {e}")))?,
                MAX_DBC_BYTES,
            ),
            &mut bytes,
        )
        .map_err(|e| fail(0, format!("cannot read: {e}")))?;
        let (text, used) = decode(&bytes, encoding).map_err(|(line, p)| fail(line, p))?;
        let mut dbc = Self::parse(&file, &text)?;
        dbc.encoding = used;
        Ok(dbc)
    }

    /// Parses DBC `text`, naming it `file` in errors.
    pub fn parse(file: &str, text: &str) -> Result<Dbc, DbcError> {
        let messages = parse::messages(file, text)?;
        Ok(Dbc {
            messages,
            encoding: "utf-8",
        })
    }

    /// The message named `name`.
    pub fn message(&self, name: &str) -> Option<&Message> {
        self.messages.iter().find(|m| m.name == name)
    }
}

/// The text of `bytes` and the encoding it was read as; an error names the line of the
/// first byte that is not UTF-8 when UTF-8 was asked for.
fn decode(bytes: &[u8], encoding: Encoding) -> Result<(String, &'static str), (usize, String)> {
    let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    match (std::str::from_utf8(bytes), encoding) {
        (Ok(s), Encoding::Auto | Encoding::Utf8) => Ok((s.to_string(), "utf-8")),
        (Err(e), Encoding::Utf8) => {
            let line = 1 + bytes[..e.valid_up_to()]
                .iter()
                .filter(|&&b| b == b'\n')
                .count();
            Err((
                line,
                format!(
                    "not UTF-8 (byte {:#04x}); set encoding = \"cp1252\" for a file CANdb++ wrote",
                    bytes[e.valid_up_to()]
                ),
            ))
        }
        _ => Ok((bytes.iter().map(|&b| cp1252(b)).collect(), "windows-1252")),
    }
}

/// A Windows-1252 byte as a character (the five bytes it leaves undefined as the C1
/// control of the same number).
fn cp1252(b: u8) -> char {
    const HIGH: [char; 32] = [
        '€', '\u{81}', '‚', 'ƒ', '„', '…', '†', '‡', 'ˆ', '‰', 'Š', '‹', 'Œ', '\u{8D}', 'Ž',
        '\u{8F}', '\u{90}', '‘', '’', '“', '”', '•', '–', '—', '˜', '™', 'š', '›', 'œ', '\u{9D}',
        'ž', 'Ÿ',
    ];
    match b {
        0x80..=0x9F => HIGH[usize::from(b - 0x80)],
        _ => char::from(b),
    }
}

#[cfg(test)]
mod tests;
