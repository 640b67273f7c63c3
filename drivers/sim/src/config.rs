//! The sim card's configuration: its section of a hwgw config file.
//!
//! ```
//! use driver_sim::SimConfig;
//!
//! let config: SimConfig = toml::from_str(r#"
//!     seed = 7
//!     digital_inputs = 8
//!     digital_outputs = 8
//!     digital_loopback = true
//!
//!     [[analog_in]]
//!     count = 2
//!     range = { lowest = -10.0, highest = 10.0, unit = "V" }
//!     waveform = { kind = "sine", amplitude = 5.0, frequency = 0.5 }
//!
//!     [[analog_out]]
//!     range = { lowest = 0.0, highest = 10.0, unit = "V" }
//!
//!     [[encoder]]
//!     resolution = 4096
//!     velocity_from = 0
//!     counts_per_unit = 1000.0
//! "#)?;
//! assert_eq!(config.analog_in[0].count, 2);
//! # Ok::<(), toml::de::Error>(())
//! ```

use device_interface::{RawRange, Scale, ScaleError, Unit};
use serde::Deserialize;

/// A simulated card: channel groups, digital bits, encoders, and test options.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimConfig {
    /// Seed of the noise waveforms: the same seed gives the same noise at the same times.
    #[serde(default)]
    pub seed: u64,
    /// Analog input channels, in groups of identical channels, numbered in order.
    #[serde(default)]
    pub analog_in: Vec<AnalogInConfig>,
    /// Analog output channels, in groups, numbered in order.
    #[serde(default)]
    pub analog_out: Vec<AnalogOutConfig>,
    /// Number of digital inputs.
    #[serde(default)]
    pub digital_inputs: u32,
    /// Number of digital outputs.
    #[serde(default)]
    pub digital_outputs: u32,
    /// Drive digital input n from digital output n (for every n both have) at each step.
    #[serde(default)]
    pub digital_loopback: bool,
    /// Simulated encoders.
    #[serde(default)]
    pub encoder: Vec<EncoderConfig>,
    /// Digital inputs switched by an encoder's travel (home and limit switches).
    #[serde(default)]
    pub switch: Vec<crate::switch::SwitchConfig>,
    /// Keep a record of up to this many output writes for tests to read back (0: off).
    #[serde(default)]
    pub record_capacity: usize,
}

/// A group of identical analog input channels.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AnalogInConfig {
    /// How many channels the group has.
    #[serde(default = "one")]
    pub count: u32,
    /// Physical range and unit.
    pub range: RangeConfig,
    /// Raw range of the simulated converter (default: 16-bit unsigned).
    #[serde(default = "raw16")]
    pub raw: RawRange,
    /// What the channels read.
    pub waveform: Waveform,
}

/// A group of identical analog output channels.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AnalogOutConfig {
    /// How many channels the group has.
    #[serde(default = "one")]
    pub count: u32,
    /// Physical range and unit.
    pub range: RangeConfig,
    /// Raw range of the simulated converter (default: 16-bit unsigned).
    #[serde(default = "raw16")]
    pub raw: RawRange,
    /// Value before the first write (default: the value nearest to 0 in the range).
    #[serde(default)]
    pub initial: Option<f64>,
}

/// Physical range and unit of a channel.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RangeConfig {
    /// Lowest value.
    pub lowest: f64,
    /// Highest value.
    pub highest: f64,
    /// Unit ("V", "mA", "degC"; empty: dimensionless).
    #[serde(default)]
    pub unit: String,
}

impl RangeConfig {
    /// The scale mapping `raw` onto this range.
    pub fn scale(&self, raw: RawRange) -> Result<Scale, ScaleError> {
        Scale::linear(raw, self.lowest, self.highest, Unit::new(&self.unit)?)
    }
}

/// What a simulated analog input reads over time (`t` in seconds since the card started).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Waveform {
    /// Always `value`.
    Constant {
        /// The value.
        value: f64,
    },
    /// `offset + amplitude * sin(2 pi frequency t + phase)`.
    Sine {
        /// Peak deviation from the offset.
        amplitude: f64,
        /// Frequency in Hz.
        frequency: f64,
        /// Centre value.
        #[serde(default)]
        offset: f64,
        /// Phase in radians.
        #[serde(default)]
        phase: f64,
    },
    /// A sawtooth from `from` to `to`, repeating every `period` seconds.
    Ramp {
        /// Value at the start of each period.
        from: f64,
        /// Value approached at the end of each period.
        to: f64,
        /// Period in seconds.
        period: f64,
    },
    /// Uniform noise in `mean ± amplitude`, from the card's seed: repeatable.
    Noise {
        /// Centre value.
        #[serde(default)]
        mean: f64,
        /// Half-width of the distribution.
        amplitude: f64,
    },
    /// The value last written to analog output `analog_out` of the same card.
    Loopback {
        /// The analog output channel read back.
        analog_out: u32,
    },
}

/// A simulated encoder.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderConfig {
    /// Counts per turn; negative for positions running from `resolution+1` to 0.
    pub resolution: i64,
    /// True when positive motion raises the position.
    #[serde(default = "yes")]
    pub upcounting: bool,
    /// Analog output channel whose value is the velocity; none: the encoder only moves when
    /// a test moves it.
    #[serde(default)]
    pub velocity_from: Option<u32>,
    /// Counts per second per unit of the velocity output's value.
    #[serde(default = "one_f64")]
    pub counts_per_unit: f64,
}

fn one() -> u32 {
    1
}

fn one_f64() -> f64 {
    1.0
}

fn yes() -> bool {
    true
}

fn raw16() -> RawRange {
    RawRange { min: 0, max: 65535 }
}

impl SimConfig {
    /// The demonstration card hwgw runs when given no configuration: four analog inputs
    /// (a sine, a ramp, noise, and a loopback of output 0), two analog outputs, eight digital
    /// inputs looped back from eight digital outputs, and an encoder driven by output 1.
    pub fn demo() -> SimConfig {
        let volts = |lowest: f64, highest: f64| RangeConfig {
            lowest,
            highest,
            unit: "V".into(),
        };
        let input = |waveform| AnalogInConfig {
            count: 1,
            range: volts(-10.0, 10.0),
            raw: raw16(),
            waveform,
        };
        SimConfig {
            seed: 1,
            analog_in: vec![
                input(Waveform::Sine {
                    amplitude: 5.0,
                    frequency: 0.5,
                    offset: 0.0,
                    phase: 0.0,
                }),
                input(Waveform::Ramp {
                    from: -10.0,
                    to: 10.0,
                    period: 4.0,
                }),
                input(Waveform::Noise {
                    mean: 1.0,
                    amplitude: 0.05,
                }),
                input(Waveform::Loopback { analog_out: 0 }),
            ],
            analog_out: vec![AnalogOutConfig {
                count: 2,
                range: volts(-10.0, 10.0),
                raw: raw16(),
                initial: None,
            }],
            digital_inputs: 8,
            digital_outputs: 8,
            digital_loopback: true,
            encoder: vec![EncoderConfig {
                resolution: 4096,
                upcounting: true,
                velocity_from: Some(1),
                counts_per_unit: 1000.0,
            }],
            switch: Vec::new(),
            record_capacity: 0,
        }
    }
}
