//! NXP PCA9685, a 16-channel 12-bit PWM controller: the configured outputs as AnalogOut
//! duty cycles, 0 (off) to 1 (on) in 4096 steps. Its registers are little-endian pairs
//! (L then H) with auto-increment on, so each is one SMBus word as it is.
//!
//! | register | address | use |
//! |---|---|---|
//! | MODE1 | 0x00 | read, and written back with AI (auto-increment) set, SLEEP and RESTART clear, the rest kept (ALLCALL, SUBn, EXTCLK); SLEEP set while a changed prescale is written |
//! | LEDn_ON | 0x06 + 4n | 0 (the pulse starts at count 0), or bit 12 (full on) |
//! | LEDn_OFF | 0x08 + 4n | the duty in counts, or bit 12 (full off) |
//! | PRE_SCALE | 0xFE | `round(25 MHz / (4096 × frequency)) − 1`, written only when it differs |
//!
//! The prescale is taken only while the oscillator sleeps, and a sleeping chip's outputs
//! are off: the chip sleeps at start only when its prescale must change, so a chip probed
//! again after a dropout (prescale unchanged) keeps its outputs running. The check reads
//! MODE1 and PRE_SCALE back: after a power loss the chip sleeps at its default prescale,
//! and is set up again.

use super::{ChipError, ChipModel, Lost, Outcome, Shape, linear};
use crate::card::ChipIo;
use crate::config::Pca9685Config;
use crate::smbus::{Smbus, Transfer};
use device_interface::{RawRange, Scale};

const MODE1: u8 = 0x00;
const PRE_SCALE: u8 = 0xfe;
const SLEEP: u8 = 1 << 4;
const AI: u8 = 1 << 5;
const RESTART: u8 = 1 << 7;
/// The full-on / full-off bit of LEDn_ON_H / LEDn_OFF_H, as a word.
const FULL: u16 = 1 << 12;
/// Counts a period.
pub const STEPS: i64 = 4096;
/// Its internal oscillator, Hz.
const OSCILLATOR: f64 = 25e6;

/// A PCA9685.
pub struct Pca9685 {
    channels: Vec<u8>,
    prescale: u8,
}

impl Pca9685 {
    /// The model of a (checked) section.
    pub fn new(c: &Pca9685Config) -> Pca9685 {
        let prescale = (OSCILLATOR / (4096.0 * c.frequency_hz)).round() - 1.0;
        Pca9685 {
            channels: c.channels.clone(),
            prescale: prescale.clamp(3.0, 255.0) as u8,
        }
    }

    fn send(&self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<(), Transfer> {
        for (i, &ch) in self.channels.iter().enumerate() {
            let duty = io.analog_out(i as u32).clamp(0, STEPS);
            let (on, off) = match duty {
                0 => (0, FULL),
                STEPS => (FULL, 0),
                d => (0, d as u16),
            };
            let base = 0x06 + 4 * ch;
            // Two transfers, ordered so the output between them is at its old level or
            // its new one, never another: to full on, set the full-on bit first (full off
            // still overrides it); otherwise set OFF first (a full-on bit still set holds
            // the output on until ON is cleared).
            if on == FULL {
                bus.write_word(base, on)?;
                bus.write_word(base + 2, off)?;
            } else {
                bus.write_word(base + 2, off)?;
                bus.write_word(base, on)?;
            }
        }
        Ok(())
    }
}

impl ChipModel for Pca9685 {
    fn model(&self) -> &'static str {
        "pca9685"
    }

    fn shape(&self) -> Shape {
        Shape::default()
    }

    fn analog_out(&self) -> Vec<(Scale, i64)> {
        // Cannot fail: a fixed raw range, a positive factor, no unit. Each starts off.
        let scale = linear(RawRange::new(0, STEPS), 1.0 / STEPS as f64, "");
        scale.map_or_else(Vec::new, |s| vec![(s, 0); self.channels.len()])
    }

    fn start(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Outcome, ChipError> {
        io.take_dirty();
        let mode = bus.read_byte(MODE1)?;
        let awake = (mode & !(SLEEP | RESTART)) | AI;
        let slept = bus.read_byte(PRE_SCALE)? != self.prescale;
        if slept {
            // Taken only while the oscillator sleeps; the outputs are set before it runs
            // again.
            bus.write_byte(MODE1, awake | SLEEP)?;
            bus.write_byte(PRE_SCALE, self.prescale)?;
        } else if mode & AI == 0 {
            // The duty words need auto-increment (without it both bytes land in the L
            // register); sleep is left as it is until they are written.
            bus.write_byte(MODE1, (mode & !RESTART) | AI)?;
        }
        self.send(bus, io)?;
        if slept || mode != awake {
            bus.write_byte(MODE1, awake)?;
        }
        Ok(Outcome::Fresh)
    }

    fn poll(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Outcome, ChipError> {
        if io.take_dirty()
            && let Err(e) = self.send(bus, io)
        {
            io.mark_dirty();
            return Err(e.into());
        }
        Ok(Outcome::Fresh)
    }

    fn check(&mut self, bus: &mut dyn Smbus, _: &ChipIo<'_>) -> Result<Option<Lost>, Transfer> {
        // Awake with auto-increment, the other bits as they are.
        let mode = bus.read_byte(MODE1)?;
        let awake = (mode & !(SLEEP | AI)) | AI;
        if let Some(lost) = Lost::compare("MODE1", mode.into(), awake.into()) {
            return Ok(Some(lost));
        }
        Ok(Lost::compare(
            "PRE_SCALE",
            bus.read_byte(PRE_SCALE)?.into(),
            self.prescale.into(),
        ))
    }
}
