//! ams AS5600, a 12-bit contactless angle sensor (a magnet on a shaft above it): one
//! Encoder of 4096 counts a turn.
//!
//! | register | address | use |
//! |---|---|---|
//! | STATUS | 0x0B | MD (bit 5): a magnet is detected; without one the chip's angle means nothing, and the chip counts as failing |
//! | RAW ANGLE | 0x0C–0x0D | the unscaled angle, 12 bits, MSB first: one SMBus word, byte-swapped |
//!
//! The first reading sets the position (the angle is absolute within a turn); each later
//! one advances the count by the shortest way round the circle, so turns are counted
//! across the wrap as long as the shaft moves less than half a turn between polls. That
//! holds across a dropout too: the last angle is kept, so a position set by homing stays
//! set when the chip answers again — but a shaft that turned half a turn or more while the
//! chip did not answer is counted short by whole turns (nothing can tell). The
//! ZPOS/MPOS/MANG programming and the burn commands are never touched.

use super::{ChipError, ChipModel, Outcome, Shape};
use crate::card::ChipIo;
use crate::config::As5600Config;
use crate::smbus::{Smbus, Transfer};

const STATUS: u8 = 0x0B;
const RAW_ANGLE: u8 = 0x0C;
/// STATUS: magnet detected.
const MD: u8 = 1 << 5;
/// Counts a turn.
pub const RESOLUTION: i64 = 4096;

/// An AS5600.
pub struct As5600 {
    upcounting: bool,
    last: Option<i64>,
}

impl As5600 {
    /// The model of a (checked) section.
    pub fn new(c: &As5600Config) -> As5600 {
        As5600 {
            upcounting: c.upcounting,
            last: None,
        }
    }
}

impl ChipModel for As5600 {
    fn model(&self) -> &'static str {
        "as5600"
    }

    fn shape(&self) -> Shape {
        Shape::default()
    }

    fn encoders(&self) -> Vec<(i64, bool)> {
        vec![(RESOLUTION, self.upcounting)]
    }

    fn start(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Outcome, ChipError> {
        self.poll(bus, io)
    }

    fn poll(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Outcome, ChipError> {
        if bus.read_byte(STATUS)? & MD == 0 {
            return Err(Transfer::Failed("no magnet detected (STATUS.MD is 0)".into()).into());
        }
        let angle = i64::from(bus.read_word(RAW_ANGLE)?.swap_bytes() & 0x0fff);
        let Some(counter) = io.encoder(0) else {
            return Ok(Outcome::Fresh);
        };
        match self.last {
            // Cannot fail: 0..4096 is a position of a 4096-count encoder.
            None => {
                let _ = counter.set_position(angle);
            }
            Some(last) => {
                let d = (angle - last).rem_euclid(RESOLUTION);
                counter.advance(if d >= RESOLUTION / 2 {
                    d - RESOLUTION
                } else {
                    d
                });
            }
        }
        self.last = Some(angle);
        Ok(Outcome::Fresh)
    }
}
