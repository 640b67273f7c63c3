//! Texas Instruments ADS1115, a 16-bit delta-sigma ADC with a programmable gain amplifier
//! and four inputs (single-ended or as pairs), converted one at a time in single-shot mode.
//!
//! | register | pointer | use |
//! |---|---|---|
//! | Conversion | 0x00 | the last result, two's complement (0 after power-on) |
//! | Config | 0x01 | OS (start / done), MUX (input), PGA (range), MODE = single-shot, DR (rate), comparator off (COMP_QUE = 11) and COMP_LAT set (below); 0x8583 after power-on |
//!
//! Both registers are big-endian on the wire while SMBus words are little-endian: every
//! word is byte-swapped. Each poll reads the conversion started by the previous poll (if
//! the chip says it is done; else it waits for the next poll) and starts the next
//! channel's, so a poll never waits for a conversion. A channel is `raw × range / 32768`
//! volts (range: the PGA's full scale; a single-ended input reads 0 V and up).
//!
//! # A reset
//!
//! Every poll reads Config (for OS) before the result: Config not as hwgw wrote it for the
//! channel (OS aside) is a reset (power-on value 0x8583) or another master, answered as
//! [`Outcome::Reset`] before the Conversion register is read — its 0 after power-on is
//! never published — and the conversion is started again. COMP_LAT is set in every word
//! hwgw writes so none equals the power-on value (a0-a1 at ±2.048 V and 128/s would): the
//! comparator is disabled (COMP_QUE = 11, ALERT/RDY high-impedance), so the latch bit
//! changes nothing, and a chip back at its power-on Config always reads otherwise. A result
//! of exactly 0 (what a reset leaves) has Config read once more after it, so a reset
//! between the two reads is caught too.
//!
//! # A stuck converter
//!
//! OS reads 0 while a conversion is under way. One not done within
//! [`conversion_deadline`] of the longest conversion at the data rate (`1.1 / rate` s: the
//! internal oscillator is within ±10 %) fails the poll ([`ChipError::NotConverting`]),
//! counted; each further deadline that passes with OS still 0 fails another, so the chip
//! goes offline by the bus side's rule (three failed polls in a row) and stays offline
//! while it is stuck. It is not started again meanwhile: writing OS during a conversion
//! "has no effect" (datasheet), and `start` (at each probe) waits on a conversion of ours
//! it finds under way instead of writing. What the chip reads is what counts: a result
//! that stays the same is not taken for a stuck converter — a steady input, one beyond the
//! range (0x7FFF / 0x8000) or a quiet one at a low gain gives the same code conversion
//! after conversion on a healthy chip, and nothing in the datasheet tells those apart from
//! a chip that stopped converting but still says it finished (i2c-stub, whose register
//! file never converts, reads that way too).

use super::{ChipError, ChipModel, Lost, Outcome, Shape, conversion_deadline, linear};
use crate::card::ChipIo;
use crate::config::{ADS1115_INPUTS, ADS1115_RANGES, ADS1115_RATES, Ads1115Config};
use crate::smbus::{Smbus, Transfer};
use device_interface::time::Timestamp;
use device_interface::{RawRange, Scale};
use std::time::Duration;

const CONVERSION: u8 = 0x00;
const CONFIG: u8 = 0x01;
/// OS: written 1, starts a conversion; read 1, none under way.
const OS: u16 = 1 << 15;
/// MODE = single-shot, comparator queue disabled (COMP_QUE = 11), and COMP_LAT, which
/// does nothing while the comparator is disabled but makes every word hwgw writes differ
/// from the power-on value.
const SINGLE_SHOT: u16 = 1 << 8 | 1 << 2 | 0b11;
/// Config after power-on (the datasheet's reset value).
pub const POWER_ON: u16 = 0x8583;

/// An ADS1115.
pub struct Ads1115 {
    /// Each channel's config word (OS set), and its full scale in volts.
    channels: Vec<(u16, f64)>,
    /// The channel whose conversion is under way, and since when it is waited for (its
    /// start, or the last time it was found overdue).
    converting: Option<(usize, Timestamp)>,
    /// The channel to convert next.
    next: usize,
    /// The longest a conversion takes at the data rate.
    takes: Duration,
}

fn index<T: PartialEq>(all: &[T], x: &T) -> u16 {
    all.iter().position(|a| a == x).unwrap_or(0) as u16
}

/// Whether two config words set the same conversion (OS aside: it starts one, or says
/// whether one is under way).
fn same(a: u16, b: u16) -> bool {
    (a ^ b) & !OS == 0
}

