//! What crosses the wire between gateways: typed messages, JSON-encoded, and the key
//! expressions they travel under.
//!
//! | key | what |
//! |---|---|
//! | `hwgw/<gw>/dev/<interface>/<device>` | a [`Sample`] of one device, every publication period |
//! | `hwgw/<gw>/@/catalogue` (queryable) | the [`Catalogue`]: every device and its shape |
//! | `hwgw/<gw>/@/write` (queryable) | a [`Write`] to one of its outputs, answered by a [`WriteReply`] |
//! | `hwgw/<gw>/@/control` (queryable) | a control-socket request, answered by its reply |
//!
//! A message that does not parse, or that is bigger than [`MAX_PAYLOAD`], is refused and
//! counted; it never panics the receiver.

use device_interface::{Interface, Scale, Status};
use serde::{Deserialize, Serialize};

/// Version of these messages; a peer speaking another is refused with both numbers.
pub const PROTOCOL: u32 = 1;

/// Largest payload read from a peer, bytes (the transport's own bound is
/// [`crate::config::MAX_MESSAGE`]).
pub const MAX_PAYLOAD: usize = crate::config::MAX_MESSAGE;

/// The key chunk of an interface: `analog_in`, ….
pub fn interface_key(i: Interface) -> &'static str {
    match i {
        Interface::AnalogIn => "analog_in",
        Interface::AnalogOut => "analog_out",
        Interface::DigitalIn => "digital_in",
        Interface::DigitalOut => "digital_out",
        Interface::Encoder => "encoder",
        Interface::Sensor => "sensor",
        Interface::Drive => "drive",
        Interface::Axis => "axis",
    }
}

/// Where gateway `gw` publishes device `device` of interface `i`.
pub fn sample_key(gw: &str, i: Interface, device: &str) -> String {
    format!("hwgw/{gw}/dev/{}/{device}", interface_key(i))
}

/// Gateway `gw`'s queryable `what` (`catalogue`, `write`, `control`).
pub fn service_key(gw: &str, what: &str) -> String {
    format!("hwgw/{gw}/@/{what}")
}

/// One device's latest state, as its gateway saw it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    /// Counts up by one per publication of this device: a gap is samples lost.
    pub seq: u64,
    /// The publisher's monotonic clock when it read the device, ns (comparable only on
    /// the same host: latency benchmarks use it).
    pub read_ns: u64,
    /// UNIX time when it read the device, ns.
    pub unix_ns: u64,
    /// The device's own age then (time since its last good sample), ns, if it had one.
    pub age_ns: Option<u64>,
    /// Its status then.
    pub status: Status,
    /// Its last error then, as text.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// One value a channel: raw values of an analog device, 0/1 of a digital one,
    /// `[position, turn]` of an encoder; `null` where the channel could not be read.
    /// Outputs carry their read-back.
    pub values: Vec<Option<i64>>,
}

/// Every device a gateway publishes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Catalogue {
    /// [`PROTOCOL`] of the gateway.
    pub protocol: u32,
    /// Its name.
    pub gateway: String,
    /// Its run: a number of its own for each time it started (two gateways answering
    /// with one name and two runs are two gateways sharing a name).
    #[serde(default)]
    pub run: u64,
    /// Its devices.
    pub devices: Vec<DeviceShape>,
}

/// One device of a catalogue.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DeviceShape {
    /// Its interface.
    pub interface: Interface,
    /// Its name at its gateway.
    pub name: String,
    /// Channels (bits); 2 for an encoder (position, turn).
    pub channels: u32,
    /// Each channel's scale (analog devices).
    #[serde(default)]
    pub scales: Vec<Scale>,
    /// Counts per turn and direction (encoders).
    #[serde(default)]
    pub encoder: Option<EncoderShape>,
}

/// What an encoder says of itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct EncoderShape {
    /// Counts per turn (may be negative).
    pub resolution: i64,
    /// Counts up when turning forward.
    pub upcounting: bool,
}

/// A write from another gateway to outputs of this one.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Write {
    /// [`PROTOCOL`] of the writer.
    pub protocol: u32,
    /// The writing gateway.
    pub writer: String,
    /// The output device's interface (`analog_out`, `digital_out`, `encoder`).
    pub interface: Interface,
    /// Its name at this gateway.
    pub device: String,
    /// `(channel, raw value)` of every output the writer drives: raw for analog, 0/1 for
    /// digital, position (0) and turn (1) for an encoder.
    pub values: Vec<(u32, i64)>,
    /// The writer's number of this message for this device, counting up from 1: a message
    /// sent again keeps its number, and is applied once (0: apply every time).
    #[serde(default)]
    pub seq: u64,
    /// The writer's run: a restarted writer counts its numbers from 1 again.
    #[serde(default)]
    pub session: u64,
}

/// The answer to a [`Write`]: the channels refused, each with why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WriteReply {
    /// `(channel, error)`; empty when every value was written.
    pub refused: Vec<(u32, String)>,
}

/// The answer to a control request forwarded to another gateway: its reply body
/// (`{"ok": …}` or `{"error": {"kind", "message"}}`) as that gateway's control socket
/// would have sent it.
pub type ControlReply = serde_json::Value;

/// Why a peer's payload was refused.
#[derive(Debug, thiserror::Error)]
pub enum WireError {
    /// Longer than [`MAX_PAYLOAD`] (its length).
    #[error("{0} bytes is more than the {MAX_PAYLOAD} a message may have")]
    TooLong(usize),
    /// Not the message expected.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
}

/// Parses a peer's payload as `T`, refusing one longer than [`MAX_PAYLOAD`].
pub fn parse<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T, WireError> {
    if bytes.len() > MAX_PAYLOAD {
        return Err(WireError::TooLong(bytes.len()));
    }
    Ok(serde_json::from_slice(bytes)?)
}

/// `v` as JSON bytes (the message types here always serialise).
pub fn to_bytes<T: Serialize>(v: &T) -> Vec<u8> {
    serde_json::to_vec(v).unwrap_or_default()
}
