//! Reading ThreadScope's VCD recordings back: this crate's own reading of the file (each
//! signal's name, rising edges and final level, times checked to go forward) and
//! sigrok-cli's edge counter over it, an independent reader (installed when missing).

use crate::peers::{SIGROK, require};
use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

/// One signal of a VCD file as read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Signal {
    /// Its name (`$var wire 1 <id> <name> $end`).
    pub name: String,
    /// Rising edges.
    pub rising: u64,
    /// Its level at the end.
    pub high: bool,
}

/// The 1-bit signals of VCD `text` by identifier; an error names what is malformed (a
/// time going back, an unknown identifier, a value that is not 0 or 1).
pub fn read(text: &str) -> Result<BTreeMap<String, Signal>, String> {
    let mut signals = BTreeMap::new();
    let mut body = false;
    let mut last_time = 0u64;
    for (n, line) in text.lines().enumerate() {
        let at = n + 1;
        let words: Vec<&str> = line.split_whitespace().collect();
        if let ["$var", "wire", "1", id, name, "$end"] = words[..] {
            let s = Signal {
                name: name.to_string(),
                rising: 0,
                high: false,
            };
            signals.insert(id.to_string(), s);
            continue;
        }
        if line.starts_with("$enddefinitions") {
            body = true;
            continue;
        }
        if !body || line.starts_with('$') || line.is_empty() {
            continue;
        }
        if let Some(t) = line.strip_prefix('#') {
            let t: u64 = t
                .parse()
                .map_err(|e| format!("line {at}: time {t:?}: {e}"))?;
            if t < last_time {
                return Err(format!("line {at}: time went back: {t} after {last_time}"));
            }
            last_time = t;
            continue;
        }
        let (level, id) = line.split_at(1);
        let high = match level {
            "1" => true,
            "0" => false,
            _ => return Err(format!("line {at}: not a 1-bit value: {line:?}")),
        };
        let s = signals
            .get_mut(id)
            .ok_or_else(|| format!("line {at}: unknown signal {id:?}"))?;
        if high && !s.high {
            s.rising += 1;
        }
        s.high = high;
    }
    Ok(signals)
}

/// sigrok-cli's count of `signal`'s rising edges in VCD `file` (its `counter` decoder).
pub fn sigrok_rising_edges(file: &Path, signal: &str) -> Result<u64, String> {
    require(&SIGROK).map_err(|e| e.to_string())?;
    let out = Command::new("sigrok-cli")
        // Idle stretches compressed to 10 samples: every edge is kept, and the 1 ns
        // timescale does not make a sample per nanosecond.
        .args(["-I", "vcd:compress=10", "-i"])
        .arg(file)
        .args([
            "-P",
            &format!("counter:data={signal}:data_edge=rising"),
            "-A",
            "counter=edge_count",
        ])
        .output()
        .map_err(|e| format!("sigrok-cli: {e}"))?;
    let text = String::from_utf8_lossy(&out.stdout);
    if !out.status.success() {
        return Err(format!(
            "sigrok-cli failed: {text}{}",
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    // One annotation per edge, counting up: the last is the count (none: no edge).
    match text.lines().last() {
        None => Ok(0),
        Some(l) => l
            .rsplit(' ')
            .next()
            .and_then(|n| n.parse().ok())
            .ok_or_else(|| format!("sigrok-cli said {l:?}")),
    }
}
