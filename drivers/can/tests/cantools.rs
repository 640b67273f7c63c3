//! hwgw's DBC reader and decoding against cantools, an independent implementation: random
//! DBC files written by cantools' own DBC writer (Windows-1252, as CANdb++ writes them:
//! repeated signal names, Intel and Motorola, signed, factors and offsets, IEEE floats,
//! 64-bit values, simple multiplexing, value tables, comments, cycle times, CAN FD), random
//! frames decoded by cantools, and every value read back through the card's devices equal
//! to cantools' to the bit. cantools is installed from PyPI, pinned (`testkit::pypi`).
//!
//! `CANTOOLS_SEED` picks another set of files (default 1), `CANTOOLS_FILES` how many
//! (default 60).

#![allow(
    clippy::unwrap_used,
    reason = "test code: a failed unwrap is a failed test"
)]

use device_interface::time::{Clock, SimClock, Timestamp};
use device_interface::{AnalogIn, AnalogOut, DeviceError, DigitalIn, DigitalOut};
use driver_can::card::{CanCard, Received};
use driver_can::map::{CanConfig, CanMap, MappedFrame, SignalRole};
use serde::Deserialize;
use std::collections::{BTreeMap, HashMap};
use std::process::Command;
use std::sync::Arc;
use std::time::Duration;

/// What the generator wrote of one file.
#[derive(Deserialize)]
struct File {
    file: String,
    messages: Vec<Message>,
}

#[derive(Deserialize)]
struct Message {
    name: String,
    id: u32,
    extended: bool,
    fd: bool,
    cycle_ms: Option<u64>,
    signals: BTreeMap<String, SignalInfo>,
    frames: Vec<Frame>,
    /// The same values as cantools encodes them (messages without multiplexing, finite
    /// values).
    sent: Vec<Frame>,
}

#[derive(Deserialize)]
struct SignalInfo {
    comment: Option<String>,
    choices: BTreeMap<String, String>,
}

#[derive(Deserialize)]
struct Frame {
    data: String,
    /// Signal name → [raw, scaled], each as Python's repr.
    values: BTreeMap<String, [String; 2]>,
}

