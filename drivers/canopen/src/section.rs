//! A CANopen card's section, `[card.canopen]`, as the TOML says it: the interface, the
//! SYNC period, what NMT does at stop, and the nodes — each with its EDS, heartbeat, and
//! the PDOs hwgw configures on it, whose mapped objects become the card's channels.
//!
//! ```toml
//! [card.canopen]
//! interface = "can0"
//! sync_ms = 20
//!
//! [[card.canopen.node]]
//! id = 5
//! eds = "io401.eds"
//! heartbeat_ms = 100
//!
//! [[card.canopen.node.tpdo]]
//! number = 1
//! transmission = "event"
//! objects = [{ object = "0x6000:1", name = "di" }, { object = "0x6401:1", name = "ai1", factor = 0.001, unit = "V" }]
//! ```

use serde::Deserialize;
use std::path::PathBuf;

/// `[card.canopen]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CanopenConfig {
    /// The CAN interface (`can0`, `vcan0`).
    pub interface: String,
    /// The SYNC producer's period, ms (absent: hwgw sends no SYNC).
    #[serde(default)]
    pub sync_ms: Option<u32>,
    /// How long an SDO request waits for its response, ms.
    #[serde(default = "default_sdo_timeout")]
    pub sdo_timeout_ms: u32,
    /// The NMT state the nodes are left in at stop, once the outputs are safe.
    #[serde(default)]
    pub at_stop: AtStop,
    /// The nodes hwgw manages.
    #[serde(default)]
    pub node: Vec<NodeConfig>,
}

fn default_sdo_timeout() -> u32 {
    500
}

/// The NMT state nodes are left in at stop.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AtStop {
    /// Left operational, their outputs at the safe values hwgw last sent.
    #[default]
    Operational,
    /// Pre-operational: PDOs stop and the nodes' own fault reactions apply.
    PreOperational,
    /// Stopped (NMT stop).
    Stopped,
}

/// `[[card.canopen.node]]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NodeConfig {
    /// Node id, 1-127.
    pub id: u8,
    /// The prefix of its channels' names (default `n<ID>`).
    #[serde(default)]
    pub name: Option<String>,
    /// The node's EDS file (relative to the deployment).
    pub eds: PathBuf,
    /// The heartbeat period hwgw asks of the node (written to 0x1017); absent: the node's
    /// own setting stands and hwgw does not watch its heartbeat.
    #[serde(default)]
    pub heartbeat_ms: Option<u16>,
    /// How long without a heartbeat before the node is offline (default 3 periods).
    #[serde(default)]
    pub heartbeat_timeout_ms: Option<u32>,
    /// Objects written once at configuration, before the PDOs (`{ object, value }`).
    #[serde(default)]
    pub sdo: Vec<SdoSetting>,
    /// The node's TPDOs: its inputs.
    #[serde(default)]
    pub tpdo: Vec<PdoConfig>,
    /// The node's RPDOs: its outputs.
    #[serde(default)]
    pub rpdo: Vec<PdoConfig>,
    /// A CiA 402 drive in profile velocity mode: its RPDOs carry the controlword
    /// (0x6040) and the target velocity (0x60FF), a TPDO its statusword (0x6041); it is
    /// the card's drive `<card>.<name>`.
    #[serde(default)]
    pub drive: Option<DriveConfig>,
}

/// A node's CiA 402 drive.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriveConfig {
    /// Its name under the card (default `drive<ID>`).
    #[serde(default)]
    pub name: Option<String>,
    /// Velocity units per count of 0x60FF (default 1).
    #[serde(default)]
    pub velocity_factor: Option<f64>,
    /// The velocity unit (default `counts/s`).
    #[serde(default)]
    pub unit: Option<String>,
}

/// One object written at configuration.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SdoSetting {
    /// `0xINDEX:SUB`.
    pub object: String,
    /// The value (an integer, or a float for REAL32/REAL64 objects).
    pub value: toml_value::Number,
}

/// A number as TOML writes it.
pub mod toml_value {
    use serde::Deserialize;

    /// An integer or a float.
    #[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
    #[serde(untagged)]
    pub enum Number {
        /// An integer.
        Int(i64),
        /// A float.
        Float(f64),
    }
}

