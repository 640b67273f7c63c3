//! One signal of a mapped frame: its layout and scale from the DBC file or a TOML table,
//! its role and channel, and its port name made unique across the card.

use super::{MapError, MappedFrame, MappedSignal, SignalConfig, SignalRole, bad};
use crate::dbc::{DbcSignal, Mux};
use crate::signal::{ByteOrder, Signal, SignalError};

/// The first names of a list, for an error that says what exists: at most 20, then how
/// many more (a DBC file may have thousands).
pub(super) fn some_names<'a>(names: impl Iterator<Item = &'a str>) -> String {
    const SHOWN: usize = 20;
    let mut shown = Vec::new();
    let mut more = 0usize;
    for n in names {
        if shown.len() < SHOWN {
            shown.push(n);
        } else {
            more += 1;
        }
    }
    match more {
        0 => shown.join(", "),
        n => format!("{} and {n} more", shown.join(", ")),
    }
}

/// What joins a message's name and a signal's in the port name of a signal whose name
/// another mapped message has too (`EngineData__Counter`): port names cannot hold dots.
pub const QUALIFIER: &str = "__";

/// Gives every signal its port name: its own name, unique across the card's mapped
/// messages, else `Message__Signal` for each signal whose name is repeated.
pub(super) fn qualify(rx: &mut [MappedFrame], tx: &mut [MappedFrame]) {
    let mut seen: std::collections::HashMap<String, usize> = std::collections::HashMap::new();
    for f in rx.iter().chain(tx.iter()) {
        for s in &f.signals {
            *seen.entry(s.name.clone()).or_default() += 1;
        }
    }
    // A qualified name can still meet another (a signal literally named `A__B`, or one
    // message mapped twice): the later one gets `__2`, `__3`, ….
    let mut taken: std::collections::HashSet<String> = std::collections::HashSet::new();
    for f in rx.iter_mut().chain(tx.iter_mut()) {
        for s in &mut f.signals {
            let base = if seen.get(&s.name).copied().unwrap_or(0) > 1 {
                format!("{}{QUALIFIER}{}", f.name, s.name)
            } else {
                s.name.clone()
            };
            let mut port = base.clone();
            let mut k = 2;
            while taken.contains(&port) {
                port = format!("{base}{QUALIFIER}{k}");
                k += 1;
            }
            taken.insert(port.clone());
            s.port = port;
        }
    }
}

/// Which of the channel counters (AI, AO, DI, DO, encoders) a signal of `role` takes from.
pub(super) fn slot(role: SignalRole, tx: bool) -> usize {
    match (role, tx) {
        (SignalRole::Analog, false) => 0,
        (SignalRole::Analog, true) => 1,
        (SignalRole::Digital, false) => 2,
        (SignalRole::Digital, true) => 3,
        (SignalRole::Encoder, _) => 4,
    }
}

