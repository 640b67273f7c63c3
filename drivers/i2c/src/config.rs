//! An I2C card's `[card.i2c]` section: the bus, and the chips on it with their settings.
//!
//! ```
//! use driver_i2c::config::{ChipConfig, I2cConfig};
//!
//! let config: I2cConfig = toml::from_str(r#"
//!     bus = "/dev/i2c-1"
//!     [[chip]]
//!     model = "mcp23017"
//!     address = 0x20
//!     inputs = [8, 9, 10]
//!     pull_up = [8]
//!     outputs = [0, 1]
//! "#)?;
//! let ChipConfig::Mcp23017(c) = &config.chip[0] else { panic!("an MCP23017") };
//! assert_eq!((c.address, c.poll_ms), (0x20, 10));
//! config.check()?;
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use device_interface::text::{Number, Quoted};
use serde::Deserialize;

/// The most chips one card polls (a 7-bit bus has 112 usable addresses; a bus with more
/// than this many chips wants more than one card anyway).
pub const MAX_CHIPS: usize = 32;
/// The shortest poll period, ms.
pub const MIN_POLL_MS: u32 = 1;
/// The longest poll period, ms (a minute).
pub const MAX_POLL_MS: u32 = 60_000;
/// The longest bus path or adapter name accepted, in bytes.
pub const MAX_NAME: usize = 255;
/// The 7-bit addresses a chip may have (0x00–0x07 and 0x78–0x7f are reserved by the I2C
/// specification).
pub const ADDRESSES: std::ops::RangeInclusive<u16> = 0x08..=0x77;

/// A card's `[card.i2c]` section.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct I2cConfig {
    /// The bus: its character device (`/dev/i2c-1`) or its adapter's name (as in
    /// `/sys/class/i2c-dev/i2c-N/name`).
    pub bus: String,
    /// The chips on it; their channels follow each other in this order on the card's
    /// devices.
    #[serde(default)]
    pub chip: Vec<ChipConfig>,
}

/// One chip: its model and that model's settings.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(tag = "model")]
pub enum ChipConfig {
    /// A Microchip MCP23017 16-bit IO expander.
    #[serde(rename = "mcp23017")]
    Mcp23017(Mcp23017Config),
    /// A Texas Instruments ADS1115 16-bit ADC.
    #[serde(rename = "ads1115")]
    Ads1115(Ads1115Config),
    /// A Microchip MCP4725 12-bit DAC.
    #[serde(rename = "mcp4725")]
    Mcp4725(Mcp4725Config),
    /// An ams AS5600 12-bit magnetic angle sensor.
    #[serde(rename = "as5600")]
    As5600(As5600Config),
    /// A Texas Instruments INA219 current and voltage monitor.
    #[serde(rename = "ina219")]
    Ina219(Ina219Config),
    /// An NXP PCA9685 16-channel 12-bit PWM controller.
    #[serde(rename = "pca9685")]
    Pca9685(Pca9685Config),
}

/// An INA219: three AnalogIn channels — shunt voltage (V), bus voltage (V) and current
/// (A, the chip's current register through the calibration written at start).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ina219Config {
    /// Its 7-bit address (0x40–0x4f by A1, A0).
    pub address: u16,
    /// Poll period, ms (default 10).
    #[serde(default = "default_poll_ms")]
    pub poll_ms: u32,
    /// The shunt resistor, ohms (default 0.1).
    #[serde(default = "default_shunt")]
    pub shunt_ohms: f64,
    /// The largest current to measure, amperes (default 3.2): sets the current LSB
    /// (max / 32768) and so the calibration.
    #[serde(default = "default_max_current")]
    pub max_current_a: f64,
}

fn default_shunt() -> f64 {
    0.1
}

fn default_max_current() -> f64 {
    3.2
}

/// A PCA9685: the channels given, each an AnalogOut duty cycle from 0 (off) to 1 (on), in
/// 4096 steps, at one PWM frequency for the chip.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Pca9685Config {
    /// Its 7-bit address (0x40–0x7f by A5..A0; 0x70 is its all-call address by default).
    pub address: u16,
    /// Poll period, ms (default 10): how often its set-up is read back. A written duty
    /// cycle is sent at once.
    #[serde(default = "default_poll_ms")]
    pub poll_ms: u32,
    /// PWM frequency, Hz (24 to 1526 with its 25 MHz oscillator).
    pub frequency_hz: f64,
    /// Its outputs (0..=15), in AnalogOut channel order; each starts off.
    pub channels: Vec<u8>,
}

