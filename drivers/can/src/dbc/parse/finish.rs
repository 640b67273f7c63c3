//! The messages once every statement is read: float types, comments, value tables, cycle
//! times and extended multiplexing put on the messages and signals they name.

use super::{Extras, Parser, Raw};
use crate::dbc::Message;
use crate::signal::ValueKind;
use std::collections::HashMap;
use std::time::Duration;

/// The messages with what the later statements said about them. Messages and signals are
/// found through maps (a file of many messages and statements is read in linear time).
pub(super) fn finish(raws: Vec<Raw>, x: Extras, p: &Parser<'_>) -> Vec<Message> {
    let mut out: Vec<(u64, Message)> = raws
        .into_iter()
        .filter(|r| !r.pseudo)
        .map(|r| (r.id, r.message))
        .collect();
    // The first message of each id, and each of its signals by name.
    let mut by_id: HashMap<u64, usize> = HashMap::new();
    for (k, (id, _)) in out.iter().enumerate() {
        by_id.entry(*id).or_insert(k);
    }
    let mut by_name: HashMap<(u64, String), (usize, usize)> = HashMap::new();
    for (&id, &m) in &by_id {
        for (k, s) in out[m].1.signals.iter().enumerate() {
            by_name.insert((id, s.name.clone()), (m, k));
        }
    }
    for (key, kind, line) in x.kinds {
        let Some(&(m, k)) = by_name.get(&key) else {
            continue;
        };
        let kind = match kind {
            1 => ValueKind::Float32,
            2 => ValueKind::Float64,
            _ => ValueKind::Integer,
        };
        let m = &mut out[m].1;
        match m.signals[k].signal.clone().with_kind(kind) {
            Ok(sig) => m.signals[k].signal = sig,
            Err(e) => m.problems.push(p.error(line, Some(&key.1), e.to_string())),
        }
    }
    for (key, text) in x.signal_comments {
        if let Some(&(m, k)) = by_name.get(&key) {
            out[m].1.signals[k].comment = Some(text);
        }
    }
    for (id, text) in x.message_comments {
        if let Some(&m) = by_id.get(&id) {
            out[m].1.comment = Some(text);
        }
    }
    for (key, list) in x.values {
        if let Some(&(m, k)) = by_name.get(&key) {
            out[m].1.signals[k].values = list;
        }
    }
    // GenMsgCycleTime is whole ms; 0 (CANdb++'s default) and anything under 1 ms is none.
    let cycle = |ms: f64| {
        (1.0..1e9)
            .contains(&ms)
            .then(|| Duration::from_secs_f64(ms / 1000.0))
    };
    for (_, m) in &mut out {
        m.cycle = x.default_cycle.and_then(cycle);
    }
    for (id, ms) in x.cycles {
        if let Some(&m) = by_id.get(&id) {
            out[m].1.cycle = cycle(ms);
        }
    }
    // VFrameFormat: a message is CAN FD when its format's name ends in _FD (Vector's
    // StandardCAN_FD, ExtendedCAN_FD); without the enum's names, its indices 14 and 15.
    let is_fd = |n: u64| match x.frame_format_names.get(n as usize) {
        Some(name) => name.ends_with("_FD"),
        None => x.frame_format_names.is_empty() && matches!(n, 14 | 15),
    };
    let default_fd = x
        .frame_format_default
        .as_deref()
        .is_some_and(|d| d.ends_with("_FD"));
    for (_, m) in &mut out {
        m.fd = default_fd || m.length > 8;
    }
    for (id, n) in x.frame_formats {
        if let Some(&m) = by_id.get(&id) {
            out[m].1.fd = is_fd(n) || out[m].1.length > 8;
        }
    }
    for id in x.extended_mux {
        if let Some(&m) = by_id.get(&id) {
            out[m].1.extended_mux = true;
        }
    }
    out.into_iter().map(|(_, m)| m).collect()
}
