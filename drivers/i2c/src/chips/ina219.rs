//! Texas Instruments INA219, a high-side current and bus voltage monitor: three AnalogIn
//! channels. Its registers are big-endian: every SMBus word is byte-swapped.
//!
//! | register | address | use |
//! |---|---|---|
//! | Configuration | 0x00 | written at start: 0x399F (32 V bus range, ±320 mV shunt range, 12-bit, continuous) — also its power-on value |
//! | Shunt voltage | 0x01 | channel 0: signed, 10 µV a count |
//! | Bus voltage | 0x02 | channel 1: bits 15..3, 4 mV a count; CNVR (bit 1), OVF (bit 0) |
//! | Power | 0x03 | read once after each set-up, which clears CNVR |
//! | Current | 0x04 | channel 2: signed, `0.04096 / (calibration × shunt Ω)` A a count |
//! | Calibration | 0x05 | written at start: `trunc(0.04096 / (max_current_a / 32768 × shunt Ω))`, bit 0 cleared (void); 0 after power-on |
//!
//! # A reset
//!
//! A chip that lost power (a brown-out) comes back converting with its power-on
//! configuration — the one hwgw writes, so Configuration cannot tell — and calibration 0,
//! so its current (and power) reads 0 while shunt and bus voltage still read right. Every
//! poll reads Calibration after the channels, before publishing them (one word more than
//! the three it reads): not as written, the poll publishes nothing and answers
//! [`Outcome::Reset`]; the bus side counts it and sets the chip up again. The check (every
//! 0.5 s) reads Configuration, which only another master changes.
//!
//! The Current register is worked out at the end of each conversion, with the calibration
//! of that moment: right after a set-up it may still hold what the chip computed before.
//! So a set-up ends by reading Power, which clears CNVR (as does the Configuration write),
//! and nothing is published until a poll finds CNVR set — a conversion finished since,
//! with the new calibration ([`Outcome::Pending`] until then). CNVR not set within
//! [`conversion_deadline`] of the longest conversion (12-bit shunt and bus, 586 µs each)
//! fails the poll, as a converter that stopped. Once set it is not needed again (it stays
//! set: Power is not read again).

use super::{ChipError, ChipModel, Lost, Outcome, Shape, conversion_deadline, linear};
use crate::card::ChipIo;
use crate::config::Ina219Config;
use crate::smbus::Smbus;
use crate::smbus::Transfer;
use device_interface::time::Timestamp;
use device_interface::{RawRange, Scale};
use std::time::Duration;

const CONFIG: u8 = 0x00;
const SHUNT: u8 = 0x01;
const BUS: u8 = 0x02;
const POWER: u8 = 0x03;
const CURRENT: u8 = 0x04;
const CALIBRATION: u8 = 0x05;
/// 32 V bus range, PGA /8 (±320 mV), 12-bit bus and shunt ADC, shunt and bus continuous.
const CONFIGURATION: u16 = 0x399f;
/// Bus voltage: conversion ready.
pub const CNVR: u16 = 1 << 1;
/// The longest conversion of both (12 bits: 586 µs each at most).
const TAKES: Duration = Duration::from_micros(2 * 586);

/// An INA219.
pub struct Ina219 {
    current_lsb: f64,
    calibration: u16,
    /// Since when a conversion with the calibration written at the last set-up is waited
    /// for (the set-up, or the last time it was found overdue); None once one finished.
    set_up: Option<Timestamp>,
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
            set_up: None,
        }
    }

    fn read(bus: &mut dyn Smbus, reg: u8) -> Result<u16, Transfer> {
        Ok(bus.read_word(reg)?.swap_bytes())
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

    fn start(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Outcome, ChipError> {
        bus.write_word(CONFIG, CONFIGURATION.swap_bytes())?;
        bus.write_word(CALIBRATION, self.calibration.swap_bytes())?;
        // Clears CNVR: the next one set is a conversion with this calibration.
        bus.read_word(POWER)?;
        self.set_up = Some(io.now());
        Ok(Outcome::Pending)
    }

    fn poll(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Outcome, ChipError> {
        let word = Self::read(bus, BUS)?;
        if let Some(since) = self.set_up {
            if word & CNVR == 0 {
                let now = io.now();
                let within = conversion_deadline(TAKES);
                if now.duration_since(since) < within {
                    return Ok(Outcome::Pending);
                }
                self.set_up = Some(now);
                return Err(ChipError::NotConverting {
                    channel: None,
                    flag: "CNVR stays 0 since hwgw set the chip up",
                    takes: TAKES,
                    within,
                });
            }
            self.set_up = None;
        }
        let shunt = Self::read(bus, SHUNT)? as i16;
        let current = Self::read(bus, CURRENT)? as i16;
        // After the channels: a reset before any of them shows here.
        let calibration = Self::read(bus, CALIBRATION)?;
        if let Some(lost) = Lost::compare("calibration", calibration, self.calibration) {
            return Ok(Outcome::Reset(lost));
        }
        io.set_analog_in(0, i64::from(shunt));
        io.set_analog_in(1, i64::from(word >> 3));
        io.set_analog_in(2, i64::from(current));
        Ok(Outcome::Fresh)
    }

    fn check(&mut self, bus: &mut dyn Smbus, _: &ChipIo<'_>) -> Result<Option<Lost>, Transfer> {
        Ok(Lost::compare(
            "configuration",
            Self::read(bus, CONFIG)?,
            CONFIGURATION,
        ))
    }
}
