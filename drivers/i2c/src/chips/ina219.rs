//! Texas Instruments INA219, a high-side current and bus voltage monitor: three AnalogIn
//! channels. Its registers are big-endian: every SMBus word is byte-swapped.
//!
//! | register | address | use |
//! |---|---|---|
//! | Configuration | 0x00 | written at start: 0x399F (32 V bus range, ±320 mV shunt range, 12-bit, continuous) |
//! | Shunt voltage | 0x01 | channel 0: signed, 10 µV a count |
//! | Bus voltage | 0x02 | channel 1: bits 15..3, 4 mV a count (CNVR, OVF below) |
//! | Current | 0x04 | channel 2: signed, `0.04096 / (calibration × shunt Ω)` A a count |
//! | Calibration | 0x05 | written at start: `trunc(0.04096 / (max_current_a / 32768 × shunt Ω))`, bit 0 cleared (void) |
//!
//! The check reads Configuration and Calibration back: after a power loss or a reset the
//! calibration is 0 (the current reads 0), and the chip is set up again.

use super::{ChipModel, Shape, linear};
use crate::card::ChipIo;
use crate::config::Ina219Config;
use crate::smbus::{Smbus, Transfer};
use device_interface::{RawRange, Scale};

const CONFIG: u8 = 0x00;
const SHUNT: u8 = 0x01;
const BUS: u8 = 0x02;
const CURRENT: u8 = 0x04;
const CALIBRATION: u8 = 0x05;
/// 32 V bus range, PGA /8 (±320 mV), 12-bit bus and shunt ADC, shunt and bus continuous.
const CONFIGURATION: u16 = 0x399f;

/// An INA219.
pub struct Ina219 {
    current_lsb: f64,
    calibration: u16,
}

impl Ina219 {
    /// The model of a (checked) section.
    pub fn new(c: &Ina219Config) -> Ina219 {
        // The register's bit 0 is void: an even calibration, and the current LSB the chip
        // really works with for it.
        let wanted = 0.04096 / (c.max_current_a / 32768.0 * c.shunt_ohms);
        let calibration = ((wanted.trunc() as u32) & !1).clamp(2, 0xfffe) as u16;
        Ina219 {
            current_lsb: 0.04096 / (f64::from(calibration) * c.shunt_ohms),
            calibration,
        }
    }
}

impl ChipModel for Ina219 {
    fn model(&self) -> &'static str {
        "ina219"
    }

    fn shape(&self) -> Shape {
        Shape::default()
    }

    fn analog_in(&self) -> Vec<Scale> {
        // Cannot fail: fixed widths, positive finite factors (the LSB from a checked
        // section), short units.
        [
            linear(RawRange::signed_bits(16), 10e-6, "V"),
            linear(RawRange::unsigned_bits(13), 4e-3, "V"),
            linear(RawRange::signed_bits(16), self.current_lsb, "A"),
        ]
        .into_iter()
        .flatten()
        .collect()
    }

    fn start(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<(), Transfer> {
        bus.write_word(CONFIG, CONFIGURATION.swap_bytes())?;
        bus.write_word(CALIBRATION, self.calibration.swap_bytes())?;
        self.poll(bus, io)
    }

    fn poll(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<(), Transfer> {
        let shunt = bus.read_word(SHUNT)?.swap_bytes() as i16;
        let busv = bus.read_word(BUS)?.swap_bytes() >> 3;
        let current = bus.read_word(CURRENT)?.swap_bytes() as i16;
        io.set_analog_in(0, i64::from(shunt));
        io.set_analog_in(1, i64::from(busv));
        io.set_analog_in(2, i64::from(current));
        Ok(())
    }

    fn check(&mut self, bus: &mut dyn Smbus, _: &ChipIo<'_>) -> Result<bool, Transfer> {
        Ok(bus.read_word(CONFIG)?.swap_bytes() == CONFIGURATION
            && bus.read_word(CALIBRATION)?.swap_bytes() == self.calibration)
    }
}
