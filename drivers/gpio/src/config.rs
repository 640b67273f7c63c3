//! A GPIO card's `[card.gpio]` section: which lines, and how each is requested.
//!
//! A line is given by its offset on a chip (`line = 3`, on the section's `chip` or its
//! own) or by the name the kernel gives it (`line = "button"`, searched across every
//! chip, or only on `chip` when one is given). A chip is a path (`/dev/gpiochip0`), a
//! name (`gpiochip0`) or a label (`gpio-sim.0-node0`, `pinctrl-bcm2711`).
//!
//! ```
//! use driver_gpio::config::{Bias, GpioConfig, LineRef};
//!
//! let config: GpioConfig = toml::from_str(r#"
//!     chip = "gpiochip0"
//!     input = [{ line = "button", bias = "pull-up", active_low = true, debounce_us = 5000 }]
//!     output = [{ line = 4, drive = "open-drain", initial = true }]
//!     encoder = [{ a = 6, b = 7, resolution = 2048 }]
//! "#)?;
//! assert_eq!(config.input[0].line, LineRef::Name("button".into()));
//! assert_eq!(config.input[0].bias, Bias::PullUp);
//! config.check()?;
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use serde::Deserialize;

/// The most lines one card requests (the kernel's limit for one request, `GPIO_V2_LINES_MAX`).
pub const MAX_LINES: usize = 64;
/// The deepest kernel event buffer a request may ask for (the kernel's own cap: 16 events
/// per line of a full request).
pub const MAX_EVENT_BUFFER: u32 = 16 * MAX_LINES as u32;
/// The longest debounce period accepted, in µs (one second: longer is a filter, not a
/// debounce, and the kernel's software debouncer holds a timer per line for it).
pub const MAX_DEBOUNCE_US: u32 = 1_000_000;
/// The longest chip, line or consumer name accepted, in bytes (the kernel's names are at
/// most 31; a path may be longer).
pub const MAX_NAME: usize = 255;

/// A card's `[card.gpio]` section.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GpioConfig {
    /// The chip of lines given by offset: a path, a name or a label.
    #[serde(default)]
    pub chip: Option<String>,
    /// The consumer name the kernel shows for the card's lines (default `hwgw`).
    #[serde(default = "default_consumer")]
    pub consumer: String,
    /// Edge events the kernel buffers per chip before it drops the oldest (default:
    /// 16 per requested line, at most 1024).
    #[serde(default)]
    pub event_buffer: Option<u32>,
    /// DigitalIn bits, in order.
    #[serde(default)]
    pub input: Vec<InputLine>,
    /// DigitalOut bits, in order.
    #[serde(default)]
    pub output: Vec<OutputLine>,
    /// Quadrature encoders decoded in software, in order (`card.encoder0`, …).
    #[serde(default)]
    pub encoder: Vec<EncoderLines>,
}

fn default_consumer() -> String {
    "hwgw".into()
}

/// A line: an offset on a chip, or a line name.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Deserialize)]
#[serde(untagged)]
pub enum LineRef {
    /// The line at this offset.
    Offset(u32),
    /// The line the kernel calls this.
    Name(String),
}

impl std::fmt::Display for LineRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LineRef::Offset(o) => write!(f, "line {o}"),
            LineRef::Name(n) => write!(f, "line {n:?}"),
        }
    }
}

/// A line's bias.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Bias {
    /// Leave the bias as the chip has it.
    #[default]
    AsIs,
    /// Pull-up.
    PullUp,
    /// Pull-down.
    PullDown,
    /// Neither.
    Disabled,
}

/// Which edges of an input are events.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Edges {
    /// Both (the default: the card's state of the line follows the events).
    #[default]
    Both,
    /// Rising edges only (the line's state is read from the chip).
    Rising,
    /// Falling edges only (the line's state is read from the chip).
    Falling,
    /// No events: the line is read from the chip at each `read_bit`.
    None,
}

