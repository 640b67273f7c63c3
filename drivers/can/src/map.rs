//! What a CAN card maps: frames to receive and send, and their signals as device channels.
//!
//! A card's `[card.socketcan]` section names the interface, optionally a DBC file, and
//! lists `rx` and `tx` frames. A frame is either a DBC message (`message = "Name"`: id,
//! length and every signal come from the file) or defined inline (`id`, `length`,
//! `[[…signal]]` tables with the DBC model: start bit, length, byte order, signedness,
//! factor, offset, min, max, unit). Signal tables on a DBC message pick a role or an
//! initial value for one of its signals by name.
//!
//! Signals become channels in file order: received analog signals are AnalogIn channels
//! 0, 1, …; received 1-bit signals DigitalIn bits (an n-bit `as = "digital"` signal takes
//! n bits, least significant first); `as = "encoder"` signals are position counters
//! (turns counted on wrap); sent signals are AnalogOut channels and DigitalOut bits.
//!
//! ```
//! use driver_can::map::{CanConfig, CanMap};
//!
//! let config: CanConfig = toml::from_str(r#"
//!     interface = "vcan0"
//!     [[rx]]
//!     id = 0x100
//!     cycle_ms = 10
//!     signal = [
//!         { name = "speed", start = 0, length = 16, factor = 0.01, unit = "m/s" },
//!         { name = "brake", start = 16, length = 1 },
//!     ]
//!     [[tx]]
//!     id = 0x200
//!     length = 2
//!     cycle_ms = 20
//!     signal = [{ name = "torque", start = 0, length = 16, signed = true, factor = 0.1 }]
//! "#)?;
//! let map = CanMap::new(&config, std::path::Path::new("."))?;
//! assert_eq!(map.counts(), [1, 1, 1, 0]); // AI, AO, DI, DO
//! assert_eq!(map.rx()[0].timeout, Some(std::time::Duration::from_millis(30)));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use crate::dbc::{Dbc, DbcError};
use crate::signal::{ByteOrder, Signal, SignalError};
use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// A card's `[card.socketcan]` section.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CanConfig {
    /// The network interface (`can0`, `vcan0`).
    pub interface: String,
    /// A DBC file to take messages from (relative to the deployment file's directory).
    #[serde(default)]
    pub dbc: Option<PathBuf>,
    /// A received frame's channels go stale after this many missed cycles (default 3).
    #[serde(default = "default_stale_cycles")]
    pub stale_after_cycles: u32,
    /// How often the link state is checked while nothing else happens, in ms (default 100).
    #[serde(default = "default_link_check")]
    pub link_check_ms: f64,
    /// Frames to receive.
    #[serde(default)]
    pub rx: Vec<FrameConfig>,
    /// Frames to send.
    #[serde(default)]
    pub tx: Vec<FrameConfig>,
}

fn default_stale_cycles() -> u32 {
    3
}

fn default_link_check() -> f64 {
    100.0
}

/// One `[[rx]]` or `[[tx]]` frame.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameConfig {
    /// A DBC message by name (then id, length and signals come from the file).
    #[serde(default)]
    pub message: Option<String>,
    /// The CAN id (inline frames).
    #[serde(default)]
    pub id: Option<u32>,
    /// A 29-bit id (inline frames).
    #[serde(default)]
    pub extended: bool,
    /// Payload bytes (inline frames; default 8).
    #[serde(default)]
    pub length: Option<usize>,
    /// A CAN FD frame.
    #[serde(default)]
    pub fd: bool,
    /// rx: the sender's cycle (for staleness); tx: the send period.
    #[serde(default)]
    pub cycle_ms: Option<f64>,
    /// rx: stale after this long without the frame (overrides `stale_after_cycles`).
    #[serde(default)]
    pub timeout_ms: Option<f64>,
    /// tx: send as soon as an output changes (default: only when there is no cycle).
    #[serde(default)]
    pub on_change: Option<bool>,
    /// Inline signals, or settings for DBC signals by name.
    #[serde(default)]
    pub signal: Vec<SignalConfig>,
}

/// What a signal is as a device channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SignalRole {
    /// An analog channel (the default for signals longer than one bit).
    Analog,
    /// Digital bits (the default for 1-bit signals).
    Digital,
    /// A position counter (received signals only).
    Encoder,
}

