//! A CAN card's section of a deployment (`[card.socketcan]`): the interface, the DBC file,
//! and the frames to receive and send with their signals, as the TOML says them (serde,
//! unknown keys refused). [`CanMap`](crate::map::CanMap) resolves and checks them.

use crate::signal::ByteOrder;
use serde::Deserialize;
use std::path::PathBuf;

/// A card's `[card.socketcan]` section.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CanConfig {
    /// The network interface (`can0`, `vcan0`).
    pub interface: String,
    /// A DBC file to take messages from (relative to the deployment file's directory).
    #[serde(default)]
    pub dbc: Option<PathBuf>,
    /// The DBC file's text encoding: `auto` (UTF-8 when it is, else Windows-1252, the
    /// default), `utf8` or `cp1252`.
    #[serde(default)]
    pub encoding: crate::dbc::Encoding,
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
    /// ISO-TP address pairs, each an exchange (request, response) the bus component's
    /// `request` operation makes.
    #[serde(default)]
    pub isotp: Vec<IsoTpConfig>,
    /// J1939: the card's extended frames are parameter groups, received and sent through
    /// the kernel's J1939 stack (matched by PGN), and the card claims an address.
    #[serde(default)]
    pub j1939: Option<J1939Config>,
}

/// The `[j1939]` table: who the card is on a J1939 network.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct J1939Config {
    /// The 64-bit NAME the address is claimed with (J1939-81), an integer or a hex string
    /// (`"0x80…"`: a NAME with the arbitrary-address bit does not fit a TOML integer).
    /// Without it the card only listens.
    #[serde(default, deserialize_with = "name_number")]
    pub name: Option<u64>,
    /// The source address to claim (0 to 253).
    #[serde(default)]
    pub address: Option<u8>,
}

/// A NAME: a non-negative integer or a hex string.
fn name_number<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<u64>, D::Error> {
    struct Visitor;
    impl serde::de::Visitor<'_> for Visitor {
        type Value = Option<u64>;
        fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            f.write_str("a 64-bit NAME: an integer, or a hex string such as \"0x8000000000000001\"")
        }
        fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<Self::Value, E> {
            u64::try_from(v)
                .map(Some)
                .map_err(|_| E::custom(format!("NAME {v}: expected a non-negative number")))
        }
        fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<Self::Value, E> {
            Ok(Some(v))
        }
        fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<Self::Value, E> {
            let digits = v
                .strip_prefix("0x")
                .or_else(|| v.strip_prefix("0X"))
                .unwrap_or(v)
                .replace('_', "");
            u64::from_str_radix(&digits, 16)
                .map(Some)
                .map_err(|_| E::custom(format!("NAME {v:?}: expected up to 16 hex digits (0x…)")))
        }
    }
    d.deserialize_any(Visitor)
}

/// One `[[isotp]]` address pair.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IsoTpConfig {
    /// Its name (`hwgw call CARD request NAME HEX`).
    pub name: String,
    /// The id requests go out on (e.g. 0x7E0).
    pub tx_id: u32,
    /// The id responses come on (e.g. 0x7E8).
    pub rx_id: u32,
    /// 29-bit ids.
    #[serde(default)]
    pub extended: bool,
    /// How long a response may take, ms (default 1000).
    #[serde(default = "default_isotp_timeout")]
    pub timeout_ms: u32,
    /// The block size hwgw's flow control asks for (0, the default: no waiting).
    #[serde(default)]
    pub block_size: u8,
    /// The separation time hwgw's flow control asks for, µs (0 to 127000; under 1000 in
    /// steps of 100).
    #[serde(default)]
    pub st_min_us: u32,
    /// Pad sent frames to 8 bytes with this byte (e.g. 0xCC).
    #[serde(default)]
    pub padding: Option<u8>,
}

fn default_isotp_timeout() -> u32 {
    1000
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
    /// A CAN FD frame (default: as the DBC message's `VFrameFormat` says, or when it is
    /// longer than 8 bytes; an inline frame: classic).
    #[serde(default)]
    pub fd: Option<bool>,
    /// rx: the sender's cycle (for staleness); tx: the send period.
    #[serde(default)]
    pub cycle_ms: Option<f64>,
    /// rx: stale after this long without the frame (overrides `stale_after_cycles`).
    #[serde(default)]
    pub timeout_ms: Option<f64>,
    /// tx: send as soon as an output changes (default: only when there is no cycle).
    #[serde(default)]
    pub on_change: Option<bool>,
    /// J1939, rx: match only messages from this source address (default: any).
    #[serde(default)]
    pub source: Option<u8>,
    /// J1939, rx: match only messages of this priority (default: any); tx: send with it
    /// (default: the id's).
    #[serde(default)]
    pub priority: Option<u8>,
    /// J1939, tx: the destination address of a PDU1 group (default: the id's).
    #[serde(default)]
    pub destination: Option<u8>,
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