impl Ads1115 {
    /// The model of a (checked) section.
    pub fn new(c: &Ads1115Config) -> Ads1115 {
        let dr = index(&ADS1115_RATES, &c.data_rate);
        let channels = c
            .channel
            .iter()
            .map(|ch| {
                let mux = index(&ADS1115_INPUTS, &ch.input.as_str());
                let pga = index(&ADS1115_RANGES, &ch.range_v);
                (
                    OS | mux << 12 | pga << 9 | SINGLE_SHOT | dr << 5,
                    ch.range_v,
                )
            })
            .collect();
        Ads1115 {
            channels,
            converting: None,
            next: 0,
            // A conversion takes 1/rate s, ±10 % (the chip's oscillator).
            takes: Duration::from_nanos(1_100_000_000 / u64::from(c.data_rate.max(1))),
        }
    }

    /// Starts channel `k`'s conversion.
    fn begin(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>, k: usize) -> Result<(), Transfer> {
        self.converting = None;
        let Some((config, _)) = self.channels.get(k) else {
            return Ok(());
        };
        bus.write_word(CONFIG, config.swap_bytes())?;
        // After the write: the chip has had at least the time since then.
        self.converting = Some((k, io.now()));
        Ok(())
    }

    fn config(bus: &mut dyn Smbus) -> Result<u16, Transfer> {
        Ok(bus.read_word(CONFIG)?.swap_bytes())
    }
}

impl ChipModel for Ads1115 {
    fn model(&self) -> &'static str {
        "ads1115"
    }

    fn shape(&self) -> Shape {
        Shape::default()
    }

    fn analog_in(&self) -> Vec<Scale> {
        self.channels
            .iter()
            .filter_map(|(_, fs)| linear(RawRange::signed_bits(16), fs / 32768.0, "V"))
            .collect()
    }

    fn start(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Outcome, ChipError> {
        let found = Self::config(bus)?;
        if found & OS == 0
            && let Some(k) = self.channels.iter().position(|(w, _)| same(*w, found))
        {
            // A conversion of ours under way (started before a dropout, or still not done
            // after a stuck spell): a write would not start another; wait for it.
            self.converting = Some((k, io.now()));
            return Ok(Outcome::Pending);
        }
        // The channel that was converting (a reset lost it), else the next one; its result
        // is read at a later poll (one found done here may be from long ago).
        let k = self.converting.map_or(self.next, |(k, _)| k);
        self.begin(bus, io, k)?;
        Ok(Outcome::Pending)
    }

    fn poll(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<Outcome, ChipError> {
        let Some((k, since)) = self.converting else {
            self.begin(bus, io, self.next)?;
            return Ok(Outcome::Pending);
        };
        let Some(&(wanted, _)) = self.channels.get(k) else {
            return Ok(Outcome::Fresh);
        };
        let found = Self::config(bus)?;
        if !same(found, wanted) {
            return Ok(Outcome::Reset(Lost {
                register: "config",
                found,
                wanted,
            }));
        }
        if found & OS == 0 {
            let now = io.now();
            let within = conversion_deadline(self.takes);
            if now.duration_since(since) < within {
                // Still converting: read it at a later poll.
                return Ok(Outcome::Pending);
            }
            self.converting = Some((k, now));
            return Err(ChipError::NotConverting {
                channel: Some(k as u32),
                flag: "OS stays 0",
                takes: self.takes,
                within,
            });
        }
        let raw = bus.read_word(CONVERSION)?.swap_bytes() as i16;
        if raw == 0 {
            // What a reset leaves: was the chip still set up after the read?
            let again = Self::config(bus)?;
            if !same(again, wanted) {
                return Ok(Outcome::Reset(Lost {
                    register: "config",
                    found: again,
                    wanted,
                }));
            }
        }
        io.set_analog_in(k as u32, i64::from(raw));
        self.next = (k + 1) % self.channels.len().max(1);
        self.begin(bus, io, self.next)?;
        Ok(Outcome::Fresh)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;
    use crate::config::Ads1115Channel;

    #[test]
    fn each_channel_has_its_scale_and_config_word() {
        let a = Ads1115::new(&Ads1115Config {
            address: 0x48,
            poll_ms: 5,
            data_rate: 860,
            channel: vec![
                Ads1115Channel {
                    input: "a0".into(),
                    range_v: 4.096,
                },
                Ads1115Channel {
                    input: "a2-a3".into(),
                    range_v: 0.256,
                },
            ],
        });
        let scales = a.analog_in();
        assert_eq!(scales.len(), 2);
        assert_eq!(scales[0].to_physical(16384), 2.048);
        assert_eq!(scales[1].to_physical(-32768), -0.256);
        assert_eq!(
            a.channels.iter().map(|c| c.0).collect::<Vec<_>>(),
            [0xc3e7, 0xbbe7]
        );
    }
}
