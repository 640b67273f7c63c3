//! A Firmata card's `[card.firmata]` section: the port, and which of the board's pins
//! become which device's channels.
//!
//! The section is checked alone at build (pins and channels in Firmata's bounds, no pin
//! twice) and against what the board says it has when its port opens
//! ([`FirmataConfig::check_board`]): each pin must offer the mode its list asks for, in the
//! resolution the section expects.
//!
//! ```
//! use driver_serial::config::FirmataConfig;
//!
//! let config: FirmataConfig = toml::from_str(r#"
//!     port = "/dev/ttyACM0"
//!     digital_in = [{ pin = 2 }, { pin = 4, pullup = true }]
//!     digital_out = [{ pin = 13, initial = false }]
//!     analog_in = [{ channel = 0 }, { channel = 1 }]
//!     pwm = [{ pin = 5, initial = 0.25 }]
//!     servo = [{ pin = 9, min_us = 600, max_us = 2400 }]
//! "#)?;
//! config.check()?;
//! assert_eq!(config.baud, 57600);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use crate::board::BoardInfo;
use crate::protocol::mode;
use driver_api::CardError;
use serde::Deserialize;

/// The highest pin number Firmata can address.
pub const MAX_PIN: u8 = 127;
/// The highest analog channel ANALOG_MESSAGE reports.
pub const MAX_CHANNEL: u8 = 15;
/// The most encoders the encoder feature numbers.
pub const MAX_ENCODERS: usize = 5;

/// A card's `[card.firmata]` section.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FirmataConfig {
    /// The serial port: a path (`/dev/ttyACM0`) or, better, a stable name
    /// (`/dev/serial/by-id/…`, or the project's udev rule's `/dev/hwgw/…`), opened anew at
    /// each reconnect.
    pub port: String,
    /// Baud rate (StandardFirmata: 57600).
    #[serde(default = "default_baud")]
    pub baud: u32,
    /// How long the board may take to start after its port opens (an Uno resets on DTR
    /// and sends its version when its firmware starts), ms; after it the version is asked.
    #[serde(default = "default_banner_ms")]
    pub banner_ms: u32,
    /// The board's analog reference, volts (an Uno's AVCC: 5.0).
    #[serde(default = "default_reference")]
    pub reference_volts: f64,
    /// How often the board samples and reports its analog inputs, ms (SAMPLING_INTERVAL).
    #[serde(default = "default_sampling_ms")]
    pub sampling_ms: u16,
    /// The resolution the analog inputs must report in, bits (the board's, checked).
    #[serde(default = "default_analog_bits")]
    pub analog_bits: u8,
    /// The resolution of the PWM outputs, bits (the board's, checked).
    #[serde(default = "default_pwm_bits")]
    pub pwm_bits: u8,
    /// DigitalIn bits, in order.
    #[serde(default)]
    pub digital_in: Vec<InputPin>,
    /// DigitalOut bits, in order.
    #[serde(default)]
    pub digital_out: Vec<OutputPin>,
    /// AnalogIn channels, in order: the board's analog channels (A0 = 0), in volts.
    #[serde(default)]
    pub analog_in: Vec<AnalogChannel>,
    /// AnalogOut channels, first: PWM pins, as a duty cycle 0–1.
    #[serde(default)]
    pub pwm: Vec<PwmPin>,
    /// AnalogOut channels, after the PWM pins: servo pins, as an angle 0–180 degrees.
    #[serde(default)]
    pub servo: Vec<ServoPin>,
    /// Quadrature encoders (firmware with the encoder feature), `card.encoder0`, ….
    #[serde(default)]
    pub encoder: Vec<EncoderPins>,
}

fn default_baud() -> u32 {
    57600
}
fn default_banner_ms() -> u32 {
    3000
}
fn default_reference() -> f64 {
    5.0
}
fn default_sampling_ms() -> u16 {
    19
}
fn default_analog_bits() -> u8 {
    10
}
fn default_pwm_bits() -> u8 {
    8
}

/// A digital input pin.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InputPin {
    /// The pin (Arduino numbering).
    pub pin: u8,
    /// The pull-up on (INPUT_PULLUP from protocol 2.5; before, a 1 written to the input).
    #[serde(default)]
    pub pullup: bool,
}

/// A digital output pin.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputPin {
    /// The pin.
    pub pin: u8,
    /// Written when the board is set up; without it, low (a Firmata board cannot say what
    /// an output is before it is one).
    #[serde(default)]
    pub initial: Option<bool>,
}

/// An analog input channel.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AnalogChannel {
    /// The channel (A0 = 0).
    pub channel: u8,
}

