//! A comedi card's `[card.comedi]` section: the board, and which of its channels become
//! which device's channels.
//!
//! Each list names groups of channels of one subdevice; a group without `subdevice` takes
//! the board's first subdevice of the fitting kind (AI; AO; DI, else DIO; DO, else DIO;
//! COUNTER), and without `channels` all of that subdevice's channels. DIO channels are made
//! inputs or outputs as the list they are in says; nothing else is configured.
//!
//! ```
//! use driver_comedi::config::{Aref, ComediConfig};
//!
//! let config: ComediConfig = toml::from_str(r#"
//!     device = "/dev/comedi0"
//!     poll_ms = 5
//!     analog_in = [{ channels = [0, 1], range = 1, aref = "ground" }]
//!     analog_out = [{ subdevice = 1, channels = [0] }]
//!     output = [{ subdevice = 2, channels = [0, 1, 2, 3], initial = false }]
//! "#)?;
//! assert_eq!(config.analog_in[0].aref, Aref::Ground);
//! config.check()?;
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use driver_api::CardError;
use serde::Deserialize;

/// The most channels one interface of a card maps (a bound on what a config may ask for;
/// comedi boards have at most a few hundred channels a subdevice).
pub const MAX_CHANNELS: usize = 1024;
/// The longest poll period, ms.
pub const MAX_POLL_MS: u32 = 60_000;
/// The most counters one card maps.
pub const MAX_ENCODERS: usize = 64;

/// A card's `[card.comedi]` section.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ComediConfig {
    /// The board's device file (`/dev/comedi0`).
    pub device: String,
    /// How often the inputs are sampled, ms (1–60000; default 10).
    #[serde(default = "default_poll_ms")]
    pub poll_ms: u32,
    /// AnalogIn channels, in order.
    #[serde(default)]
    pub analog_in: Vec<AnalogGroup>,
    /// AnalogOut channels, in order.
    #[serde(default)]
    pub analog_out: Vec<AnalogGroup>,
    /// DigitalIn bits, in order.
    #[serde(default)]
    pub input: Vec<DigitalGroup>,
    /// DigitalOut bits, in order.
    #[serde(default)]
    pub output: Vec<OutputGroup>,
    /// Counters read as encoders, in order (`card.encoder0`, …).
    #[serde(default)]
    pub encoder: Vec<CounterConfig>,
}

fn default_poll_ms() -> u32 {
    10
}

/// An analog reference (comedi's `AREF_*`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Aref {
    /// To ground (the default).
    #[default]
    Ground,
    /// To a common reference.
    Common,
    /// Differential.
    Diff,
    /// Board-specific.
    Other,
}

impl Aref {
    /// comedi's number for it.
    pub fn raw(self) -> u32 {
        match self {
            Aref::Ground => comedi_sys::AREF_GROUND,
            Aref::Common => comedi_sys::AREF_COMMON,
            Aref::Diff => comedi_sys::AREF_DIFF,
            Aref::Other => comedi_sys::AREF_OTHER,
        }
    }

    /// The subdevice flag that says a subdevice takes it.
    pub fn flag(self) -> u32 {
        match self {
            Aref::Ground => comedi_sys::SDF_GROUND,
            Aref::Common => comedi_sys::SDF_COMMON,
            Aref::Diff => comedi_sys::SDF_DIFF,
            Aref::Other => comedi_sys::SDF_OTHER,
        }
    }

    /// Its name in a config.
    pub fn name(self) -> &'static str {
        match self {
            Aref::Ground => "ground",
            Aref::Common => "common",
            Aref::Diff => "diff",
            Aref::Other => "other",
        }
    }
}

/// Analog channels of one subdevice (inputs or outputs, as the list they are in says).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AnalogGroup {
    /// The subdevice (default: the board's first AI, or AO).
    #[serde(default)]
    pub subdevice: Option<u32>,
    /// Its channels (default: all).
    #[serde(default)]
    pub channels: Option<Vec<u32>>,
    /// The range each starts in: an index into the channel's range table (default 0).
    #[serde(default)]
    pub range: u32,
    /// The reference (default ground).
    #[serde(default)]
    pub aref: Aref,
    /// Outputs only: a value, in the range's unit, written at start. Without one nothing
    /// is written until asked and the read-back is what the board reads back.
    #[serde(default)]
    pub initial: Option<f64>,
}