/// The PCA9685's PWM frequencies, Hz (prescale 255 down to 3).
pub const PCA9685_FREQUENCY: std::ops::RangeInclusive<f64> = 24.0..=1526.0;

/// An AS5600: one Encoder (`card.encoderN`, numbered across the card's chips), 4096
/// counts a turn, turns counted across the wrap. Poll it faster than half a turn of the
/// fastest motion, or turns are miscounted.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct As5600Config {
    /// Its 7-bit address (0x36; the AS5600L's is programmable, 0x40 by default).
    pub address: u16,
    /// Poll period, ms (default 10).
    #[serde(default = "default_poll_ms")]
    pub poll_ms: u32,
    /// True when the position counts up as turns roll over forwards (default true).
    #[serde(default = "default_true")]
    pub upcounting: bool,
}

fn default_true() -> bool {
    true
}

/// An MCP4725: one AnalogOut channel, 0 V to its supply (the DAC's reference) in 4096
/// steps.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Mcp4725Config {
    /// Its 7-bit address (0x60–0x67: fixed bits by variant, A0 by pin).
    pub address: u16,
    /// Poll period, ms (default 10). A written value is sent at once; the code is sent
    /// again every half second (its check).
    #[serde(default = "default_poll_ms")]
    pub poll_ms: u32,
    /// Its supply, the full scale, in volts (2.7 to 5.5).
    pub vref_v: f64,
    /// The output from the start, in volts (default 0).
    #[serde(default)]
    pub initial_v: f64,
}

/// The MCP4725's supply range, volts.
pub const MCP4725_SUPPLY: std::ops::RangeInclusive<f64> = 2.7..=5.5;

/// An ADS1115: each channel an input (or pair) with its full-scale range, converted in
/// turn in single-shot mode; the card's AnalogIn channels, in the order given.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ads1115Config {
    /// Its 7-bit address (0x48–0x4b by its ADDR pin).
    pub address: u16,
    /// Poll period, ms (default 10): each poll reads the conversion started by the
    /// previous one and starts the next channel's.
    #[serde(default = "default_poll_ms")]
    pub poll_ms: u32,
    /// Conversions per second the chip runs at: 8, 16, 32, 64, 128, 250, 475 or 860
    /// (default 860; slower is quieter).
    #[serde(default = "default_data_rate")]
    pub data_rate: u32,
    /// The channels.
    #[serde(default)]
    pub channel: Vec<Ads1115Channel>,
}

fn default_data_rate() -> u32 {
    860
}

/// One ADS1115 channel.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ads1115Channel {
    /// `a0`..`a3` against ground, or a pair: `a0-a1`, `a0-a3`, `a1-a3`, `a2-a3`.
    pub input: String,
    /// Full-scale range in volts (the PGA): 6.144, 4.096, 2.048, 1.024, 0.512 or 0.256.
    pub range_v: f64,
}

/// The ADS1115's inputs, by their MUX code (config bits 14..12).
pub const ADS1115_INPUTS: [&str; 8] = ["a0-a1", "a0-a3", "a1-a3", "a2-a3", "a0", "a1", "a2", "a3"];
/// The ADS1115's full-scale ranges in volts, by their PGA code (bits 11..9).
pub const ADS1115_RANGES: [f64; 6] = [6.144, 4.096, 2.048, 1.024, 0.512, 0.256];
/// The ADS1115's data rates, by their DR code (bits 7..5).
pub const ADS1115_RATES: [u32; 8] = [8, 16, 32, 64, 128, 250, 475, 860];

fn default_poll_ms() -> u32 {
    10
}

/// An MCP23017: pins 0–7 are GPA0–7, pins 8–15 GPB0–7. Inputs are the card's DigitalIn
/// bits and outputs its DigitalOut bits, in the order given; pins in neither stay inputs.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Mcp23017Config {
    /// Its 7-bit address (0x20–0x27 by its A2..A0 pins).
    pub address: u16,
    /// Poll period, ms (default 10): inputs read and written outputs sent this often.
    #[serde(default = "default_poll_ms")]
    pub poll_ms: u32,
    /// Input pins, in DigitalIn bit order.
    #[serde(default)]
    pub inputs: Vec<u8>,
    /// Output pins, in DigitalOut bit order.
    #[serde(default)]
    pub outputs: Vec<u8>,
    /// Input pins with the chip's 100 kΩ pull-up on (GPPU).
    #[serde(default)]
    pub pull_up: Vec<u8>,
    /// Input pins read inverted by the chip (IPOL): on when the pin is low.
    #[serde(default)]
    pub invert: Vec<u8>,
    /// Output pins on from the start (written to OLAT before the pin becomes an output).
    #[serde(default)]
    pub initial_on: Vec<u8>,
}

