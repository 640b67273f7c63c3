//! Reading the messages and signals of a DBC file.
//!
//! Only what a gateway needs is read: `BO_` (message id, name, payload length) and the
//! `SG_` lines under it (start bit, length, byte order, signedness, factor, offset, range,
//! unit). Every other section — nodes, comments, attributes, value tables — is skipped.
//! Multiplexed signals are refused with a clear error rather than decoded wrongly. Errors
//! name the file, the line and the signal.
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

use crate::signal::{ByteOrder, Signal, SignalError};

/// A signal of a message, with its name and declared range.
#[derive(Debug, Clone, PartialEq)]
pub struct DbcSignal {
    /// The signal's name.
    pub name: String,
    /// Where and how it sits in the payload.
    pub signal: Signal,
    /// Declared physical minimum (DBC `[min|max]`; 0|0 means "not given").
    pub min: f64,
    /// Declared physical maximum.
    pub max: f64,
    /// The line it was declared on.
    pub line: usize,
}

/// A message: a CAN id and its signals.
#[derive(Debug, Clone, PartialEq)]
pub struct Message {
    /// The CAN id (without the extended flag).
    pub id: u32,
    /// True for a 29-bit id.
    pub extended: bool,
    /// The message's name.
    pub name: String,
    /// Payload length in bytes.
    pub length: usize,
    /// Its signals, in file order.
    pub signals: Vec<DbcSignal>,
}

impl Message {
    /// The signal named `name`.
    pub fn signal(&self, name: &str) -> Option<&DbcSignal> {
        self.signals.iter().find(|s| s.name == name)
    }
}

/// Why a DBC file was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{file}:{line}: {}{problem}", .signal.as_ref().map(|s| format!("signal {s}: ")).unwrap_or_default())]
pub struct DbcError {
    /// The file.
    pub file: String,
    /// The line, from 1.
    pub line: usize,
    /// The signal concerned, if any.
    pub signal: Option<String>,
    /// What is wrong.
    pub problem: String,
}

/// The largest DBC file read, bytes (16 MiB; real ones are well under a megabyte).
pub const MAX_DBC_BYTES: u64 = 16 << 20;

/// The messages of a DBC file.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Dbc {
    /// In file order.
    pub messages: Vec<Message>,
}

/// The extended-id flag DBC files put on 29-bit ids.
const EXTENDED: u32 = 0x8000_0000;

impl Dbc {
    /// Reads `path`.
    pub fn load(path: &std::path::Path) -> Result<Dbc, DbcError> {
        let file = path.display().to_string();
        let fail = |problem: String| DbcError {
            file: file.clone(),
            line: 0,
            signal: None,
            problem,
        };
        // A DBC file is text of bounded size: not a device, a pipe or a directory.
        let meta = std::fs::metadata(path).map_err(|e| fail(format!("cannot read: {e}")))?;
        if !meta.is_file() {
            return Err(fail("not a regular file (a DBC file is text)".into()));
        }
        if meta.len() > MAX_DBC_BYTES {
            return Err(fail(format!(
                "{} bytes: a DBC file is at most {MAX_DBC_BYTES} bytes",
                meta.len()
            )));
        }
        let mut text = String::new();
        std::io::Read::read_to_string(
            &mut std::io::Read::take(
                std::fs::File::open(path).map_err(|e| fail(format!("cannot read: {e}")))?,
                MAX_DBC_BYTES,
            ),
            &mut text,
        )
        .map_err(|e| fail(format!("cannot read: {e}")))?;
        Self::parse(&file, &text)
    }

