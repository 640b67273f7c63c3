//! The deployment file: cards, aliases, ThreadScope, components and connections, in TOML.
//!
//! Parsing is strict — unknown keys are errors — and every error names the file, line,
//! column and key path and says what was expected.
//! [`Gateway::build`](crate::deploy::Gateway::build) then validates what the types cannot:
//! unique names, known drivers and component types, properties, connection ends that
//! exist — with the same locations.
//!
//! ```
//! use hwgw::config::Deployment;
//!
//! let text = r#"
//!     [[card]]
//!     name = "sim0"
//!     driver = "sim"
//!     [card.sim]
//!     digital_outputs = 8
//!
//!     [[component]]
//!     name = "blink"
//!     type = "blinker"
//!     activity = { type = "periodic", period_ms = 500 }
//!     properties = { device = "sim0", bit = 3 }
//! "#;
//! let d = Deployment::parse(text, "example.toml")?;
//! assert_eq!(d.cards[0].name, "sim0");
//! # Ok::<(), hwgw::config::ConfigError>(())
//! ```

use driver_sim::SimConfig;
use rtt::port::ConnPolicy;
use serde::Deserialize;
use std::fmt;
use std::path::Path;
use std::time::Duration;

/// A whole deployment.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Deployment {
    /// Pulse each runtime thread's bit on the DigitalOut aliased "ThreadScope".
    #[serde(default)]
    pub thread_scope: bool,
    /// Hold CPU wake-up latency at this many µs while running (`/dev/cpu_dma_latency`).
    #[serde(default)]
    pub cpu_dma_latency_us: Option<u32>,
    /// Path of the control socket (default: /run/hwgw/hwgw.sock as root, else a per-user
    /// runtime path).
    #[serde(default)]
    pub control_socket: Option<String>,
    /// IO cards.
    #[serde(default, rename = "card")]
    pub cards: Vec<CardConfig>,
    /// Extra names for devices.
    #[serde(default, rename = "alias")]
    pub aliases: Vec<AliasConfig>,
    /// Components, started in this order (stopped in reverse).
    #[serde(default, rename = "component")]
    pub components: Vec<ComponentConfig>,
    /// Port-to-port connections.
    #[serde(default, rename = "connection")]
    pub connections: Vec<ConnectionConfig>,
    /// Serve chosen devices as a Modbus TCP register table (off when absent).
    #[serde(default)]
    pub modbus_server: Option<ModbusServerConfig>,
}

/// hwgw as a Modbus TCP server.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModbusServerConfig {
    /// `address:port` to listen on (e.g. 127.0.0.1:5502; 0.0.0.0 only on purpose).
    pub listen: String,
    /// The register table.
    #[serde(default, rename = "register")]
    pub registers: Vec<ServedRegister>,
}

/// One entry of the served register table.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServedRegister {
    /// The table: input_registers, holding_registers, discrete_inputs or coils.
    pub table: driver_modbus::plan::Table,
    /// First address (0-based).
    pub address: u16,
    /// The device's registry name.
    pub device: String,
    /// Which of its interfaces.
    pub interface: AliasInterface,
    /// Channel (or bit).
    #[serde(default)]
    pub channel: u32,
    /// Register type (default u16).
    #[serde(default, rename = "type")]
    pub ty: driver_modbus::codec::ValueType,
    /// Word order.
    #[serde(default)]
    pub words: driver_modbus::codec::WordOrder,
    /// Byte order.
    #[serde(default)]
    pub bytes: driver_modbus::codec::ByteOrder,
    /// Register value = (physical - offset) / scale (default 1).
    #[serde(default = "one_f64")]
    pub scale: f64,
    /// See `scale`.
    #[serde(default)]
    pub offset: f64,
}

fn one_f64() -> f64 {
    1.0
}