/// A PDO.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PdoConfig {
    /// Its number (1-512; 1-4 have the predefined COB-IDs).
    pub number: u16,
    /// Its COB-ID (default: the predefined connection set's for PDOs 1-4).
    #[serde(default)]
    pub cob_id: Option<u16>,
    /// When it is sent.
    #[serde(default)]
    pub transmission: Transmission,
    /// A TPDO's event timer, ms (sent at least this often).
    #[serde(default)]
    pub event_timer_ms: Option<u16>,
    /// A TPDO's inhibit time, multiples of 100 µs.
    #[serde(default)]
    pub inhibit_100us: Option<u16>,
    /// The objects it carries, in order.
    pub objects: Vec<ObjectConfig>,
}

/// When a PDO is sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(untagged)]
pub enum Transmission {
    /// A name: `"event"` (type 255; an RPDO: sent by hwgw when an output changes) or
    /// `"sync"` (type 1; an RPDO: sent by hwgw after each SYNC).
    Named(Named),
    /// A transmission type number: 0-240 synchronous, 254/255 event-driven.
    Type(u8),
}

/// Event-driven, when the section does not say.
impl Default for Transmission {
    fn default() -> Self {
        Transmission::Named(Named::Event)
    }
}

/// The named transmission types.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Named {
    /// Event-driven (255).
    Event,
    /// Every SYNC (1).
    Sync,
}

impl Transmission {
    /// The transmission type number.
    pub fn number(self) -> u8 {
        match self {
            Transmission::Named(Named::Event) => 255,
            Transmission::Named(Named::Sync) => 1,
            Transmission::Type(t) => t,
        }
    }

    /// Whether it is synchronous (0-240).
    pub fn is_sync(self) -> bool {
        self.number() <= 240
    }
}

/// One mapped object and the channel(s) it becomes.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObjectConfig {
    /// `0xINDEX:SUB` (hex index; sub decimal, or hex with 0x).
    pub object: String,
    /// The channel's name (default `<node>_<index>_<sub>`); a digital object of several
    /// bits is channels `<name>_0`, `<name>_1`, ….
    #[serde(default)]
    pub name: Option<String>,
    /// Analog or digital (default: digital for BOOLEAN and the CiA 401 digital objects
    /// 0x6000-0x6FFF… 0x6000-0x6020 and 0x6200-0x6220, else analog).
    #[serde(default, rename = "type")]
    pub kind: Option<Kind>,
    /// physical = raw × factor + offset (analog).
    #[serde(default)]
    pub factor: Option<f64>,
    /// See `factor`.
    #[serde(default)]
    pub offset: Option<f64>,
    /// The physical unit (analog).
    #[serde(default)]
    pub unit: Option<String>,
}

/// What a mapped object becomes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Kind {
    /// One analog channel.
    Analog,
    /// One digital channel per bit.
    Digital,
}

/// `0xINDEX:SUB` → (index, sub).
pub fn parse_object(text: &str) -> Option<(u16, u8)> {
    let (index, sub) = text.trim().split_once(':')?;
    let index = index.trim();
    let index = index
        .strip_prefix("0x")
        .or_else(|| index.strip_prefix("0X"))
        .unwrap_or(index);
    let index = u16::from_str_radix(index, 16).ok()?;
    let sub = sub.trim();
    let sub = match sub.strip_prefix("0x").or_else(|| sub.strip_prefix("0X")) {
        Some(hex) => u8::from_str_radix(hex, 16).ok()?,
        None => sub.parse().ok()?,
    };
    Some((index, sub))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;

    #[test]
    fn objects_are_hex_index_and_sub() {
        assert_eq!(parse_object("0x6000:1"), Some((0x6000, 1)));
        assert_eq!(parse_object("6401:0x10"), Some((0x6401, 16)));
        assert_eq!(parse_object("0x6000"), None);
        assert_eq!(parse_object("0x16000:1"), None);
        assert_eq!(parse_object("0x6000:256"), None);
    }

    #[test]
    fn transmissions_by_name_or_number() {
        #[derive(Deserialize)]
        struct T {
            t: Transmission,
        }
        let t = |s: &str| toml::from_str::<T>(s).map(|t| t.t.number());
        assert_eq!(t("t = \"event\"").unwrap(), 255);
        assert_eq!(t("t = \"sync\"").unwrap(), 1);
        assert_eq!(t("t = 254").unwrap(), 254);
        assert!(t("t = \"often\"").is_err());
    }
}