/// A PWM output pin.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PwmPin {
    /// The pin.
    pub pin: u8,
    /// The duty cycle written at set-up (0–1); without it, 0.
    #[serde(default)]
    pub initial: Option<f64>,
}

/// A servo output pin.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServoPin {
    /// The pin.
    pub pin: u8,
    /// The pulse at 0 degrees, µs (SERVO_CONFIG; the Servo library's default 544).
    #[serde(default = "default_min_us")]
    pub min_us: u16,
    /// The pulse at 180 degrees, µs (default 2400).
    #[serde(default = "default_max_us")]
    pub max_us: u16,
    /// The angle written at set-up; without it, 90.
    #[serde(default)]
    pub initial: Option<f64>,
}

fn default_min_us() -> u16 {
    544
}
fn default_max_us() -> u16 {
    2400
}

/// A quadrature encoder on two pins.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderPins {
    /// Channel A's pin.
    pub a: u8,
    /// Channel B's pin.
    pub b: u8,
    /// Counts per turn (may be negative: counting the other way).
    pub resolution: i64,
}

fn pin_bound(key: String, pin: u8) -> Result<(), CardError> {
    if pin > MAX_PIN {
        return Err(CardError::at(
            key,
            format!("pin {pin}: Firmata numbers pins 0-{MAX_PIN}"),
        ));
    }
    Ok(())
}

impl FirmataConfig {
    /// Checks the section alone: bounds, and no pin in two places.
    pub fn check(&self) -> Result<(), CardError> {
        self.check_line()?;
        self.check_pins()?;
        self.check_analog_in()
    }

    /// The port, the line's and the board's numbers.
    fn check_line(&self) -> Result<(), CardError> {
        if self.port.is_empty() || self.port.len() > 4096 || self.port.contains('\0') {
            return Err(CardError::at(
                "port",
                "a serial port's path (1-4096 bytes, no NUL)",
            ));
        }
        if !(300..=4_000_000).contains(&self.baud) {
            return Err(CardError::at("baud", format!("{}: 300-4000000", self.baud)));
        }
        if !(100..=60_000).contains(&self.banner_ms) {
            return Err(CardError::at(
                "banner_ms",
                format!("{}: 100-60000 ms", self.banner_ms),
            ));
        }
        if !(self.reference_volts.is_finite()
            && self.reference_volts > 0.0
            && self.reference_volts <= 100.0)
        {
            return Err(CardError::at(
                "reference_volts",
                format!("{}: above 0, at most 100 V", self.reference_volts),
            ));
        }
        if !(1..=16383).contains(&self.sampling_ms) {
            return Err(CardError::at(
                "sampling_ms",
                format!("{}: 1-16383 ms", self.sampling_ms),
            ));
        }
        for (key, bits) in [
            ("analog_bits", self.analog_bits),
            ("pwm_bits", self.pwm_bits),
        ] {
            if !(1..=16).contains(&bits) {
                return Err(CardError::at(key, format!("{bits}: 1-16 bits")));
            }
        }
        Ok(())
    }

    /// Every pin list: each pin in one place only, the outputs' values within bounds.
    fn check_pins(&self) -> Result<(), CardError> {
        let mut used: Vec<(u8, String)> = Vec::new();
        let mut claim = |key: String, pin: u8| -> Result<(), CardError> {
            pin_bound(key.clone(), pin)?;
            if let Some((_, other)) = used.iter().find(|(p, _)| *p == pin) {
                return Err(CardError::at(key, format!("pin {pin} is {other} already")));
            }
            used.push((pin, key));
            Ok(())
        };
        for (i, p) in self.digital_in.iter().enumerate() {
            claim(format!("digital_in[{i}].pin"), p.pin)?;
        }
        for (i, p) in self.digital_out.iter().enumerate() {
            claim(format!("digital_out[{i}].pin"), p.pin)?;
        }
        for (i, p) in self.pwm.iter().enumerate() {
            claim(format!("pwm[{i}].pin"), p.pin)?;
            if let Some(v) = p.initial
                && !(0.0..=1.0).contains(&v)
            {
                return Err(CardError::at(
                    format!("pwm[{i}].initial"),
                    format!("{v}: a duty cycle 0-1"),
                ));
            }
        }
        for (i, p) in self.servo.iter().enumerate() {
            claim(format!("servo[{i}].pin"), p.pin)?;
            if !(p.min_us < p.max_us && p.max_us <= 16383) {
                return Err(CardError::at(
                    format!("servo[{i}].max_us"),
                    format!(
                        "{}-{} µs: min_us below max_us, at most 16383",
                        p.min_us, p.max_us
                    ),
                ));
            }
            if let Some(v) = p.initial
                && !(0.0..=180.0).contains(&v)
            {
                return Err(CardError::at(
                    format!("servo[{i}].initial"),
                    format!("{v}: an angle 0-180"),
                ));
            }
        }
        if self.encoder.len() > MAX_ENCODERS {
            return Err(CardError::at(
                "encoder",
                format!(
                    "{} encoders: the encoder feature has {MAX_ENCODERS}",
                    self.encoder.len()
                ),
            ));
        }
        for (i, e) in self.encoder.iter().enumerate() {
            claim(format!("encoder[{i}].a"), e.a)?;
            claim(format!("encoder[{i}].b"), e.b)?;
            if e.resolution == 0 || e.resolution.unsigned_abs() > 1 << 28 {
                return Err(CardError::at(
                    format!("encoder[{i}].resolution"),
                    format!("{}: nonzero, at most 2^28 counts a turn", e.resolution),
                ));
            }
        }
        Ok(())
    }