/// A section that cannot work, and where.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{key}: {message}")]
pub struct ConfigError {
    /// The key, relative to the section (`chip[1].address`).
    pub key: String,
    /// What is wrong.
    pub message: String,
}

fn err(key: impl Into<String>, message: impl Into<String>) -> ConfigError {
    ConfigError {
        key: key.into(),
        message: message.into(),
    }
}

impl ChipConfig {
    /// Its address.
    pub fn address(&self) -> u16 {
        match self {
            ChipConfig::Mcp23017(c) => c.address,
            ChipConfig::Ads1115(c) => c.address,
            ChipConfig::Mcp4725(c) => c.address,
            ChipConfig::As5600(c) => c.address,
            ChipConfig::Ina219(c) => c.address,
            ChipConfig::Pca9685(c) => c.address,
        }
    }

    /// Its poll period, ms.
    pub fn poll_ms(&self) -> u32 {
        match self {
            ChipConfig::Mcp23017(c) => c.poll_ms,
            ChipConfig::Ads1115(c) => c.poll_ms,
            ChipConfig::Mcp4725(c) => c.poll_ms,
            ChipConfig::As5600(c) => c.poll_ms,
            ChipConfig::Ina219(c) => c.poll_ms,
            ChipConfig::Pca9685(c) => c.poll_ms,
        }
    }
}

impl I2cConfig {
    /// Checks what the types cannot say; the first problem, with its key.
    pub fn check(&self) -> Result<(), ConfigError> {
        if self.bus.is_empty() || self.bus.len() > MAX_NAME {
            return Err(err(
                "bus",
                format!("a path or adapter name of 1 to {MAX_NAME} bytes"),
            ));
        }
        if self.chip.len() > MAX_CHIPS {
            return Err(err(
                "chip",
                format!(
                    "{} chips; one card polls at most {MAX_CHIPS}",
                    self.chip.len()
                ),
            ));
        }
        for (i, c) in self.chip.iter().enumerate() {
            let key = |k: &str| format!("chip[{i}].{k}");
            if !ADDRESSES.contains(&c.address()) {
                return Err(err(
                    key("address"),
                    format!(
                        "{:#04x} is not a 7-bit chip address ({:#04x}..={:#04x})",
                        c.address(),
                        ADDRESSES.start(),
                        ADDRESSES.end()
                    ),
                ));
            }
            let pca9685 = |o: &ChipConfig| matches!(o, ChipConfig::Pca9685(_));
            if c.address() == PCA9685_ALL_CALL
                && !pca9685(c)
                && let Some(j) = self.chip.iter().position(pca9685)
            {
                return Err(err(
                    key("address"),
                    format!(
                        "{PCA9685_ALL_CALL:#04x} is the LED All Call address of the PCA9685 \
                         chip[{j}] (on by default): it would answer this chip's transfers too"
                    ),
                ));
            }
            if let Some(j) = self.chip[..i]
                .iter()
                .position(|o| o.address() == c.address())
            {
                return Err(err(
                    key("address"),
                    format!("{:#04x} is chip[{j}]'s address already", c.address()),
                ));
            }
            if !(MIN_POLL_MS..=MAX_POLL_MS).contains(&c.poll_ms()) {
                return Err(err(
                    key("poll_ms"),
                    format!(
                        "{} ms; between {MIN_POLL_MS} and {MAX_POLL_MS}",
                        c.poll_ms()
                    ),
                ));
            }
            match c {
                ChipConfig::Mcp23017(m) => m.check(),
                ChipConfig::Ads1115(a) => a.check(),
                ChipConfig::As5600(_) => Ok(()),
                ChipConfig::Ina219(i) => i.check(),
                ChipConfig::Pca9685(p) => p.check(),
                ChipConfig::Mcp4725(d) => d.check(),
            }
            .map_err(|e| err(key(&e.key), e.message))?;
        }
        Ok(())
    }
}

