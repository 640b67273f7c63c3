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

pub use crate::section::{CanConfig, FrameConfig, SignalConfig, SignalRole};

mod isotp;
mod j1939;
mod signals;

pub use j1939::{J1939Frame, J1939Node};

pub use signals::QUALIFIER;

use crate::dbc::{Dbc, DbcError, DbcSignal, Mux};
use crate::signal::Signal;
use signals::{map_signal, qualify, slot, some_names};
use std::path::Path;
use std::time::Duration;

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
    /// Its channel's port name (and an encoder's device name): its name, or
    /// `Message__Signal` when another mapped message of the card has a signal of the same
    /// name (see [`QUALIFIER`]).
    pub port: String,
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
    /// Present only when its message's multiplexer holds this value (DBC `m<k>`).
    pub mux: Option<u64>,
    /// The multiplexer of its message (DBC `M`).
    pub multiplexer: bool,
    /// Its DBC comment (`CM_`).
    pub comment: Option<String>,
    /// Its DBC value descriptions (`VAL_`): raw value and name.
    pub values: Vec<(i64, String)>,
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
    /// A J1939 parameter group: what it is matched by or sent as.
    pub j1939: Option<J1939Frame>,
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
    isotp: Vec<(String, can_socket::isotp::IsoTp)>,
    /// J1939 is on (a `[j1939]` table), and the node that claims an address, if any.
    j1939: Option<Option<J1939Node>>,
}

/// The payload lengths a CAN FD frame can have.
const FD_LENGTHS: [usize; 16] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64];

/// The shortest cycle or timeout, ms: 100 µs, about one classic frame at 1 Mbit/s (a
/// shorter one would only keep the bus thread busy).
pub const MIN_CYCLE_MS: f64 = 0.1;

/// `ms` as a duration of at least `min` ms and under a million seconds.
fn millis_at_least(path: &str, ms: f64, min: f64) -> Result<Duration, MapError> {
    if ms.is_finite() && ms >= min && ms < 1e9 {
        Ok(Duration::from_secs_f64(ms / 1000.0))
    } else {
        Err(bad(
            path,
            format!("{ms} ms: expected a time from {min} ms to a million seconds"),
        ))
    }
}