    /// Parses DBC `text`, naming it `file` in errors.
    pub fn parse(file: &str, text: &str) -> Result<Dbc, DbcError> {
        let mut dbc = Dbc::default();
        for (n, raw) in text.lines().enumerate() {
            let line = n + 1;
            let trimmed = raw.trim();
            let err = |signal: Option<&str>, problem: String| DbcError {
                file: file.to_string(),
                line,
                signal: signal.map(String::from),
                problem,
            };
            if let Some(rest) = trimmed.strip_prefix("BO_ ") {
                dbc.messages.push(message(rest).map_err(|p| err(None, p))?);
            } else if let Some(rest) = trimmed.strip_prefix("SG_ ") {
                let name = rest.split_whitespace().next().unwrap_or("");
                let Some(m) = dbc.messages.last_mut() else {
                    return Err(err(
                        Some(name),
                        "a signal outside any message (no BO_ line before it)".into(),
                    ));
                };
                let s = signal(rest, line).map_err(|p| err(Some(name), p))?;
                if s.signal.bytes_needed() > m.length {
                    return Err(err(
                        Some(name),
                        format!(
                            "it reaches byte {} but message {} has {} bytes",
                            s.signal.bytes_needed(),
                            m.name,
                            m.length
                        ),
                    ));
                }
                if m.signal(&s.name).is_some() {
                    return Err(err(
                        Some(name),
                        format!("message {} already has a signal of that name", m.name),
                    ));
                }
                m.signals.push(s);
            }
        }
        Ok(dbc)
    }

    /// The message named `name`.
    pub fn message(&self, name: &str) -> Option<&Message> {
        self.messages.iter().find(|m| m.name == name)
    }
}

/// `291 EngineData: 8 ECU`
fn message(rest: &str) -> Result<Message, String> {
    let mut words = rest.split_whitespace();
    let id_text = words.next().ok_or("BO_ without an id")?;
    let raw_id: u32 = id_text
        .parse()
        .map_err(|_| format!("message id {id_text:?} is not a number"))?;
    let name = words
        .next()
        .ok_or("BO_ without a name")?
        .trim_end_matches(':')
        .to_string();
    let len_text = words
        .next()
        .ok_or_else(|| format!("message {name} has no length"))?;
    let length: usize = len_text
        .parse()
        .map_err(|_| format!("message {name}: length {len_text:?} is not a number"))?;
    if length > 64 {
        return Err(format!(
            "message {name}: {length} bytes is more than a CAN FD frame carries (64)"
        ));
    }
    let extended = raw_id & EXTENDED != 0;
    let id = raw_id & !EXTENDED;
    if (!extended && id > 0x7FF) || id > 0x1FFF_FFFF {
        return Err(format!(
            "message {name}: id {id:#x} does not fit a {} id",
            if extended { "29-bit" } else { "11-bit" }
        ));
    }
    Ok(Message {
        id,
        extended,
        name,
        length,
        signals: Vec::new(),
    })
}