fn env_or(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// The generator's files and expectations, in a fresh directory of its own (`name`).
fn generate(name: &str) -> (std::path::PathBuf, Vec<File>) {
    let seed = env_or("CANTOOLS_SEED", 1);
    let files = env_or("CANTOOLS_FILES", 60);
    let dir = std::env::temp_dir().join(format!("hwgw-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let path = testkit::pypi::cantools().unwrap();
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/cantools_random.py");
    let out = Command::new(testkit::peers::PYTHON)
        .env("PYTHONPATH", &path)
        .arg(script)
        .arg(&dir)
        .args([seed.to_string(), files.to_string(), "20".to_string()])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "the cantools generator failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let files = serde_json::from_slice(&std::fs::read(dir.join("expected.json")).unwrap());
    (dir, files.unwrap())
}

/// A deployment mapping every message of `file` as received, or every one cantools
/// encoded values of as sent.
fn deployment(file: &File, tx: bool) -> CanConfig {
    let mut toml = format!("interface = \"vcan0\"\ndbc = \"{}\"\n", file.file);
    for m in &file.messages {
        if !tx {
            toml.push_str(&format!("[[rx]]\nmessage = \"{}\"\n", m.name));
        } else if !m.sent.is_empty() {
            toml.push_str(&format!("[[tx]]\nmessage = \"{}\"\n", m.name));
        }
    }
    toml::from_str(&toml).unwrap()
}

/// A card with `file`'s deployment ([`deployment`]), its link up; `None` (said in `bad`)
/// when hwgw refuses the file.
fn card(
    file: &File,
    tx: bool,
    dir: &std::path::Path,
    clock: &Arc<SimClock>,
    bad: &mut Vec<String>,
) -> Option<Arc<CanCard>> {
    match CanMap::new(&deployment(file, tx), dir) {
        Ok(map) => {
            let card = CanCard::new(map, clock.clone());
            card.set_link(true, None);
            Some(card)
        }
        Err(e) => {
            bad.push(format!("{}: refused: {e}", file.file));
            None
        }
    }
}

fn bytes(hex: &str) -> Vec<u8> {
    (0..hex.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).unwrap())
        .collect()
}

/// Comments compared with their white space folded (hwgw folds line breaks for port docs).
fn folded(s: &str) -> String {
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// Checks the mapped frame's names, cycle, comments and value tables against cantools'.
fn check_layout(
    file: &str,
    m: &Message,
    frame: &MappedFrame,
    shared: &HashMap<&str, usize>,
    bad: &mut Vec<String>,
) {
    let at = format!("{file} {}", m.name);
    // cantools writes no VFrameFormat and reads a message as CAN FD only by that
    // attribute; a message longer than 8 bytes can only be one.
    let fd = m.fd || frame.length > 8;
    if (frame.id, frame.extended, frame.fd) != (m.id, m.extended, fd) {
        bad.push(format!(
            "{at}: id {:#x} extended {} fd {}, cantools {:#x} {} {}",
            frame.id, frame.extended, frame.fd, m.id, m.extended, fd
        ));
    }
    // A GenMsgCycleTime under 1 ms is no cycle; cantools writes whole milliseconds.
    let cycle = m.cycle_ms.filter(|&c| c > 0).map(Duration::from_millis);
    if frame.cycle != cycle {
        bad.push(format!("{at}: cycle {:?}, cantools {cycle:?}", frame.cycle));
    }
    for s in &frame.signals {
        let Some(info) = m.signals.get(&s.name) else {
            bad.push(format!(
                "{at}: signal {} is not in cantools' message",
                s.name
            ));
            continue;
        };
        let port = if shared[s.name.as_str()] > 1 {
            format!("{}__{}", m.name, s.name)
        } else {
            s.name.clone()
        };
        if s.port != port {
            bad.push(format!(
                "{at}.{}: port {:?}, expected {port:?}",
                s.name, s.port
            ));
        }
        if s.comment.as_deref().map(folded) != info.comment.as_deref().map(folded) {
            bad.push(format!(
                "{at}.{}: comment {:?}, cantools {:?}",
                s.name, s.comment, info.comment
            ));
        }
        let values: BTreeMap<String, String> = s
            .values
            .iter()
            .map(|(k, v)| (k.to_string(), v.clone()))
            .collect();
        if values != info.choices {
            bad.push(format!(
                "{at}.{}: values {values:?}, cantools {:?}",
                s.name, info.choices
            ));
        }
    }
    if frame.signals.len() != m.signals.len() {
        bad.push(format!(
            "{at}: {} signals mapped, cantools has {}",
            frame.signals.len(),
            m.signals.len()
        ));
    }
}

/// Feeds each of cantools' frames to the card and compares every value cantools decoded;
/// returns how many were compared.
fn check_values(
    file: &str,
    m: &Message,
    frame: &MappedFrame,
    card: &CanCard,
    clock: &SimClock,
    bad: &mut Vec<String>,
) -> usize {
    let mut compared = 0;
    for f in &m.frames {
        let data = bytes(&f.data);
        let at = format!("{file} {} #{}", m.name, f.data);
        match card.receive(m.id, m.extended, frame.fd, &data, clock.now()) {
            Received::Decoded(_) => {}
            other => {
                bad.push(format!("{at}: not decoded ({other:?})"));
                continue;
            }
        }
        for (name, [raw, value]) in &f.values {
            let Some(s) = frame.signals.iter().find(|s| &s.name == name) else {
                bad.push(format!(
                    "{at}: cantools decoded {name}, hwgw has no such signal"
                ));
                continue;
            };
            let expected: f64 = value.parse().unwrap();
            let got = match s.role {
                SignalRole::Digital => {
                    let raw: i64 = raw.parse().unwrap();
                    let bit = card.read_bit(s.channel);
                    (!matches!(bit, Ok(b) if b == (raw != 0)))
                        .then(|| format!("{bit:?}, cantools raw {raw}"))
                }
                _ => match card.read(s.channel) {
                    Ok(v) if v.to_bits() == expected.to_bits() => None,
                    Err(DeviceError::NotANumber { .. }) if !expected.is_finite() => None,
                    other => Some(format!("{other:?}, cantools {value} (raw {raw})")),
                },
            };
            compared += 1;
            if let Some(g) = got {
                bad.push(format!("{at} {name}: {g}"));
            }
        }
    }
    compared
}

/// Writes each of cantools' encoded value sets through the card's output devices and
/// compares the frame the card composes with cantools' bytes; returns how many frames.
fn check_sent(
    file: &str,
    m: &Message,
    f: usize,
    frame: &MappedFrame,
    card: &CanCard,
    bad: &mut Vec<String>,
) -> usize {
    for sent in &m.sent {
        let at = format!("{file} {} {:?}", m.name, sent.values);
        for (name, [raw, value]) in &sent.values {
            let Some(s) = frame.signals.iter().find(|s| &s.name == name) else {
                bad.push(format!("{at}: hwgw has no signal {name}"));
                continue;
            };
            let written = match s.role {
                SignalRole::Digital => card.set_bit(s.channel, raw != "0"),
                _ => card.write(s.channel, value.parse().unwrap()),
            };
            if let Err(e) = written {
                bad.push(format!("{at}: {name} = {value} refused: {e}"));
            }
        }
        let mut buf = [0u8; 64];
        let n = card.compose(f, &mut buf);
        let got: String = buf[..n].iter().map(|b| format!("{b:02x}")).collect();
        if got != sent.data {
            bad.push(format!("{at}: sent {got}, cantools encodes {}", sent.data));
        }
    }
    m.sent.len()
}

#[test]
fn random_dbc_messages_are_sent_as_cantools_encodes_them() {
    let (dir, files) = generate("cantools-tx");
    let clock = Arc::new(SimClock::new(Timestamp::from_nanos(1_000_000)));
    let (mut bad, mut frames) = (Vec::new(), 0);
    for file in &files {
        let Some(card) = card(file, true, &dir, &clock, &mut bad) else {
            continue;
        };
        for m in file.messages.iter().filter(|m| !m.sent.is_empty()) {
            let tx = card.map().tx();
            let Some(f) = tx.iter().position(|f| f.name == m.name) else {
                bad.push(format!("{} {}: not mapped", file.file, m.name));
                continue;
            };
            frames += check_sent(&file.file, m, f, &tx[f], &card, &mut bad);
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
    eprintln!("cantools: {frames} frames sent, {} differences", bad.len());
    assert!(frames > 1000, "too few frames compared: {frames}");
    assert!(
        bad.is_empty(),
        "{} differences from cantools, the first:\n{}",
        bad.len(),
        bad.iter().take(25).cloned().collect::<Vec<_>>().join("\n")
    );
}

#[test]
fn random_dbc_files_read_and_decode_as_cantools_does() {
    let seed = env_or("CANTOOLS_SEED", 1);
    let (dir, files) = generate("cantools-rx");
    let clock = Arc::new(SimClock::new(Timestamp::from_nanos(1_000_000)));
    let (mut bad, mut values, mut messages) = (Vec::new(), 0, 0);
    for file in &files {
        let Some(card) = card(file, false, &dir, &clock, &mut bad) else {
            continue;
        };
        let mut shared: HashMap<&str, usize> = HashMap::new();
        for m in &file.messages {
            for name in m.signals.keys() {
                *shared.entry(name).or_default() += 1;
            }
        }
        for m in &file.messages {
            let Some(frame) = card.map().rx().iter().find(|f| f.name == m.name) else {
                bad.push(format!("{} {}: not mapped", file.file, m.name));
                continue;
            };
            check_layout(&file.file, m, frame, &shared, &mut bad);
            values += check_values(&file.file, m, frame, &card, &clock, &mut bad);
            messages += 1;
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
    eprintln!(
        "cantools: {} files, {messages} messages, {values} values compared, {} differences",
        files.len(),
        bad.len()
    );
    assert!(values > 1000, "too few values compared: {values}");
    assert!(
        bad.is_empty(),
        "{} differences from cantools (seed {seed}), the first:\n{}",
        bad.len(),
        bad.iter().take(25).cloned().collect::<Vec<_>>().join("\n")
    );
}