/// One signal table.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SignalConfig {
    /// Its name (a DBC signal's name on DBC messages).
    pub name: String,
    /// DBC start bit.
    #[serde(default)]
    pub start: Option<u32>,
    /// Length in bits.
    #[serde(default)]
    pub length: Option<u32>,
    /// Byte order (default Intel).
    #[serde(default)]
    pub byte_order: Option<ByteOrder>,
    /// Signed (default false).
    #[serde(default)]
    pub signed: Option<bool>,
    /// `physical = raw * factor + offset` (default 1).
    #[serde(default)]
    pub factor: Option<f64>,
    /// Default 0.
    #[serde(default)]
    pub offset: Option<f64>,
    /// Physical minimum (with `max`; default none).
    #[serde(default)]
    pub min: Option<f64>,
    /// Physical maximum.
    #[serde(default)]
    pub max: Option<f64>,
    /// Unit.
    #[serde(default)]
    pub unit: Option<String>,
    /// The channel kind.
    #[serde(default, rename = "as")]
    pub role: Option<SignalRole>,
    /// Encoders: counts per turn.
    #[serde(default)]
    pub resolution: Option<i64>,
    /// Encoders: counting direction (default up).
    #[serde(default)]
    pub upcounting: Option<bool>,
    /// tx: the physical value sent before the first write (default: raw 0).
    #[serde(default)]
    pub initial: Option<f64>,
}

/// Why a CAN section was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum MapError {
    /// The DBC file.
    #[error(transparent)]
    Dbc(#[from] DbcError),
    /// A setting, named by its key path inside the section.
    #[error("{path}: {message}")]
    Setting {
        /// Key path, e.g. `rx[1].signal[0]`.
        path: String,
        /// What is wrong.
        message: String,
    },
}

fn bad(path: impl Into<String>, message: impl Into<String>) -> MapError {
    MapError::Setting {
        path: path.into(),
        message: message.into(),
    }
}

/// A mapped signal.
#[derive(Debug, Clone)]
pub struct MappedSignal {
    /// Its name.
    pub name: String,
    /// Layout and scale (limits applied).
    pub signal: Signal,
    /// Its kind.
    pub role: SignalRole,
    /// Its first channel (analog), bit (digital) or encoder index.
    pub channel: u32,
    /// Encoders: counts per turn and direction.
    pub encoder: Option<(i64, bool)>,
    /// tx: the raw value before the first write.
    pub initial_raw: i64,
}

impl MappedSignal {
    /// Channels (analog, encoder) or bits (digital) it takes.
    pub fn width(&self) -> u32 {
        match self.role {
            SignalRole::Digital => self.signal.layout().1,
            _ => 1,
        }
    }
}

/// A mapped frame.
#[derive(Debug, Clone)]
pub struct MappedFrame {
    /// The DBC message name, or the id in hex.
    pub name: String,
    /// The id (without flags).
    pub id: u32,
    /// 29-bit id.
    pub extended: bool,
    /// Payload bytes.
    pub length: usize,
    /// A CAN FD frame.
    pub fd: bool,
    /// rx: expected cycle; tx: send period.
    pub cycle: Option<Duration>,
    /// rx: stale after this long without the frame.
    pub timeout: Option<Duration>,
    /// tx: sent when an output changes.
    pub on_change: bool,
    /// Its signals.
    pub signals: Vec<MappedSignal>,
}

/// A card's frames and channels.
#[derive(Debug, Clone)]
pub struct CanMap {
    interface: String,
    link_check: Duration,
    rx: Vec<MappedFrame>,
    tx: Vec<MappedFrame>,
    counts: [u32; 4],
    encoders: u32,
}

/// The payload lengths a CAN FD frame can have.
const FD_LENGTHS: [usize; 16] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64];

fn millis(path: &str, ms: f64) -> Result<Duration, MapError> {
    if ms.is_finite() && ms > 0.0 && ms < 1e9 {
        Ok(Duration::from_secs_f64(ms / 1000.0))
    } else {
        Err(bad(path, format!("{ms} ms: expected a time above 0")))
    }
}

impl CanMap {
    /// Resolves `config`; a relative DBC path is taken from `base` (the deployment file's
    /// directory).
    pub fn new(config: &CanConfig, base: &Path) -> Result<CanMap, MapError> {
        if config.interface.is_empty() || config.interface.len() > 15 {
            return Err(bad(
                "interface",
                format!(
                    "{:?}: expected a network interface name (1 to 15 characters)",
                    config.interface
                ),
            ));
        }
        if config.stale_after_cycles == 0 {
            return Err(bad("stale_after_cycles", "expected 1 or more"));
        }
        let dbc = match &config.dbc {
            Some(p) => Some(Dbc::load(&base.join(p))?),
            None => None,
        };
        let mut next = [0u32; 5]; // AI, AO, DI, DO, encoders
        let mut frames = [Vec::new(), Vec::new()];
        for (dir, list) in [("rx", &config.rx), ("tx", &config.tx)] {
            let tx = dir == "tx";
            for (i, f) in list.iter().enumerate() {
                let path = format!("{dir}[{i}]");
                let frame = frame(config, dbc.as_ref(), f, &path, tx, &mut next)?;
                let same = if tx { &frames[1] } else { &frames[0] };
                if let Some(j) = same
                    .iter()
                    .position(|o: &MappedFrame| o.id == frame.id && o.extended == frame.extended)
                {
                    return Err(bad(
                        &path,
                        format!("id {:#x} is already mapped as {dir}[{j}]", frame.id),
                    ));
                }
                frames[usize::from(tx)].push(frame);
            }
        }
        let [rx, tx] = frames;
        Ok(CanMap {
            interface: config.interface.clone(),
            link_check: millis("link_check_ms", config.link_check_ms)?,
            rx,
            tx,
            counts: [next[0], next[1], next[2], next[3]],
            encoders: next[4],
        })
    }