    /// The analog inputs: channels Firmata reports, each once.
    fn check_analog_in(&self) -> Result<(), CardError> {
        let mut channels: Vec<u8> = Vec::new();
        for (i, c) in self.analog_in.iter().enumerate() {
            let key = format!("analog_in[{i}].channel");
            if c.channel > MAX_CHANNEL {
                return Err(CardError::at(
                    key,
                    format!("A{}: Firmata reports A0-A{MAX_CHANNEL}", c.channel),
                ));
            }
            if channels.contains(&c.channel) {
                return Err(CardError::at(
                    key,
                    format!("A{} is mapped already", c.channel),
                ));
            }
            channels.push(c.channel);
        }
        Ok(())
    }

    /// Checks the section against what the board says it has; the error names the pin,
    /// what it was asked for and what the board offers.
    pub fn check_board(&self, board: &BoardInfo) -> Result<(), CardError> {
        let need = |key: String, pin: u8, m: u8, bits: Option<u8>| -> Result<(), CardError> {
            match board.resolution(pin, m) {
                Some(r) if bits.is_none_or(|b| b == r) => Ok(()),
                Some(r) => Err(CardError::at(
                    key,
                    format!(
                        "pin {pin} is {} in {r} bits on this board, not {} bits (set {}_bits = {r})",
                        mode::name(m),
                        bits.unwrap_or(0),
                        if m == mode::PWM { "pwm" } else { "analog" }
                    ),
                )),
                None => Err(CardError::at(
                    key,
                    format!(
                        "pin {pin} cannot be {}: its modes are {} ({}; {} pins: {})",
                        mode::name(m),
                        board.modes_of(pin),
                        board.describe(),
                        mode::name(m),
                        board.pins_with(m)
                    ),
                )),
            }
        };
        for (i, p) in self.digital_in.iter().enumerate() {
            need(format!("digital_in[{i}].pin"), p.pin, mode::INPUT, None)?;
        }
        for (i, p) in self.digital_out.iter().enumerate() {
            need(format!("digital_out[{i}].pin"), p.pin, mode::OUTPUT, None)?;
        }
        for (i, p) in self.pwm.iter().enumerate() {
            need(
                format!("pwm[{i}].pin"),
                p.pin,
                mode::PWM,
                Some(self.pwm_bits),
            )?;
        }
        for (i, p) in self.servo.iter().enumerate() {
            need(format!("servo[{i}].pin"), p.pin, mode::SERVO, None)?;
        }
        for (i, e) in self.encoder.iter().enumerate() {
            need(format!("encoder[{i}].a"), e.a, mode::ENCODER, None)?;
            need(format!("encoder[{i}].b"), e.b, mode::ENCODER, None)?;
        }
        for (i, c) in self.analog_in.iter().enumerate() {
            let key = format!("analog_in[{i}].channel");
            let Some(pin) = board.analog_pin(c.channel) else {
                return Err(CardError::at(
                    key,
                    format!(
                        "the board has no A{} (its analog channels: {})",
                        c.channel,
                        board.channels()
                    ),
                ));
            };
            let other = self
                .digital_in
                .iter()
                .map(|p| p.pin)
                .chain(self.digital_out.iter().map(|p| p.pin))
                .chain(self.pwm.iter().map(|p| p.pin))
                .chain(self.servo.iter().map(|p| p.pin))
                .chain(self.encoder.iter().flat_map(|e| [e.a, e.b]))
                .any(|p| p == pin);
            if other {
                return Err(CardError::at(
                    key,
                    format!(
                        "A{} is pin {pin}, which the section uses already",
                        c.channel
                    ),
                ));
            }
            need(key, pin, mode::ANALOG, Some(self.analog_bits))?;
        }
        Ok(())
    }
}