impl Ina219Config {
    fn check(&self) -> Result<(), ConfigError> {
        for (key, v) in [
            ("shunt_ohms", self.shunt_ohms),
            ("max_current_a", self.max_current_a),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= 1000.0) {
                return Err(err(key, format!("{}; above 0 and at most 1000", Number(v))));
            }
        }
        // The calibration register holds 2..=0xfffe (bit 0 is void).
        let cal = 0.04096 / (self.max_current_a / 32768.0 * self.shunt_ohms);
        if !(2.0..=65534.0).contains(&cal.trunc()) {
            return Err(err(
                "max_current_a",
                format!(
                    "{} A over {} Ω needs calibration {}; the INA219 takes 2 to 65534",
                    Number(self.max_current_a),
                    Number(self.shunt_ohms),
                    Number(cal.round())
                ),
            ));
        }
        Ok(())
    }
}

/// The PCA9685's LED All Call address at power-on: every PCA9685 on the bus answers it.
pub const PCA9685_ALL_CALL: u16 = 0x70;

impl Pca9685Config {
    fn check(&self) -> Result<(), ConfigError> {
        if self.address == PCA9685_ALL_CALL {
            return Err(err(
                "address",
                format!(
                    "{PCA9685_ALL_CALL:#04x} is the PCA9685's LED All Call address (on by \
                     default): every PCA9685 on the bus answers it, so a chip there cannot \
                     be told from the others; give the chip's own address (0x40-0x7f by its \
                     A5..A0 pins, not 0x70)"
                ),
            ));
        }
        if !PCA9685_FREQUENCY.contains(&self.frequency_hz) {
            return Err(err(
                "frequency_hz",
                format!("{} Hz; between 24 and 1526", Number(self.frequency_hz)),
            ));
        }
        for (n, &ch) in self.channels.iter().enumerate() {
            if ch > 15 {
                return Err(err(
                    format!("channels[{n}]"),
                    format!("output {ch}: the PCA9685 has outputs 0..=15"),
                ));
            }
            if self.channels[..n].contains(&ch) {
                return Err(err(
                    format!("channels[{n}]"),
                    format!("output {ch} is given twice"),
                ));
            }
        }
        Ok(())
    }
}

impl Mcp4725Config {
    fn check(&self) -> Result<(), ConfigError> {
        if !MCP4725_SUPPLY.contains(&self.vref_v) {
            return Err(err(
                "vref_v",
                format!(
                    "{} V; the MCP4725 runs on 2.7 to 5.5 V",
                    Number(self.vref_v)
                ),
            ));
        }
        if !(0.0..=self.vref_v).contains(&self.initial_v) {
            return Err(err(
                "initial_v",
                format!(
                    "{} V; between 0 and vref_v ({} V)",
                    Number(self.initial_v),
                    Number(self.vref_v)
                ),
            ));
        }
        Ok(())
    }
}

impl Mcp23017Config {
    fn check(&self) -> Result<(), ConfigError> {
        let mut seen = [None::<&str>; 16];
        for (what, pins) in [("inputs", &self.inputs), ("outputs", &self.outputs)] {
            for (n, &p) in pins.iter().enumerate() {
                let key = format!("{what}[{n}]");
                let Some(slot) = seen.get_mut(usize::from(p)) else {
                    return Err(err(key, format!("pin {p}: the MCP23017 has pins 0..=15")));
                };
                if let Some(other) = slot {
                    return Err(err(key, format!("pin {p} is in {other} already")));
                }
                *slot = Some(what);
            }
        }
        for (what, pins, must) in [
            ("pull_up", &self.pull_up, "inputs"),
            ("invert", &self.invert, "inputs"),
            ("initial_on", &self.initial_on, "outputs"),
        ] {
            for (n, &p) in pins.iter().enumerate() {
                if seen.get(usize::from(p)).copied().flatten() != Some(must) {
                    return Err(err(
                        format!("{what}[{n}]"),
                        format!("pin {p} is not one of the {must}"),
                    ));
                }
            }
        }
        Ok(())
    }
}

/// The most channels one ADS1115 section converts in turn.
pub const MAX_ADS1115_CHANNELS: usize = 8;