/// Digital input channels of one subdevice.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DigitalGroup {
    /// The subdevice (default: the board's first DI, else its first DIO).
    #[serde(default)]
    pub subdevice: Option<u32>,
    /// Its channels (default: all).
    #[serde(default)]
    pub channels: Option<Vec<u32>>,
}

/// Digital output channels of one subdevice.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputGroup {
    /// The subdevice (default: the board's first DO, else its first DIO).
    #[serde(default)]
    pub subdevice: Option<u32>,
    /// Its channels (default: all).
    #[serde(default)]
    pub channels: Option<Vec<u32>>,
    /// A level written at start. Without one nothing is written until asked: the
    /// outputs keep the levels they have (a DIO input is made an output at its pin's).
    #[serde(default)]
    pub initial: Option<bool>,
}

/// A counter channel read as an encoder.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CounterConfig {
    /// The subdevice (default: the board's first COUNTER).
    #[serde(default)]
    pub subdevice: Option<u32>,
    /// The counter's channel (default 0).
    #[serde(default)]
    pub channel: u32,
    /// Counts per turn (negative: counting down).
    pub resolution: i64,
    /// Whether the count grows with the position (default true).
    #[serde(default = "yes")]
    pub upcounting: bool,
}

fn yes() -> bool {
    true
}

fn err(key: impl Into<String>, message: impl std::fmt::Display) -> CardError {
    CardError::at(key, message)
}

impl ComediConfig {
    /// Checks what can be checked without the board (bounds; the channels against the
    /// board are checked when the card is built).
    pub fn check(&self) -> Result<(), CardError> {
        if self.device.is_empty() || self.device.len() > 4096 || self.device.contains('\0') {
            return Err(err("device", "must be a path (1–4096 bytes, no NUL)"));
        }
        if !(1..=MAX_POLL_MS).contains(&self.poll_ms) {
            return Err(err(
                "poll_ms",
                format!("{} is outside 1..={MAX_POLL_MS}", self.poll_ms),
            ));
        }
        let lists = [
            (
                "analog_in",
                self.analog_in
                    .iter()
                    .map(|g| &g.channels)
                    .collect::<Vec<_>>(),
            ),
            (
                "analog_out",
                self.analog_out.iter().map(|g| &g.channels).collect(),
            ),
            ("input", self.input.iter().map(|g| &g.channels).collect()),
            ("output", self.output.iter().map(|g| &g.channels).collect()),
        ];
        for (list, groups) in lists {
            if groups.len() > MAX_CHANNELS {
                return Err(err(list, format!("more than {MAX_CHANNELS} groups")));
            }
            for (i, channels) in groups.iter().enumerate() {
                if let Some(c) = channels {
                    if c.is_empty() {
                        return Err(err(
                            format!("{list}[{i}].channels"),
                            "is empty (leave it out for all)",
                        ));
                    }
                    if c.len() > MAX_CHANNELS {
                        return Err(err(
                            format!("{list}[{i}].channels"),
                            format!("more than {MAX_CHANNELS}"),
                        ));
                    }
                }
            }
        }
        for (i, g) in self.analog_in.iter().enumerate() {
            if g.initial.is_some() {
                return Err(err(
                    format!("analog_in[{i}].initial"),
                    "an input has no initial value",
                ));
            }
        }
        for (i, g) in self.analog_out.iter().enumerate() {
            if g.initial.is_some_and(|v| !v.is_finite()) {
                return Err(err(format!("analog_out[{i}].initial"), "is not a number"));
            }
        }
        if self.encoder.len() > MAX_ENCODERS {
            return Err(err("encoder", format!("more than {MAX_ENCODERS}")));
        }
        for (i, e) in self.encoder.iter().enumerate() {
            device_interface::encoder::EncoderGeometry::new(e.resolution, e.upcounting)
                .map_err(|e| err(format!("encoder[{i}].resolution"), e.to_string()))?;
        }
        Ok(())
    }
}
