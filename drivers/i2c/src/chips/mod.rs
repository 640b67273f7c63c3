//! Chip models: what each chip's registers mean, one file per chip.
//!
//! # Adding a chip model
//!
//! 1. A file `chips/<model>.rs` with a type implementing [`ChipModel`]: its [`Shape`] (how
//!    many channels of each interface it adds to the card), its channels' scales and its
//!    outputs' starting values (`analog_in`, `analog_out`, `initial_on`, `encoders`; a
//!    linear scale is [`linear`]), `start` (configure the chip
//!    and write its outputs' starting values, outputs before directions so no pin shows a
//!    level nobody asked for) and `poll` (read inputs into the card's images, send outputs
//!    the devices changed), both answering an [`Outcome`], and `check` if the chip keeps
//!    set-up that a power loss or a reset undoes (read it back; answer the register that
//!    differs, [`Lost`], and the bus side counts a reset and calls `start` again). A
//!    register that is cheap to read with each poll and tells a reset (the INA219's
//!    calibration, the ADS1115's config) is read by `poll`, before anything read is
//!    published: it answers [`Outcome::Reset`] and publishes nothing. A chip that converts
//!    answers [`Outcome::Pending`] while a conversion is under way and
//!    [`ChipError::NotConverting`] when one is overdue. Use only SMBus byte/word transfers
//!    ([`Smbus`]), the size the real chip uses for each register (i2c-stub keeps one word
//!    per register and does not overlap a word register with the byte register after it).
//! 2. A variant of [`ChipConfig`] with the chip's settings and
//!    their checks, and a line in [`model`] making the model from it.
//! 3. A kernel test on i2c-stub: inputs set with `i2cset` read through the devices, outputs
//!    read back with `i2cget`, and the conformance kit.

pub mod ads1115;
pub mod as5600;
pub mod ina219;
pub mod mcp23017;
pub mod mcp4725;
pub mod pca9685;
#[cfg(test)]
pub(crate) mod tests;

use crate::card::{ChipIo, ChipPlace};
pub use crate::card::{Lost, Shape};
use crate::config::ChipConfig;
use crate::smbus::{Smbus, Transfer};
use device_interface::{RawRange, Scale, ScaleError, Unit};
use std::fmt;
use std::time::Duration;

/// What a poll (or a start) of a chip came to, when every transfer answered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// Inputs read into the card's images (or nothing to read): the chip is fresh, and
    /// online if it was not.
    Fresh,
    /// Nothing new yet — a conversion under way, the first since the chip was set up not
    /// finished: the chip keeps its state (an offline one stays offline, an online one's
    /// last good sample grows old) and its failures in a row are not forgiven.
    Pending,
    /// The chip is not set up as `start` left it (a reset, a power loss or another
    /// master): nothing this poll read was published; the bus side counts a reset and
    /// calls `start` again. `start` itself never answers it.
    Reset(Lost),
}

/// Why a poll of a chip failed: each one is counted, and
/// [`FAILS_TO_OFFLINE`](crate::bus::FAILS_TO_OFFLINE) in a row take the chip offline (a
/// [`Transfer::NoAnswer`] at once).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ChipError {
    /// A transfer failed.
    #[error(transparent)]
    Transfer(#[from] Transfer),
    /// A conversion the chip should have finished by now is not done: the converter is
    /// stuck (or its clock stopped). Each overdue span counts once.
    #[error(
        "{} not done within {} µs (one takes at most {} µs; {flag}): the chip is not converting",
        Conversion(*.channel),
        .within.as_micros(),
        .takes.as_micros()
    )]
    NotConverting {
        /// The channel converted, on a chip with several.
        channel: Option<u32>,
        /// What the chip shows ("OS stays 0").
        flag: &'static str,
        /// How long one takes at most, by the datasheet.
        takes: Duration,
        /// How long it was given.
        within: Duration,
    },
}

/// "channel n's conversion", or "a conversion".
struct Conversion(Option<u32>);