/// How an output drives its line.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Drive {
    /// Drives both levels.
    #[default]
    PushPull,
    /// Drives low only; high is left to a pull-up.
    OpenDrain,
    /// Drives high only; low is left to a pull-down.
    OpenSource,
}

/// One DigitalIn bit.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InputLine {
    /// The line.
    pub line: LineRef,
    /// Its chip, instead of the section's.
    #[serde(default)]
    pub chip: Option<String>,
    /// Bias (default: as is).
    #[serde(default)]
    pub bias: Bias,
    /// The bit is on when the line is low.
    #[serde(default)]
    pub active_low: bool,
    /// Debounce period in µs (0: none). The kernel debounces in software where the chip
    /// cannot.
    #[serde(default)]
    pub debounce_us: u32,
    /// Which edges are events (default both).
    #[serde(default)]
    pub edges: Edges,
}

/// One DigitalOut bit.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputLine {
    /// The line.
    pub line: LineRef,
    /// Its chip, instead of the section's.
    #[serde(default)]
    pub chip: Option<String>,
    /// Drive (default push-pull).
    #[serde(default)]
    pub drive: Drive,
    /// Bias (default: as is).
    #[serde(default)]
    pub bias: Bias,
    /// The line is low when the bit is on.
    #[serde(default)]
    pub active_low: bool,
    /// The bit's value from the moment the line is requested (default off).
    #[serde(default)]
    pub initial: bool,
}

/// A quadrature encoder: two lines (A, B) and an optional index, decoded from their edges
/// (every edge counts: 4 counts per cycle of A).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderLines {
    /// Line A.
    pub a: LineRef,
    /// Line B.
    pub b: LineRef,
    /// An index line: its rising edge sets the position to 0 (keeping the turn).
    #[serde(default)]
    pub index: Option<LineRef>,
    /// The chip of all three, instead of the section's.
    #[serde(default)]
    pub chip: Option<String>,
    /// Counts per turn.
    pub resolution: i64,
    /// Counting up when A leads B (default true).
    #[serde(default = "yes")]
    pub upcounting: bool,
    /// Bias of the lines (default: as is).
    #[serde(default)]
    pub bias: Bias,
    /// The lines are active low.
    #[serde(default)]
    pub active_low: bool,
    /// Debounce period of the lines in µs (0: none).
    #[serde(default)]
    pub debounce_us: u32,
}

fn yes() -> bool {
    true
}

/// A section that cannot be a card: the key it is about and what is wrong.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{key}: {message}")]
pub struct ConfigError {
    /// The key under the section (`input[2].debounce_us`).
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

impl GpioConfig {
    /// Every line of the section with its key, chip and role, in channel order: inputs,
    /// outputs, then each encoder's A, B and index.
    pub fn lines(&self) -> Vec<(String, Option<&str>, &LineRef)> {
        let section = self.chip.as_deref();
        let mut all = Vec::new();
        for (i, l) in self.input.iter().enumerate() {
            all.push((
                format!("input[{i}].line"),
                l.chip.as_deref().or(section),
                &l.line,
            ));
        }
        for (i, l) in self.output.iter().enumerate() {
            all.push((
                format!("output[{i}].line"),
                l.chip.as_deref().or(section),
                &l.line,
            ));
        }
        for (i, e) in self.encoder.iter().enumerate() {
            let chip = e.chip.as_deref().or(section);
            all.push((format!("encoder[{i}].a"), chip, &e.a));
            all.push((format!("encoder[{i}].b"), chip, &e.b));
            if let Some(x) = &e.index {
                all.push((format!("encoder[{i}].index"), chip, x));
            }
        }
        all
    }