    /// The network interface.
    pub fn interface(&self) -> &str {
        &self.interface
    }

    /// How often the link is checked.
    pub fn link_check(&self) -> Duration {
        self.link_check
    }

    /// Received frames.
    pub fn rx(&self) -> &[MappedFrame] {
        &self.rx
    }

    /// The most signals any received frame has.
    pub fn widest_rx(&self) -> usize {
        self.rx.iter().map(|f| f.signals.len()).max().unwrap_or(0)
    }

    /// Sent frames.
    pub fn tx(&self) -> &[MappedFrame] {
        &self.tx
    }

    /// Channel counts: analog in, analog out, digital in bits, digital out bits.
    pub fn counts(&self) -> [u32; 4] {
        self.counts
    }

    /// Number of encoders.
    pub fn encoder_count(&self) -> u32 {
        self.encoders
    }

    /// Encoder signals, in encoder order.
    pub fn encoders(&self) -> impl Iterator<Item = &MappedSignal> {
        self.rx
            .iter()
            .flat_map(|f| &f.signals)
            .filter(|s| s.role == SignalRole::Encoder)
    }
}

fn frame(
    config: &CanConfig,
    dbc: Option<&Dbc>,
    f: &FrameConfig,
    path: &str,
    tx: bool,
    next: &mut [u32; 5],
) -> Result<MappedFrame, MapError> {
    // The DBC message's layout, or the inline one.
    let (name, id, extended, length, base) = match &f.message {
        Some(m) => {
            let Some(dbc) = dbc else {
                return Err(bad(
                    format!("{path}.message"),
                    format!("message {m:?} needs a DBC file (set dbc = \"….dbc\")"),
                ));
            };
            let Some(msg) = dbc.message(m) else {
                let names: Vec<&str> = dbc.messages.iter().map(|m| m.name.as_str()).collect();
                return Err(bad(
                    format!("{path}.message"),
                    format!(
                        "the DBC file has no message {m:?} (it has: {})",
                        names.join(", ")
                    ),
                ));
            };
            if f.id.is_some() || f.length.is_some() || f.extended {
                return Err(bad(
                    path,
                    "id, extended and length come from the DBC message; remove them",
                ));
            }
            (
                msg.name.clone(),
                msg.id,
                msg.extended,
                msg.length,
                Some(msg),
            )
        }
        None => {
            let Some(id) = f.id else {
                return Err(bad(path, "a frame needs message = \"…\" (DBC) or id = …"));
            };
            (
                format!("{id:#x}"),
                id,
                f.extended,
                f.length.unwrap_or(8),
                None,
            )
        }
    };
    let max_id = if extended { 0x1FFF_FFFF } else { 0x7FF };
    if id > max_id {
        return Err(bad(
            format!("{path}.id"),
            format!(
                "{id:#x} does not fit {} id (largest {max_id:#x})",
                if extended { "a 29-bit" } else { "an 11-bit" }
            ),
        ));
    }
    if f.fd && !FD_LENGTHS.contains(&length) || !f.fd && length > 8 {
        return Err(bad(
            format!("{path}.length"),
            if f.fd {
                format!("{length} bytes: a CAN FD frame has 0-8, 12, 16, 20, 24, 32, 48 or 64")
            } else {
                format!("{length} bytes: a classic frame has 0 to 8 (set fd = true for more)")
            },
        ));
    }
    let cycle = f
        .cycle_ms
        .map(|ms| millis(&format!("{path}.cycle_ms"), ms))
        .transpose()?;
    let timeout = match (f.timeout_ms, cycle) {
        (_, _) if tx && f.timeout_ms.is_some() => {
            return Err(bad(
                format!("{path}.timeout_ms"),
                "only received frames time out",
            ));
        }
        (Some(ms), _) => Some(millis(&format!("{path}.timeout_ms"), ms)?),
        (None, Some(c)) => Some(c * config.stale_after_cycles),
        (None, None) => None,
    };
    let on_change = match (tx, f.on_change) {
        (false, Some(_)) => {
            return Err(bad(
                format!("{path}.on_change"),
                "on_change is for sent frames",
            ));
        }
        (false, None) => false,
        (true, Some(false)) if cycle.is_none() => {
            return Err(bad(
                path,
                "with no cycle_ms and on_change = false the frame would never be sent",
            ));
        }
        (true, Some(v)) => v,
        (true, None) => cycle.is_none(),
    };

    // Signals: the DBC message's, each possibly adjusted by a table; or the tables alone.
    let mut signals = Vec::new();
    let mut used = vec![false; f.signal.len()];
    // (name, the DBC signal with its [min|max], the index of its table)
    type Entry = (String, Option<(Signal, f64, f64)>, Option<usize>);
    let list: Vec<Entry> = match base {
        Some(msg) => msg
            .signals
            .iter()
            .map(|s| {
                let table = f.signal.iter().position(|t| t.name == s.name);
                (
                    s.name.clone(),
                    Some((s.signal.clone(), s.min, s.max)),
                    table,
                )
            })
            .collect(),
        None => (0..f.signal.len())
            .map(|k| (f.signal[k].name.clone(), None, Some(k)))
            .collect(),
    };
    for (name, from_dbc, table) in list {
        let spath = match table {
            Some(k) => format!("{path}.signal[{k}]"),
            None => format!("{path} ({name})"),
        };
        let t = table.map(|k| {
            used[k] = true;
            &f.signal[k]
        });
        let here = |e: SignalError| bad(format!("{spath} ({name})"), e.to_string());
        let signal = match (from_dbc, t) {
            (Some((s, min, max)), t) => {
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
                        format!("{spath} ({name})"),
                        "the layout and scale of a DBC signal come from the DBC file; \
                         only as, resolution, upcounting and initial can be set here",
                    ));
                }
                s.with_limits(min, max).map_err(here)?
            }
            (None, Some(t)) => {
                let (Some(start), Some(bits)) = (t.start, t.length) else {
                    return Err(bad(
                        format!("{spath} ({name})"),
                        "an inline signal needs start and length",
                    ));
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
                    _ => {
                        return Err(bad(
                            format!("{spath} ({name})"),
                            "give both min and max, or neither",
                        ));
                    }
                };
                if s.bytes_needed() > length {
                    return Err(bad(
                        format!("{spath} ({name})"),
                        format!(
                            "it reaches byte {} but the frame has {length} bytes",
                            s.bytes_needed()
                        ),
                    ));
                }
                s
            }
            (None, None) => {
                return Err(bad(
                    spath,
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
                    format!("{spath} ({name})"),
                    "an encoder is an input: map it in an rx frame",
                ));
            }
            SignalRole::Encoder => {
                let Some(resolution) = t.and_then(|t| t.resolution) else {
                    return Err(bad(
                        format!("{spath} ({name})"),
                        "an encoder needs resolution (counts per turn)",
                    ));
                };
                Some((resolution, t.and_then(|t| t.upcounting).unwrap_or(true)))
            }
            _ => {
                if t.is_some_and(|t| t.resolution.is_some() || t.upcounting.is_some()) {
                    return Err(bad(
                        format!("{spath} ({name})"),
                        "resolution and upcounting are for as = \"encoder\"",
                    ));
                }
                None
            }
        };
        let initial = t.and_then(|t| t.initial);
        let initial_raw = match initial {
            _ if !tx && initial.is_some() => {
                return Err(bad(
                    format!("{spath} ({name})"),
                    "initial is for sent signals",
                ));
            }
            Some(v) => signal.scale().to_raw(v).ok_or_else(|| {
                bad(
                    format!("{spath} ({name})"),
                    format!("initial {v} is outside the signal's range"),
                )
            })?,
            None => signal.scale().raw_range().clamp(0),
        };
        // tx frames are packed from these signals: overlapping ones would clobber
        // each other.
        if tx
            && let Some(o) = signals
                .iter()
                .find(|o: &&MappedSignal| o.signal.overlaps(&signal))
        {
            return Err(bad(
                format!("{spath} ({name})"),
                format!("it overlaps signal {} in a sent frame", o.name),
            ));
        }
        let slot = match (role, tx) {
            (SignalRole::Analog, false) => 0,
            (SignalRole::Analog, true) => 1,
            (SignalRole::Digital, false) => 2,
            (SignalRole::Digital, true) => 3,
            (SignalRole::Encoder, _) => 4,
        };
        let mapped = MappedSignal {
            name,
            signal,
            role,
            channel: next[slot],
            encoder,
            initial_raw,
        };
        next[slot] += mapped.width();
        signals.push(mapped);
    }
    if let Some(k) = used.iter().position(|u| !u) {
        return Err(bad(
            format!("{path}.signal[{k}]"),
            format!("message {name} has no signal {:?}", f.signal[k].name),
        ));
    }
    Ok(MappedFrame {
        name,
        id,
        extended,
        length,
        fd: f.fd,
        cycle,
        timeout,
        on_change,
        signals,
    })
}
