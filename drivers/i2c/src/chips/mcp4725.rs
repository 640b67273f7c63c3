//! Microchip MCP4725, a 12-bit DAC whose full scale is its supply.
//!
//! Written in the fast mode: two bytes after the address, the first `0 0 PD1 PD0 D11 D10
//! D9 D8` (power-down bits 00: normal), the second `D7..D0`. As an SMBus transfer that is a
//! byte-data write whose "register" is the first byte — which is how i2c-stub stores it
//! (register `D11..D8` holds `D7..D0`). The EEPROM is never written. One AnalogOut channel:
//! `code × vref / 4096` volts.
//!
//! The DAC register cannot be read back with SMBus transfers (the chip's read is a plain
//! five-byte I2C read, which i2c-stub and some SMBus-only adapters lack), and a chip that
//! lost power comes back at its EEPROM's code: the check sends the code again instead (the
//! same code, so the output does not move), which puts such a chip back at the asked
//! value within [`CHECK_PERIOD`](crate::bus::CHECK_PERIOD).

use super::{ChipError, ChipModel, Lost, Outcome, Shape, linear};
use crate::card::ChipIo;
use crate::config::Mcp4725Config;
use crate::smbus::{Smbus, Transfer};
use device_interface::{RawRange, Scale};

/// An MCP4725.
pub struct Mcp4725 {
    vref: f64,
    initial_v: f64,
}

impl Mcp4725 {
    /// The model of a (checked) section.
    pub fn new(c: &Mcp4725Config) -> Mcp4725 {
        Mcp4725 {
            vref: c.vref_v,
            initial_v: c.initial_v,
        }
    }

    fn send(bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<(), Transfer> {
        let code = io.analog_out(0).clamp(0, 4095) as u16;
        bus.write_byte((code >> 8) as u8, (code & 0xff) as u8)
    }
}

impl ChipModel for Mcp4725 {
    fn model(&self) -> &'static str {
        "mcp4725"
    }

    fn shape(&self) -> Shape {
        Shape::default()
    }

    fn analog_out(&self) -> Vec<(Scale, i64)> {
        // Cannot fail: 12 bits, a checked positive reference, a short unit.
        let scale = linear(RawRange::unsigned_bits(12), self.vref / 4096.0, "V");
        scale
            .map(|s| (s, s.to_raw_saturating(self.initial_v)))
            .into_iter()
            .collect()
    }

    fn start(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Outcome, ChipError> {
        io.take_dirty();
        Self::send(bus, io)?;
        Ok(Outcome::Fresh)
    }

    fn poll(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Outcome, ChipError> {
        if io.take_dirty()
            && let Err(e) = Self::send(bus, io)
        {
            io.mark_dirty();
            return Err(e.into());
        }
        Ok(Outcome::Fresh)
    }

    fn check(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Option<Lost>, Transfer> {
        Self::send(bus, io).map(|()| None)
    }
}