impl fmt::Display for Conversion {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            Some(n) => write!(f, "channel {n}'s conversion"),
            None => f.write_str("a conversion"),
        }
    }
}

/// How long a conversion that takes at most `takes` is given before it counts as stuck:
/// twice that, and 1 ms for the transfers around it and the bus thread's own delays.
pub fn conversion_deadline(takes: Duration) -> Duration {
    takes * 2 + Duration::from_millis(1)
}

/// A chip's register model. Runs on the card's bus thread only; keeps the real-time
/// contract there: no blocking but the transfers themselves, no allocation while the
/// transfers succeed (a failed one's [`Transfer`] carries its text).
pub trait ChipModel: Send {
    /// The model's name, for logs and errors.
    fn model(&self) -> &'static str;
    /// Its digital channels.
    fn shape(&self) -> Shape;
    /// Its analog inputs' scales, one per AnalogIn channel. Default: none.
    fn analog_in(&self) -> Vec<Scale> {
        Vec::new()
    }
    /// Its DigitalOut bits' levels from the start, one per bit. Default: all off.
    fn initial_on(&self) -> Vec<bool> {
        Vec::new()
    }
    /// Its analog outputs' scales and raw values from the start, one per AnalogOut
    /// channel. Default: none.
    fn analog_out(&self) -> Vec<(Scale, i64)> {
        Vec::new()
    }
    /// Its encoders' resolution and counting direction. Default: none.
    fn encoders(&self) -> Vec<(i64, bool)> {
        Vec::new()
    }
    /// Configures the chip and writes its outputs' current values: at start, again each
    /// time it answers after it did not, and after a reset was found. Answers
    /// [`Outcome::Fresh`] when it read the inputs too (or has none), [`Outcome::Pending`]
    /// when the first sample is still to come (the chip goes online with it).
    fn start(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Outcome, ChipError>;
    /// One poll: inputs read into the images, outputs the devices changed sent.
    fn poll(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Outcome, ChipError>;
    /// Whether the chip is still set up as `start` left it (called after a poll of an
    /// online chip, every [`CHECK_PERIOD`](crate::bus::CHECK_PERIOD)): the register that
    /// differs has the bus side count a reset and call `start` again. Default: a chip
    /// with nothing to lose, always as left.
    fn check(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Option<Lost>, Transfer> {
        let _ = (bus, io);
        Ok(None)
    }
}

/// Where a chip section's model sits on its card: its address, period and channels, with
/// their scales and starting values.
pub fn place(config: &ChipConfig, model: &dyn ChipModel) -> ChipPlace {
    ChipPlace {
        address: config.address(),
        poll_ms: config.poll_ms(),
        model: model.model(),
        shape: model.shape(),
        initial_on: model.initial_on(),
        analog_in: model.analog_in(),
        analog_out: model.analog_out(),
        encoders: model.encoders(),
    }
}

/// `raw × factor` in `unit` over `raw`. None only for what no model gives: a raw range
/// it failed to make, a factor that is not positive and finite, a unit too long.
pub fn linear(raw: Result<RawRange, ScaleError>, factor: f64, unit: &str) -> Option<Scale> {
    Scale::from_factor(raw.ok()?, factor, 0.0, Unit::new(unit).ok()?).ok()
}

/// The model a chip section describes (checked).
pub fn model(config: &ChipConfig) -> Box<dyn ChipModel> {
    match config {
        ChipConfig::Mcp23017(c) => Box::new(mcp23017::Mcp23017::new(c)),
        ChipConfig::Ads1115(c) => Box::new(ads1115::Ads1115::new(c)),
        ChipConfig::Mcp4725(c) => Box::new(mcp4725::Mcp4725::new(c)),
        ChipConfig::As5600(c) => Box::new(as5600::As5600::new(c)),
        ChipConfig::Ina219(c) => Box::new(ina219::Ina219::new(c)),
        ChipConfig::Pca9685(c) => Box::new(pca9685::Pca9685::new(c)),
    }
}
