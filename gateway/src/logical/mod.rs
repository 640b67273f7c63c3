//! Logical devices in the deployment: `[[logical]]` sensors, drives and axes built over
//! the devices the cards registered, registered by name like them, and served as ports and
//! operations by IO components of their own (manual L5824–5876, road map L322; the devices
//! themselves are [`device_interface::logical`]).
//!
//! ```toml
//! [[logical]]
//! name = "drive0"
//! type = "drive"
//! setpoint = { device = "sim0", channel = 1 }   # an analog output
//! volts_per_unit = 0.1                           # output per unit of velocity
//! enable = { device = "sim0", bit = 0 }          # a digital output, on to enable
//! unit = "mm/s"
//!
//! [[logical]]
//! name = "axis0"
//! type = "axis"
//! drive = "drive0"
//! encoder = "sim0.encoder0"
//! counts_per_unit = 100.0
//! unit = "mm"
//! home = { device = "sim0", bit = 8 }
//! homing = { velocity = 5.0, back_off = 2.0 }
//! ```
//!
//! The drive's outputs stay under their card's output policy: `hwgw check` refuses a drive
//! whose enable output the card keeps as it is at stop or drives on, or whose setpoint it
//! keeps or drives to anything but zero velocity.

mod build;
mod claimed;
mod io;

pub(crate) use build::build;
pub(crate) use io::drive as drive_io;

use serde::Deserialize;

/// One `[[logical]]` device: its `type` and its keys.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum LogicalConfig {
    /// A reading in a unit of its own.
    Sensor(SensorConfig),
    /// A velocity-controlled drive.
    Drive(DriveConfig),
    /// An axis: a drive, an encoder, switches.
    Axis(AxisConfig),
}

impl LogicalConfig {
    /// Its name.
    pub fn name(&self) -> &str {
        match self {
            LogicalConfig::Sensor(s) => &s.name,
            LogicalConfig::Drive(d) => &d.name,
            LogicalConfig::Axis(a) => &a.name,
        }
    }
}

/// The registered devices `l` is built on.
pub(crate) fn devices_named(l: &LogicalConfig) -> Vec<&str> {
    fn bits<'a>(b: &[&'a Option<BitRef>]) -> Vec<&'a str> {
        b.iter()
            .filter_map(|b| b.as_ref().map(|b| b.device.as_str()))
            .collect()
    }
    match l {
        LogicalConfig::Sensor(s) => s
            .analog_in
            .iter()
            .map(|c| c.device.as_str())
            .chain(s.encoder.as_deref())
            .collect(),
        LogicalConfig::Drive(d) => {
            let mut v = vec![d.setpoint.device.as_str()];
            v.extend(bits(&[&d.enable, &d.fault]));
            v
        }
        LogicalConfig::Axis(a) => {
            let mut v = vec![a.drive.as_str(), a.encoder.as_str()];
            v.extend(bits(&[&a.limit_min, &a.limit_max, &a.home]));
            v
        }
    }
}

/// One channel of a device: `{ device = "sim0", channel = 1 }`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChannelRef {
    /// The device's registered name (a card's name for its channels).
    pub device: String,
    /// The channel.
    pub channel: u32,
}

/// One bit of a device: `{ device = "sim0", bit = 4, invert = false }`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BitRef {
    /// The device's registered name.
    pub device: String,
    /// The bit.
    pub bit: u32,
    /// Active low: the wire is off when the logical signal is on.
    #[serde(default)]
    pub invert: bool,
}

/// `type = "sensor"`: an analog input channel (`gain × value + offset`) or an encoder
/// (`count / counts_per_unit + offset`) in a unit.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorConfig {
    /// Its name.
    pub name: String,
    /// The analog input channel it reads (or `encoder`).
    #[serde(default)]
    pub analog_in: Option<ChannelRef>,
    /// The encoder it reads (or `analog_in`).
    #[serde(default)]
    pub encoder: Option<String>,
    /// Multiplies the analog input's value (default 1).
    #[serde(default)]
    pub gain: Option<f64>,
    /// Encoder counts to a unit (with `encoder`).
    #[serde(default)]
    pub counts_per_unit: Option<f64>,
    /// Added to the reading (default 0).
    #[serde(default)]
    pub offset: f64,
    /// The unit.
    #[serde(default)]
    pub unit: String,
    /// How often its `value` port is sampled, ms (default 10).
    #[serde(default = "ten")]
    pub sample_period_ms: f64,
}

/// `type = "drive"`: an analog setpoint `volts_per_unit × velocity + offset`, an optional
/// enable output and fault input.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriveConfig {
    /// Its name.
    pub name: String,
    /// The analog output carrying the velocity setpoint.
    pub setpoint: ChannelRef,
    /// Setpoint output per unit of velocity; not 0.
    pub volts_per_unit: f64,
    /// The setpoint output at zero velocity (default 0).
    #[serde(default)]
    pub offset: f64,
    /// The digital output that enables the drive.
    #[serde(default)]
    pub enable: Option<BitRef>,
    /// The digital input that is on when the drive failed.
    #[serde(default)]
    pub fault: Option<BitRef>,
    /// The velocity unit.
    #[serde(default)]
    pub unit: String,
}

/// `type = "axis"`: a drive, an encoder, optional limit and home switches and homing.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AxisConfig {
    /// Its name.
    pub name: String,
    /// The drive's registered name (a `[[logical]]` drive, or another crate's).
    pub drive: String,
    /// The encoder's registered name.
    pub encoder: String,
    /// Encoder counts per unit of position (negative: the position falls as it counts).
    pub counts_per_unit: f64,
    /// The position unit; the drive's velocity is in this unit per second.
    #[serde(default)]
    pub unit: String,
    /// The low-end limit switch, on at the limit.
    #[serde(default)]
    pub limit_min: Option<BitRef>,
    /// The high-end limit switch.
    #[serde(default)]
    pub limit_max: Option<BitRef>,
    /// The home switch.
    #[serde(default)]
    pub home: Option<BitRef>,
    /// How it homes (needs `home`).
    #[serde(default)]
    pub homing: Option<HomingSection>,
    /// Its own thread's period, ms (default 10): the switches are watched and homing
    /// advances once a period.
    #[serde(default = "ten")]
    pub period_ms: f64,
    /// Its own thread's scheduling.
    #[serde(default)]
    pub thread: rtt::ThreadOptions,
}

/// An axis' `homing` keys.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HomingSection {
    /// Search velocity, unit/s; its sign is the direction.
    pub velocity: f64,
    /// The position the home switch's edge gets (default 0).
    #[serde(default)]
    pub position: f64,
    /// How far to move back off the switch (default 0).
    #[serde(default)]
    pub back_off: f64,
    /// The farthest the search may go (default: no limit but the limit switches).
    #[serde(default)]
    pub max_travel: Option<f64>,
}

fn ten() -> f64 {
    10.0
}