/// `EngineTemp : 16|8@1+ (1,-40) [-40|215] "degC" Gateway`
fn signal(rest: &str, line: usize) -> Result<DbcSignal, String> {
    let (head, body) = rest
        .split_once(':')
        .ok_or("expected `name : start|length@order± (factor,offset) [min|max] \"unit\"`")?;
    let mut head_words = head.split_whitespace();
    let name = head_words
        .next()
        .ok_or("a signal without a name")?
        .to_string();
    if head_words.next().is_some() {
        return Err("multiplexed signals are not supported yet".into());
    }
    let body = body.trim();
    let (layout, rest) = body
        .split_once(' ')
        .ok_or("no (factor,offset) after the bit layout")?;
    let (start_text, rest_layout) = layout
        .split_once('|')
        .ok_or_else(|| format!("bit layout {layout:?}: expected start|length@order±"))?;
    let (len_text, order_sign) = rest_layout
        .split_once('@')
        .ok_or_else(|| format!("bit layout {layout:?}: expected start|length@order±"))?;
    let start: u32 = start_text
        .parse()
        .map_err(|_| format!("start bit {start_text:?} is not a number"))?;
    let length: u32 = len_text
        .parse()
        .map_err(|_| format!("length {len_text:?} is not a number"))?;
    let mut oc = order_sign.chars();
    let order = match oc.next() {
        Some('1') => ByteOrder::Intel,
        Some('0') => ByteOrder::Motorola,
        _ => {
            return Err(format!(
                "byte order in {layout:?}: expected @1 (Intel) or @0 (Motorola)"
            ));
        }
    };
    let signed = match oc.next() {
        Some('+') => false,
        Some('-') => true,
        _ => return Err(format!("sign in {layout:?}: expected + or -")),
    };
    let between =
        |text: &str, open: char, close: char, what: &str| -> Result<(String, String), String> {
            let a = text.find(open).ok_or_else(|| format!("no {what}"))?;
            // Search after the opening delimiter: for "unit" both delimiters are the same.
            let b = text[a + 1..]
                .find(close)
                .ok_or_else(|| format!("unclosed {what}"))?
                + a
                + 1;
            Ok((text[a + 1..b].to_string(), text[b + 1..].to_string()))
        };
    let (fo, after) = between(rest, '(', ')', "(factor,offset)")?;
    let (f_text, o_text) = fo
        .split_once(',')
        .ok_or_else(|| format!("({fo}): expected (factor,offset)"))?;
    let factor: f64 = f_text
        .trim()
        .parse()
        .map_err(|_| format!("factor {f_text:?} is not a number"))?;
    let offset: f64 = o_text
        .trim()
        .parse()
        .map_err(|_| format!("offset {o_text:?} is not a number"))?;
    let (mm, after) = between(&after, '[', ']', "[min|max]")?;
    let (min_text, max_text) = mm
        .split_once('|')
        .ok_or_else(|| format!("[{mm}]: expected [min|max]"))?;
    let min: f64 = min_text
        .trim()
        .parse()
        .map_err(|_| format!("minimum {min_text:?} is not a number"))?;
    let max: f64 = max_text
        .trim()
        .parse()
        .map_err(|_| format!("maximum {max_text:?} is not a number"))?;
    let (unit, _) = between(&after, '"', '"', "\"unit\"")?;
    let signal = Signal::new(start, length, order, signed, factor, offset, &unit)
        .map_err(|e: SignalError| e.to_string())?;
    Ok(DbcSignal {
        name,
        signal,
        min,
        max,
        line,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const DBC: &str = r#"VERSION ""

NS_ :
    CM_
    BA_DEF_

BU_: ECU Gateway

BO_ 291 EngineData: 8 ECU
 SG_ EngineTemp : 16|8@1+ (1,-40) [-40|215] "degC" Gateway
 SG_ RPM : 24|16@1+ (0.25,0) [0|16383.75] "rpm" Gateway
 SG_ Torque : 7|16@0- (0.1,0) [-3276.8|3276.7] "Nm" Gateway

BO_ 2147487744 Extended: 4 ECU
 SG_ Flag : 0|1@1+ (1,0) [0|1] "" Gateway

CM_ SG_ 291 RPM "engine speed";
BA_ "GenMsgCycleTime" BO_ 291 100;
VAL_ 291 EngineTemp 0 "cold" ;
"#;

    #[test]
    fn messages_and_signals() {
        let dbc = Dbc::parse("car.dbc", DBC).unwrap();
        assert_eq!(dbc.messages.len(), 2);
        let m = dbc.message("EngineData").unwrap();
        assert_eq!(
            (m.id, m.extended, m.length, m.signals.len()),
            (0x123, false, 8, 3)
        );
        let payload = [0x12, 0x34, 130, 0x40, 0x1F, 0, 0, 0];
        assert_eq!(
            m.signal("EngineTemp")
                .unwrap()
                .signal
                .decode(&payload)
                .unwrap(),
            90.0
        );
        assert_eq!(
            m.signal("RPM").unwrap().signal.decode(&payload).unwrap(),
            2000.0
        );
        assert_eq!(
            m.signal("Torque").unwrap().signal.decode(&payload).unwrap(),
            466.0,
            "0x1234 = 4660 * 0.1"
        );
        let t = m.signal("Torque").unwrap();
        assert_eq!((t.min, t.max, t.line), (-3276.8, 3276.7, 12));
        let e = dbc.message("Extended").unwrap();
        assert_eq!((e.id, e.extended), (0x1000, true));
    }

    #[test]
    fn malformed_files_name_file_line_and_signal() {
        let cases = [
            (
                "BO_ 291 M: 8 ECU\n SG_ A : 16|8@2+ (1,0) [0|0] \"\" X\n",
                "bad.dbc:2: signal A: byte order in \"16|8@2+\": expected @1 (Intel) or @0 (Motorola)",
            ),
            (
                "BO_ 291 M: 8 ECU\n SG_ A : 16|8@1+ (1;0) [0|0] \"\" X\n",
                "bad.dbc:2: signal A: (1;0): expected (factor,offset)",
            ),
            (
                "BO_ 291 M: 2 ECU\n SG_ A : 16|8@1+ (1,0) [0|0] \"\" X\n",
                "bad.dbc:2: signal A: it reaches byte 3 but message M has 2 bytes",
            ),
            (
                " SG_ A : 16|8@1+ (1,0) [0|0] \"\" X\n",
                "bad.dbc:1: signal A: a signal outside any message (no BO_ line before it)",
            ),
            (
                "BO_ x M: 8 ECU\n",
                "bad.dbc:1: message id \"x\" is not a number",
            ),
            (
                "BO_ 4096 M: 8 ECU\n",
                "bad.dbc:1: message M: id 0x1000 does not fit a 11-bit id",
            ),
            (
                "BO_ 291 M: 8 ECU\n SG_ A M : 0|8@1+ (1,0) [0|0] \"\" X\n",
                "bad.dbc:2: signal A: multiplexed signals are not supported yet",
            ),
            (
                "BO_ 291 M: 8 ECU\n SG_ A : 0|65@1+ (1,0) [0|0] \"\" X\n",
                "bad.dbc:2: signal A: a signal is 1 to 64 bits long, not 65",
            ),
            (
                "BO_ 291 M: 8 ECU\n SG_ A : 0|8@1+ (0,0) [0|0] \"\" X\n",
                "bad.dbc:2: signal A: factor 0 and offset 0 are invalid: needs a finite non-zero factor and a finite offset",
            ),
            (
                "BO_ 291 M: 8 ECU\n SG_ A : 0|8@1+ (1,0) [0|0] \"\" X\n SG_ A : 8|8@1+ (1,0) [0|0] \"\" X\n",
                "bad.dbc:3: signal A: message M already has a signal of that name",
            ),
            (
                "BO_ 291 M: 8 ECU\n SG_ A : 0|8@1+ (1,0) [0|0] \"V X\n",
                "bad.dbc:2: signal A: unclosed \"unit\"",
            ),
            (
                "BO_ 291 M: 8 ECU\n SG_ A : 0|8@1+ (1,0) [0|0\n",
                "bad.dbc:2: signal A: unclosed [min|max]",
            ),
        ];
        for (text, want) in cases {
            assert_eq!(Dbc::parse("bad.dbc", text).unwrap_err().to_string(), want);
        }
        // Whatever the bytes, parsing answers with a value, never a panic.
        let mut seed = 7u64;
        for _ in 0..3000 {
            let mut line = String::from("BO_ 291 M: 8 ECU\n SG_ A : 0|8@1+ (1,0) [0|1] \"V\" X\n");
            for _ in 0..4 {
                seed = seed
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let at = (seed >> 33) as usize % line.len();
                let junk = [
                    '"', '(', ')', '[', ']', '|', '@', ':', ' ', '-', '9', 'x', '\n',
                ][(seed >> 20) as usize % 13];
                if line.is_char_boundary(at) {
                    line.insert(at, junk);
                }
            }
            let _ = Dbc::parse("fuzz.dbc", &line);
        }
        let missing = Dbc::load(std::path::Path::new("/nonexistent/car.dbc")).unwrap_err();
        assert!(
            missing
                .to_string()
                .starts_with("/nonexistent/car.dbc:0: cannot read"),
            "{missing}"
        );
    }
}
