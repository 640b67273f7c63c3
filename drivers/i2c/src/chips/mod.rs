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
//!    the devices changed), and `check` if the chip keeps set-up that a power loss or a
//!    reset undoes (read it back; answer false and the bus side counts a reset and calls
//!    `start` again). Use only SMBus byte/word transfers ([`Smbus`]), the size the
//!    real chip uses for each register (i2c-stub keeps one word per register and does not
//!    overlap a word register with the byte register after it).
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

pub use crate::card::Shape;
use crate::card::{ChipIo, ChipPlace};
use crate::config::ChipConfig;
use crate::smbus::{Smbus, Transfer};
use device_interface::{RawRange, Scale, ScaleError, Unit};

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
    /// Configures the chip and writes its outputs' current values: at start, and again
    /// each time it answers after it did not.
    fn start(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<(), Transfer>;
    /// One poll: inputs read into the images, outputs the devices changed sent.
    fn poll(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<(), Transfer>;
    /// Whether the chip is still set up as `start` left it (called after a poll, every
    /// [`CHECK_PERIOD`](crate::bus::CHECK_PERIOD)); false has the bus side count a reset
    /// and call `start` again. Default: a chip with nothing to lose, always true.
    fn check(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<bool, Transfer> {
        let _ = (bus, io);
        Ok(true)
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