impl Ads1115Config {
    fn check(&self) -> Result<(), ConfigError> {
        if !ADS1115_RATES.contains(&self.data_rate) {
            return Err(err(
                "data_rate",
                format!("{} conversions/s; one of {ADS1115_RATES:?}", self.data_rate),
            ));
        }
        if self.channel.len() > MAX_ADS1115_CHANNELS {
            return Err(err(
                "channel",
                format!(
                    "{} channels; at most {MAX_ADS1115_CHANNELS}",
                    self.channel.len()
                ),
            ));
        }
        for (i, c) in self.channel.iter().enumerate() {
            if !ADS1115_INPUTS.contains(&c.input.as_str()) {
                return Err(err(
                    format!("channel[{i}].input"),
                    format!("{}; one of {}", Quoted(&c.input), ADS1115_INPUTS.join(", ")),
                ));
            }
            if !ADS1115_RANGES.contains(&c.range_v) {
                return Err(err(
                    format!("channel[{i}].range_v"),
                    format!("{} V; one of {ADS1115_RANGES:?}", Number(c.range_v)),
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;

    fn parse(text: &str) -> I2cConfig {
        toml::from_str(text).unwrap()
    }

    #[test]
    fn bad_sections_name_their_key() {
        let base = "bus = \"/dev/i2c-0\"\n[[chip]]\nmodel = \"mcp23017\"\n";
        for (body, key, words) in [
            ("address = 0x78", "chip[0].address", "not a 7-bit"),
            ("address = 0x20\npoll_ms = 0", "chip[0].poll_ms", "between"),
            (
                "address = 0x20\ninputs = [16]",
                "chip[0].inputs[0]",
                "0..=15",
            ),
            (
                "address = 0x20\ninputs = [1]\noutputs = [1]",
                "chip[0].outputs[0]",
                "in inputs",
            ),
            (
                "address = 0x20\noutputs = [1]\npull_up = [1]",
                "chip[0].pull_up[0]",
                "not one of the inputs",
            ),
            (
                "address = 0x20\ninputs = [2]\ninitial_on = [2]",
                "chip[0].initial_on[0]",
                "outputs",
            ),
        ] {
            let e = parse(&format!("{base}{body}")).check().unwrap_err();
            assert_eq!(e.key, key, "{body}: {e}");
            assert!(e.message.contains(words), "{body}: {e}");
        }
        let ads = "bus = \"/dev/i2c-0\"\n[[chip]]\nmodel = \"ads1115\"\naddress = 0x48\n";
        for (body, key, words) in [
            ("data_rate = 100", "chip[0].data_rate", "one of"),
            (
                "channel = [{ input = \"a4\", range_v = 4.096 }]",
                "chip[0].channel[0].input",
                "a0-a1",
            ),
            (
                "channel = [{ input = \"a0\", range_v = 5.0 }]",
                "chip[0].channel[0].range_v",
                "6.144",
            ),
        ] {
            let e = parse(&format!("{ads}{body}")).check().unwrap_err();
            assert_eq!(e.key, key, "{body}: {e}");
            assert!(e.message.contains(words), "{body}: {e}");
        }
        let pwm = "bus = \"/dev/i2c-0\"\n[[chip]]\nmodel = \"pca9685\"\nfrequency_hz = 200.0\nchannels = [0]\n";
        let e = parse(&format!("{pwm}address = 0x70")).check().unwrap_err();
        assert_eq!(e.key, "chip[0].address");
        assert!(
            e.message
                .starts_with("0x70 is the PCA9685's LED All Call address"),
            "{e}"
        );
        assert_eq!(parse(&format!("{pwm}address = 0x40")).check(), Ok(()));
        let other = format!("{pwm}address = 0x41\n[[chip]]\nmodel = \"ads1115\"\naddress = 0x70\n");
        let e = parse(&other).check().unwrap_err();
        assert_eq!(e.key, "chip[1].address");
        assert!(
            e.message
                .contains("All Call address of the PCA9685 chip[0]"),
            "{e}"
        );
        let two = format!("{base}address = 0x20\n[[chip]]\nmodel = \"mcp23017\"\naddress = 0x20\n");
        assert_eq!(parse(&two).check().unwrap_err().key, "chip[1].address");
    }

    #[test]
    fn unknown_models_and_keys_are_refused() {
        let e =
            toml::from_str::<I2cConfig>("bus = \"x\"\n[[chip]]\nmodel = \"mcp9999\"\naddress = 1")
                .unwrap_err();
        assert!(e.to_string().contains("mcp23017"), "{e}");
        let e = toml::from_str::<I2cConfig>(
            "bus = \"x\"\n[[chip]]\nmodel = \"mcp23017\"\naddress = 32\npullup = [1]",
        )
        .unwrap_err();
        assert!(e.to_string().contains("pullup"), "{e}");
    }
}