/// One IO card: a driver and its section.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CardConfig {
    /// The card's name: its devices are registered under it.
    pub name: String,
    /// Which driver runs it: "sim", "modbus" or "socketcan".
    pub driver: String,
    /// Period of the card's bus cycle, ms.
    #[serde(default = "default_card_period")]
    pub period_ms: f64,
    /// Period at which IO components sample the card's inputs into ports, ms (default: the
    /// card's period).
    #[serde(default)]
    pub sample_period_ms: Option<f64>,
    /// Analog output values to drive when the gateway stops (default: each channel's
    /// initial value).
    #[serde(default)]
    pub safe_analog_out: Option<Vec<f64>>,
    /// Digital outputs to leave on when the gateway stops (default: all off).
    #[serde(default)]
    pub safe_digital_out_on: Vec<u32>,
    /// Where the card's own activity thread runs (the sim card's cycle, the CAN bus
    /// component): `{ policy = "fifo", priority = 60, cpus = [1] }`; default SCHED_OTHER.
    #[serde(default)]
    pub thread: rtt::ThreadOptions,
    /// Names for the card's channels: the IO components' ports are called by them
    /// (unnamed channels keep `ch0…`/`bit0…`).
    #[serde(default)]
    pub names: ChannelNames,
    /// The sim driver's section.
    #[serde(default)]
    pub sim: Option<toml::Spanned<SimConfig>>,
    /// The modbus driver's section: the line, the unit, timing and the register map.
    #[serde(default)]
    pub modbus: Option<toml::Spanned<driver_modbus::config::ModbusConfig>>,
    /// The socketcan driver's section: the interface, a DBC file, rx and tx frames.
    #[serde(default)]
    pub socketcan: Option<toml::Spanned<driver_can::map::CanConfig>>,
}

/// Port names for a card's channels, in channel order.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChannelNames {
    /// Analog inputs.
    #[serde(default)]
    pub analog_in: Vec<String>,
    /// Analog outputs.
    #[serde(default)]
    pub analog_out: Vec<String>,
    /// Digital inputs.
    #[serde(default)]
    pub digital_in: Vec<String>,
    /// Digital outputs.
    #[serde(default)]
    pub digital_out: Vec<String>,
}

impl ChannelNames {
    /// The port name of channel `i` of a list: its given name, else `prefix{i}`.
    pub fn port(names: &[String], prefix: &str, i: u32) -> String {
        names
            .get(i as usize)
            .cloned()
            .unwrap_or_else(|| format!("{prefix}{i}"))
    }

    /// Checks the names against the card's channel counts: not more names than channels,
    /// no empty names, no dots (they separate component and port), no duplicates.
    /// Errors are (key path under the card, message).
    pub fn check(&self, counts: [u32; 4]) -> Result<(), (String, String)> {
        let lists = [
            ("analog_in", &self.analog_in),
            ("analog_out", &self.analog_out),
            ("digital_in", &self.digital_in),
            ("digital_out", &self.digital_out),
        ];
        for ((key, names), count) in lists.into_iter().zip(counts) {
            if names.len() > count as usize {
                return Err((
                    format!("names.{key}"),
                    format!("{} names for {count} channels", names.len()),
                ));
            }
            for (i, n) in names.iter().enumerate() {
                if n.is_empty() || n.contains('.') || n.chars().any(char::is_whitespace) {
                    return Err((
                        format!("names.{key}[{i}]"),
                        format!("{n:?} is not a port name (no dots, no spaces, not empty)"),
                    ));
                }
                if names[..i].contains(n) {
                    return Err((format!("names.{key}[{i}]"), format!("{n:?} is used twice")));
                }
            }
        }
        Ok(())
    }
}

fn default_card_period() -> f64 {
    10.0
}

/// A device interface, by name (for aliases and the served register table).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AliasInterface {
    /// AnalogIn.
    AnalogIn,
    /// AnalogOut.
    AnalogOut,
    /// DigitalIn.
    DigitalIn,
    /// DigitalOut.
    DigitalOut,
    /// Encoder.
    Encoder,
}

/// Another name for a registered device.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AliasConfig {
    /// The interface.
    pub interface: AliasInterface,
    /// The new name.
    pub name: String,
    /// The device it stands for.
    pub target: String,
}

/// How a component steps.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum ActivityConfig {
    /// Every `period_ms`.
    Periodic {
        /// Period in ms.
        period_ms: f64,
        /// "other" or "fifo".
        #[serde(default)]
        policy: rtt::SchedPolicy,
        /// Priority (1..=99 for fifo).
        #[serde(default)]
        priority: i32,
        /// CPUs to run on.
        #[serde(default)]
        cpus: Vec<usize>,
        /// Consecutive overruns before the activity reports itself unhealthy.
        #[serde(default)]
        max_overruns: Option<u32>,
    },
    /// When woken by an event port, an operation or a trigger.
    NonPeriodic,
}

impl ActivityConfig {
    /// The runtime's activity spec.
    pub fn spec(&self) -> rtt::ActivitySpec {
        match self {
            ActivityConfig::Periodic {
                period_ms,
                policy,
                priority,
                cpus,
                max_overruns,
            } => rtt::ActivitySpec::Periodic {
                period: millis(*period_ms),
                thread: rtt::ThreadOptions {
                    policy: *policy,
                    priority: *priority,
                    cpus: cpus.clone(),
                },
                timing: rtt::Timing::Absolute,
                max_overruns: *max_overruns,
            },
            ActivityConfig::NonPeriodic => rtt::ActivitySpec::non_periodic(),
        }
    }
}