    /// Checks what can be checked without the kernel: limits, names, debounce periods,
    /// resolutions.
    pub fn check(&self) -> Result<(), ConfigError> {
        if self.consumer.is_empty() || self.consumer.len() > 31 {
            return Err(err(
                "consumer",
                format!(
                    "{:?}: a consumer name is 1 to 31 bytes (the kernel keeps 31)",
                    self.consumer
                ),
            ));
        }
        if let Some(n) = self.event_buffer
            && !(1..=MAX_EVENT_BUFFER).contains(&n)
        {
            return Err(err(
                "event_buffer",
                format!("{n}: the kernel buffers 1 to {MAX_EVENT_BUFFER} events per request"),
            ));
        }
        if let Some(c) = &self.chip {
            check_name("chip", c)?;
        }
        let lines = self.lines();
        if lines.is_empty() {
            return Err(err(
                "input",
                "the card has no lines: give input, output or encoder lines",
            ));
        }
        if lines.len() > MAX_LINES {
            return Err(err(
                "input",
                format!(
                    "{} lines; a card takes at most {MAX_LINES} (the kernel's limit per request)",
                    lines.len()
                ),
            ));
        }
        for (key, chip, line) in &lines {
            if let Some(c) = chip {
                check_name(key, c)?;
            }
            if let LineRef::Name(n) = line {
                check_name(key, n)?;
            }
            if chip.is_none() && matches!(line, LineRef::Offset(_)) {
                return Err(err(
                    key.clone(),
                    format!(
                        "{line} on which chip? Give `chip` (a path, name or label) or a line name"
                    ),
                ));
            }
        }
        let debounce = self
            .input
            .iter()
            .enumerate()
            .map(|(i, l)| (format!("input[{i}].debounce_us"), l.debounce_us))
            .chain(
                self.encoder
                    .iter()
                    .enumerate()
                    .map(|(i, e)| (format!("encoder[{i}].debounce_us"), e.debounce_us)),
            );
        for (key, us) in debounce {
            if us > MAX_DEBOUNCE_US {
                return Err(err(
                    key,
                    format!("{us} µs: a debounce period is at most {MAX_DEBOUNCE_US} µs"),
                ));
            }
        }
        for (i, e) in self.encoder.iter().enumerate() {
            if e.resolution < 1 {
                return Err(err(
                    format!("encoder[{i}].resolution"),
                    format!("{}: counts per turn must be at least 1", e.resolution),
                ));
            }
        }
        Ok(())
    }
}

fn check_name(key: &str, name: &str) -> Result<(), ConfigError> {
    if name.is_empty() || name.len() > MAX_NAME || name.contains('\0') {
        return Err(err(
            key,
            format!("{name:?}: a name or path is 1 to {MAX_NAME} bytes, without NUL"),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;

    fn parse(s: &str) -> GpioConfig {
        toml::from_str(s).unwrap()
    }

    #[test]
    fn limits_name_their_key() {
        let c = parse("chip = \"c\"\ninput = [{ line = 1, debounce_us = 2000000 }]");
        assert_eq!(c.check().unwrap_err().key, "input[0].debounce_us");
        let c = parse("input = [{ line = 1 }]");
        let e = c.check().unwrap_err();
        assert_eq!(e.key, "input[0].line");
        assert!(e.message.contains("which chip"), "{e}");
        let c = parse("chip = \"c\"\nencoder = [{ a = 1, b = 2, resolution = 0 }]");
        assert_eq!(c.check().unwrap_err().key, "encoder[0].resolution");
        let c = parse("chip = \"c\"\nevent_buffer = 5000\noutput = [{ line = 1 }]");
        assert_eq!(c.check().unwrap_err().key, "event_buffer");
        let many: Vec<String> = (0..65).map(|i| format!("{{ line = {i} }}")).collect();
        let c = parse(&format!("chip = \"c\"\ninput = [{}]", many.join(", ")));
        assert!(c.check().unwrap_err().message.contains("at most 64"));
        assert!(parse("").check().is_err());
    }

    #[test]
    fn unknown_keys_and_values_are_refused() {
        assert!(toml::from_str::<GpioConfig>("input = [{ line = 1, pull = \"up\" }]").is_err());
        assert!(toml::from_str::<GpioConfig>("input = [{ line = 1, bias = \"up\" }]").is_err());
        assert!(toml::from_str::<GpioConfig>("output = [{ line = -1 }]").is_err());
    }
}
