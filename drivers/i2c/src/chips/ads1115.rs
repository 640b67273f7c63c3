//! Texas Instruments ADS1115, a 16-bit delta-sigma ADC with a programmable gain amplifier
//! and four inputs (single-ended or as pairs), converted one at a time in single-shot mode.
//!
//! | register | pointer | use |
//! |---|---|---|
//! | Conversion | 0x00 | the last result, two's complement |
//! | Config | 0x01 | OS (start / done), MUX (input), PGA (range), MODE = single-shot, DR (rate), comparator off |
//!
//! Both registers are big-endian on the wire while SMBus words are little-endian: every
//! word is byte-swapped. Each poll reads the conversion started by the previous poll (if
//! the chip says it is done; else it waits for the next poll) and starts the next
//! channel's, so a poll never waits for a conversion. A conversion still not done after
//! twice its time at the data rate (counted in polls) is a failed transfer, counted, and
//! is started again. A channel is `raw × range / 32768`
//! volts (range: the PGA's full scale; a single-ended input reads 0 V and up).

use super::{ChipModel, Shape, linear};
use crate::card::ChipIo;
use crate::config::{ADS1115_INPUTS, ADS1115_RANGES, ADS1115_RATES, Ads1115Config};
use crate::smbus::{Smbus, Transfer};
use device_interface::{RawRange, Scale};

const CONVERSION: u8 = 0x00;
const CONFIG: u8 = 0x01;
/// OS: written 1, starts a conversion; read 1, none under way.
const OS: u16 = 1 << 15;
/// MODE = single-shot, comparator queue disabled (COMP_QUE = 11).
const SINGLE_SHOT: u16 = 1 << 8 | 0b11;

/// An ADS1115.
pub struct Ads1115 {
    /// Each channel's config word (OS set), and its full scale in volts.
    channels: Vec<(u16, f64)>,
    /// The channel whose conversion was started last.
    current: Option<usize>,
    /// Polls that found it still converting.
    waited: u32,
    /// Polls it may take: twice a conversion's time, and one.
    patience: u32,
}

fn index<T: PartialEq>(all: &[T], x: &T) -> u16 {
    all.iter().position(|a| a == x).unwrap_or(0) as u16
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
        // A conversion takes 1/rate s (±10 %, the chip's oscillator).
        let polls = (2000.0 / f64::from(c.data_rate) / f64::from(c.poll_ms.max(1))).ceil();
        Ads1115 {
            channels,
            current: None,
            waited: 0,
            patience: polls as u32 + 1,
        }
    }

    fn begin(&mut self, bus: &mut dyn Smbus, channel: usize) -> Result<(), Transfer> {
        let Some((config, _)) = self.channels.get(channel) else {
            return Ok(());
        };
        bus.write_word(CONFIG, config.swap_bytes())?;
        self.current = Some(channel);
        self.waited = 0;
        Ok(())
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

    fn start(&mut self, bus: &mut dyn Smbus, _: &ChipIo<'_>) -> Result<(), Transfer> {
        self.current = None;
        self.begin(bus, 0)
    }

    fn poll(&mut self, bus: &mut dyn Smbus, io: &ChipIo<'_>) -> Result<(), Transfer> {
        let Some(k) = self.current else {
            return self.begin(bus, 0);
        };
        if bus.read_word(CONFIG)?.swap_bytes() & OS == 0 {
            self.waited += 1;
            if self.waited < self.patience {
                // Still converting: read it next poll.
                return Ok(());
            }
            let waited = self.waited;
            self.begin(bus, k)?;
            return Err(Transfer::Failed(format!(
                "channel {k}'s conversion not done after {waited} polls; started again"
            )));
        }
        let raw = bus.read_word(CONVERSION)?.swap_bytes() as i16;
        io.set_analog_in(k as u32, i64::from(raw));
        self.begin(bus, (k + 1) % self.channels.len().max(1))
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
            [0xc3e3, 0xbbe3]
        );
    }
}