/// A duration from milliseconds (negative and NaN count as zero; `check` refuses them).
pub fn millis(ms: f64) -> Duration {
    Duration::from_secs_f64((ms / 1000.0).max(0.0))
}

/// One component.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ComponentConfig {
    /// Its name.
    pub name: String,
    /// Its type: one of the types built into the binary.
    #[serde(rename = "type")]
    pub kind: String,
    /// How it steps.
    pub activity: ActivityConfig,
    /// Values for its properties (checked against the component's own property bag).
    #[serde(default)]
    pub properties: toml::Table,
    /// Start it after configuring (default true).
    #[serde(default = "yes")]
    pub start: bool,
}

fn yes() -> bool {
    true
}

/// A connection from an output port to an input port, each written `component.port`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConnectionConfig {
    /// `component.port` of the output.
    pub from: String,
    /// `component.port` of the input.
    pub to: String,
    /// The connection policy (default: data).
    #[serde(default)]
    pub policy: ConnPolicy,
}

/// Splits `component.port` at the last dot.
pub fn split_port(address: &str) -> Option<(&str, &str)> {
    address
        .rsplit_once('.')
        .filter(|(c, p)| !c.is_empty() && !p.is_empty())
}

/// Where in a file something is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Location {
    /// The file.
    pub file: String,
    /// Line, from 1.
    pub line: usize,
    /// Column, from 1.
    pub column: usize,
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}:{}", self.file, self.line, self.column)
    }
}

/// Line and column (from 1) of byte `offset` in `text`.
pub fn locate(file: &str, text: &str, offset: usize) -> Location {
    let before = &text[..offset.min(text.len())];
    let line = before.matches('\n').count() + 1;
    let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
    Location {
        file: file.to_string(),
        line,
        column,
    }
}

/// One problem in a deployment file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Problem {
    /// Where, when known.
    pub location: Option<Location>,
    /// Key path, e.g. `card[0].sim.analog_in[1].range`.
    pub path: String,
    /// What is wrong and what was expected.
    pub message: String,
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if let Some(l) = &self.location {
            write!(f, "{l}: ")?;
        }
        if self.path.is_empty() {
            write!(f, "{}", self.message)
        } else {
            write!(f, "{}: {}", self.path, self.message)
        }
    }
}

/// Why a deployment file was refused: every problem found.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("{file}: cannot read: {message}")]
    Read {
        /// The file.
        file: String,
        /// The OS error.
        message: String,
    },
    /// The file is not a valid deployment.
    #[error("{}", .0.iter().map(|p| p.to_string()).collect::<Vec<_>>().join("\n"))]
    Invalid(Vec<Problem>),
}

impl ConfigError {
    /// The problems (empty for a read error).
    pub fn problems(&self) -> &[Problem] {
        match self {
            ConfigError::Invalid(p) => p,
            ConfigError::Read { .. } => &[],
        }
    }
}

impl Deployment {
    /// Reads and parses `path` (no semantic checks: see
    /// [`Gateway::build`](crate::deploy::Gateway::build)).
    pub fn load(path: &Path) -> Result<(Deployment, String), ConfigError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| ConfigError::Read {
            file: file.clone(),
            message: e.to_string(),
        })?;
        Ok((Self::parse(&text, &file)?, text))
    }

    /// Parses deployment `text`, naming it `file` in errors.
    pub fn parse(text: &str, file: &str) -> Result<Deployment, ConfigError> {
        let de = toml::de::Deserializer::parse(text).map_err(|e| {
            ConfigError::Invalid(vec![Problem {
                location: e.span().map(|s| locate(file, text, s.start)),
                path: String::new(),
                message: e.message().trim().to_string(),
            }])
        })?;
        serde_path_to_error::deserialize(de).map_err(|e| {
            // toml::Spanned shows up in serde's path as a private field name.
            let path = e
                .path()
                .to_string()
                .replace(".$__serde_spanned_private_value", "");
            let inner = e.into_inner();
            ConfigError::Invalid(vec![Problem {
                location: inner.span().map(|s| locate(file, text, s.start)),
                path: if path == "." { String::new() } else { path },
                message: inner.message().trim().to_string(),
            }])
        })
    }
}