/// One signal of a frame: a DBC signal (`from_dbc`, adjusted by its table `t`), or the
/// table alone (inline); its channel is the next of its kind in `next`.
pub(super) fn map_signal(
    name: &str,
    from_dbc: Option<&DbcSignal>,
    t: Option<&SignalConfig>,
    spath: &str,
    length: usize,
    tx: bool,
    next: &[u32; 5],
) -> Result<MappedSignal, MapError> {
    let here_path = format!("{spath} ({name})");
    let here = |e: SignalError| bad(&here_path, e.to_string());
    let signal = match (from_dbc, t) {
        (Some(d), t) => {
            if let Some(t) = t
                && (t.start.is_some()
                    || t.length.is_some()
                    || t.byte_order.is_some()
                    || t.signed.is_some()
                    || t.factor.is_some()
                    || t.offset.is_some()
                    || t.min.is_some()
                    || t.max.is_some()
                    || t.unit.is_some())
            {
                return Err(bad(
                    &here_path,
                    "the layout and scale of a DBC signal come from the DBC file; \
                     only as, resolution, upcounting and initial can be set here",
                ));
            }
            d.signal.clone().with_limits(d.min, d.max).map_err(here)?
        }
        (None, Some(t)) => inline_signal(t, &here_path, length)?,
        (None, None) => {
            return Err(bad(
                here_path,
                "a signal with neither a DBC definition nor a table",
            ));
        }
    };
    let len = signal.layout().1;
    let role = t.and_then(|t| t.role).unwrap_or(if len == 1 {
        SignalRole::Digital
    } else {
        SignalRole::Analog
    });
    let encoder = match role {
        SignalRole::Encoder if tx => {
            return Err(bad(
                &here_path,
                "an encoder is an input: map it in an rx frame",
            ));
        }
        SignalRole::Encoder => {
            let Some(resolution) = t.and_then(|t| t.resolution) else {
                return Err(bad(
                    &here_path,
                    "an encoder needs resolution (counts per turn)",
                ));
            };
            let up = t.and_then(|t| t.upcounting).unwrap_or(true);
            // The card builds the counter from these: a resolution it refuses is this
            // signal's error, not a channel quietly left out.
            if device_interface::encoder::WrappingCounter::new(resolution, up, signal.layout().1)
                .is_err()
            {
                return Err(bad(
                    &here_path,
                    format!("resolution {resolution}: expected a count of steps per turn, not 0"),
                ));
            }
            Some((resolution, up))
        }
        _ => {
            if t.is_some_and(|t| t.resolution.is_some() || t.upcounting.is_some()) {
                return Err(bad(
                    &here_path,
                    "resolution and upcounting are for as = \"encoder\"",
                ));
            }
            None
        }
    };
    if role != SignalRole::Analog && signal.kind() != crate::signal::ValueKind::Integer {
        return Err(bad(
            &here_path,
            "a float signal is an analog channel (as = \"analog\")",
        ));
    }
    let initial = t.and_then(|t| t.initial);
    let initial_raw = match initial {
        _ if !tx && initial.is_some() => {
            return Err(bad(&here_path, "initial is for sent signals"));
        }
        Some(v) => signal.raw_of(v).ok_or_else(|| {
            bad(
                &here_path,
                format!("initial {v} is outside the signal's range"),
            )
        })?,
        None => match signal.kind() {
            crate::signal::ValueKind::Integer => signal.scale().raw_range().clamp(0),
            // A float's raw is its bits: 0.0's are all zero.
            _ => signal.raw_of(0.0).unwrap_or(0),
        },
    };
    let (mux, multiplexer) = match from_dbc.map(|d| d.mux) {
        Some(Mux::When(k)) => (Some(k), false),
        Some(Mux::Multiplexer) => (None, true),
        _ => (None, false),
    };
    Ok(MappedSignal {
        name: name.to_string(),
        port: name.to_string(),
        channel: next[slot(role, tx)],
        signal,
        role,
        encoder,
        initial_raw,
        mux,
        multiplexer,
        comment: from_dbc.and_then(|d| d.comment.clone()),
        values: from_dbc.map(|d| d.values.clone()).unwrap_or_default(),
    })
}

/// An inline signal from its table.
fn inline_signal(t: &SignalConfig, path: &str, length: usize) -> Result<Signal, MapError> {
    let here = |e: SignalError| bad(path, e.to_string());
    let (Some(start), Some(bits)) = (t.start, t.length) else {
        return Err(bad(path, "an inline signal needs start and length"));
    };
    let s = Signal::new(
        start,
        bits,
        t.byte_order.unwrap_or(ByteOrder::Intel),
        t.signed.unwrap_or(false),
        t.factor.unwrap_or(1.0),
        t.offset.unwrap_or(0.0),
        t.unit.as_deref().unwrap_or(""),
    )
    .map_err(here)?;
    let s = match (t.min, t.max) {
        (None, None) => s,
        (Some(min), Some(max)) => s.with_limits(min, max).map_err(here)?,
        _ => return Err(bad(path, "give both min and max, or neither")),
    };
    if s.bytes_needed() > length {
        return Err(bad(
            path,
            format!(
                "it reaches byte {} but the frame has {length} bytes",
                s.bytes_needed()
            ),
        ));
    }
    Ok(s)
}
