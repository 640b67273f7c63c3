//! Microchip MCP23017, a 16-bit IO expander, used with IOCON as after power-on (BANK = 0,
//! sequential addressing): each A register is followed by its B register and one SMBus
//! word transfer covers both, A in the low byte; pin n is bit n of that word.
//!
//! | register | address | use |
//! |---|---|---|
//! | IOCON | 0x05, then 0x0A | set to 0 (BANK = 0, sequential) at start: 0x05 is IOCON if BANK was 1 (and GPINTENB, unused, if not), 0x0A is IOCON then |
//! | IODIR | 0x00 | 1 = input; pins not configured as outputs stay inputs |
//! | IPOL | 0x02 | inputs read inverted (`invert`) |
//! | GPPU | 0x0C | 100 kΩ pull-ups (`pull_up`) |
//! | GPIO | 0x12 | inputs read, each poll |
//! | OLAT | 0x14 | outputs written, when a device changed one (and at start) |
//!
//! The check reads IODIR, IPOL and GPPU back: after a power loss or a reset the chip is
//! all inputs, no pull-ups, and is set up again (its outputs written first).

use super::{ChipError, ChipModel, Lost, Outcome, Shape};
use crate::card::ChipIo;
use crate::config::Mcp23017Config;
use crate::smbus::{Smbus, Transfer};

const IODIR: u8 = 0x00;
/// IOCON as BANK = 1 places it.
const IOCON_BANK1: u8 = 0x05;
/// IOCON as BANK = 0 places it.
const IOCON: u8 = 0x0A;
const IPOL: u8 = 0x02;
const GPPU: u8 = 0x0C;
const GPIO: u8 = 0x12;
const OLAT: u8 = 0x14;

fn mask(pins: &[u8]) -> u16 {
    pins.iter().fold(0, |m, &p| m | 1u16 << (p & 15))
}

/// An MCP23017.
pub struct Mcp23017 {
    inputs: Vec<u8>,
    outputs: Vec<u8>,
    initial_on: Vec<bool>,
    iodir: u16,
    ipol: u16,
    gppu: u16,
}

impl Mcp23017 {
    /// The model of a (checked) section.
    pub fn new(c: &Mcp23017Config) -> Mcp23017 {
        Mcp23017 {
            inputs: c.inputs.clone(),
            outputs: c.outputs.clone(),
            initial_on: c.outputs.iter().map(|p| c.initial_on.contains(p)).collect(),
            iodir: !mask(&c.outputs),
            ipol: mask(&c.invert),
            gppu: mask(&c.pull_up),
        }
    }

    fn write_outputs(&self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<(), Transfer> {
        let olat = self
            .outputs
            .iter()
            .enumerate()
            .filter(|(bit, _)| io.output(*bit as u32))
            .fold(0u16, |m, (_, &p)| m | 1 << p);
        bus.write_word(OLAT, olat)
    }
}

impl ChipModel for Mcp23017 {
    fn model(&self) -> &'static str {
        "mcp23017"
    }

    fn shape(&self) -> Shape {
        Shape {
            digital_in: self.inputs.len() as u32,
            digital_out: self.outputs.len() as u32,
        }
    }

    fn initial_on(&self) -> Vec<bool> {
        self.initial_on.clone()
    }

    fn start(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Outcome, ChipError> {
        io.take_dirty();
        // The register map every later transfer assumes.
        bus.write_byte(IOCON_BANK1, 0)?;
        bus.write_byte(IOCON, 0)?;
        // Latches first: a pin that becomes an output drives what was asked from then on.
        self.write_outputs(bus, io)?;
        bus.write_word(IPOL, self.ipol)?;
        bus.write_word(GPPU, self.gppu)?;
        bus.write_word(IODIR, self.iodir)?;
        self.poll(bus, io)
    }

    fn poll(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Outcome, ChipError> {
        if !self.inputs.is_empty() {
            let gpio = bus.read_word(GPIO)?;
            for (bit, &p) in self.inputs.iter().enumerate() {
                io.set_input(bit as u32, gpio >> p & 1 == 1);
            }
        }
        if io.take_dirty()
            && let Err(e) = self.write_outputs(bus, io)
        {
            io.mark_dirty();
            return Err(e.into());
        }
        Ok(Outcome::Fresh)
    }

    fn check(&mut self, bus: &mut dyn Smbus, _: &ChipIo<'_>) -> Result<Option<Lost>, Transfer> {
        for (register, reg, wanted) in [
            ("IODIR", IODIR, self.iodir),
            ("IPOL", IPOL, self.ipol),
            ("GPPU", GPPU, self.gppu),
        ] {
            if let Some(lost) = Lost::compare(register, bus.read_word(reg)?, wanted) {
                return Ok(Some(lost));
            }
        }
        Ok(None)
    }
}