/// A cycle or timeout from the TOML.
fn millis(path: &str, ms: f64) -> Result<Duration, MapError> {
    millis_at_least(path, ms, MIN_CYCLE_MS)
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
            Some(p) => Some(Dbc::load(&base.join(p), config.encoding)?),
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
                if let Some((j, what)) = j1939::clash(same, &frame) {
                    return Err(bad(
                        &path,
                        format!("{what} is already mapped as {dir}[{j}]"),
                    ));
                }
                frames[usize::from(tx)].push(frame);
            }
        }
        let [mut rx, mut tx] = frames;
        qualify(&mut rx, &mut tx);
        Ok(CanMap {
            interface: config.interface.clone(),
            link_check: millis_at_least("link_check_ms", config.link_check_ms, 1.0)?,
            rx,
            tx,
            counts: [next[0], next[1], next[2], next[3]],
            encoders: next[4],
            isotp: isotp::resolve(&config.isotp)?,
            j1939: config.j1939.as_ref().map(j1939::node).transpose()?,
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

    /// The ISO-TP address pairs, by name.
    pub fn isotp(&self) -> &[(String, can_socket::isotp::IsoTp)] {
        &self.isotp
    }

    /// Whether the card speaks J1939, and the node that claims an address if it does.
    pub fn j1939(&self) -> Option<Option<J1939Node>> {
        self.j1939
    }

    /// The longest payload of the frames in one direction (rx or tx), at least 64 bytes.
    pub fn longest(&self, tx: bool) -> usize {
        let frames = if tx { &self.tx } else { &self.rx };
        frames.iter().map(|f| f.length).max().unwrap_or(0).max(64)
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
                return Err(bad(
                    format!("{path}.message"),
                    format!(
                        "the DBC file has no message {m:?} (it has: {})",
                        some_names(dbc.messages.iter().map(|m| m.name.as_str()))
                    ),
                ));
            };
            let same: Vec<String> = dbc
                .messages
                .iter()
                .filter(|d| d.name == *m)
                .map(|d| format!("{:#x}", d.id))
                .collect();
            if same.len() > 1 {
                return Err(bad(
                    format!("{path}.message"),
                    format!(
                        "the DBC file has {} messages named {m:?} (ids {}): map it by id and length",
                        same.len(),
                        same.join(", ")
                    ),
                ));
            }
            if f.id.is_some() || f.length.is_some() || f.extended {
                return Err(bad(
                    path,
                    "id, extended and length come from the DBC message; remove them",
                ));
            }
            // What is wrong with a message matters once it is mapped.
            if let Some(e) = msg.problems.first() {
                return Err(bad(format!("{path}.message"), e.to_string()));
            }
            if msg.extended_mux {
                return Err(bad(
                    format!("{path}.message"),
                    format!(
                        "message {m} uses extended multiplexing (SG_MUL_VAL_ or a signal both multiplexed and a multiplexer), which hwgw does not decode"
                    ),
                ));
            }
            let muxed = msg.signals.iter().any(|s| matches!(s.mux, Mux::When(_)));
            if muxed && msg.multiplexer().is_none() {
                return Err(bad(
                    format!("{path}.message"),
                    format!("message {m} has multiplexed signals but no multiplexer (M)"),
                ));
            }
            if muxed && tx {
                return Err(bad(
                    format!("{path}.message"),
                    format!(
                        "message {m} is multiplexed: hwgw receives multiplexed messages, it does not send them"
                    ),
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
    // The TOML's word, else the DBC message's frame format (which a J1939 group's length
    // over 8 does not make FD: the kernel's transport carries it in classic frames).
    let j1939 = j1939::frame(config, f, path, (id, extended, length), tx)?;
    let fd =
        f.fd.unwrap_or(j1939.is_none() && base.is_some_and(|m| m.fd));
    // (A J1939 group's FD and length were checked with the rest of its J1939 side.)
    if j1939.is_none() && (fd && !FD_LENGTHS.contains(&length) || !fd && length > 8) {
        return Err(bad(
            format!("{path}.length"),
            if fd {
                format!("{length} bytes: a CAN FD frame has 0-8, 12, 16, 20, 24, 32, 48 or 64")
            } else {
                format!("{length} bytes: a classic frame has 0 to 8 (set fd = true for more)")
            },
        ));
    }
    // The TOML's cycle, else (for a received frame) the DBC message's GenMsgCycleTime. A
    // sent frame is cyclic only when the TOML says so: a DBC attribute is not reason
    // enough to start writing a bus.
    let cycle = match f.cycle_ms {
        Some(ms) => Some(millis(&format!("{path}.cycle_ms"), ms)?),
        None if tx => None,
        None => base.and_then(|m| m.cycle),
    };
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
    let mut signals: Vec<MappedSignal> = Vec::new();
    let mut used = vec![false; f.signal.len()];
    let list: Vec<(&str, Option<&DbcSignal>, Option<usize>)> = match base {
        Some(msg) => msg
            .signals
            .iter()
            .map(|s| {
                let table = f.signal.iter().position(|t| t.name == s.name);
                (s.name.as_str(), Some(s), table)
            })
            .collect(),
        None => (0..f.signal.len())
            .map(|k| (f.signal[k].name.as_str(), None, Some(k)))
            .collect(),
    };
    for (name, from_dbc, table) in list {
        let spath = match table {
            Some(k) => format!("{path}.signal[{k}]"),
            // A DBC signal the TOML does not list: the message's path (the name is added
            // where a problem is reported).
            None => path.to_string(),
        };
        let t = table.map(|k| {
            used[k] = true;
            &f.signal[k]
        });
        let mapped = map_signal(name, from_dbc, t, &spath, length, tx, next)?;
        // tx frames are packed from these signals: overlapping ones would clobber
        // each other.
        if tx && let Some(o) = signals.iter().find(|o| o.signal.overlaps(&mapped.signal)) {
            return Err(bad(
                format!("{spath} ({name})"),
                format!("it overlaps signal {} in a sent frame", o.name),
            ));
        }
        let slot = slot(mapped.role, tx);
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
        fd,
        cycle,
        timeout,
        on_change,
        signals,
        j1939,
    })
}
