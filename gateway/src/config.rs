//! The deployment file: cards, aliases, ThreadScope, components and connections, in TOML.
//!
//! Parsing is strict — unknown keys are errors — and every error names the file, line,
//! column and key path and says what was expected. A card's driver section
//! (`[card.<driver>]`) and a server's section (`[modbus_server]`: any other top-level key)
//! are kept as written here and parsed by their driver or server type when the gateway is
//! built, so drivers and servers from other crates bring their own section types; a
//! top-level key that is no server type of the build is refused then.
//! [`Gateway::build`](crate::deploy::Gateway::build) then validates what the types cannot:
//! unique names, known drivers and component types, driver sections, properties,
//! connection ends that exist — with the same locations.
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

pub use crate::problems::{Location, Problem};
pub use driver_api::ChannelNames;

use crate::problems::Source;
use rtt::port::ConnPolicy;
use serde::Deserialize;
use serde::de::{self, MapAccess, Visitor};
use std::collections::BTreeMap;
use std::fmt;
use std::path::Path;
use std::time::Duration;

/// A whole deployment.
///
/// Besides the keys below ([`DEPLOYMENT_KEYS`]) a deployment may have server sections,
/// kept in [`servers`](Self::servers) as written.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct Deployment {
    /// Pulse each runtime thread's bit on the DigitalOut aliased "ThreadScope".
    #[serde(default)]
    pub thread_scope: bool,
    /// Record each runtime thread's bit into a VCD file while running, named after this
    /// one (relative to the deployment file's folder): each `run` creates a new numbered
    /// file, `threads.vcd` giving `threads-1.vcd`, `threads-2.vcd`, … (the highest number
    /// the newest), never over an existing name nor through a link; `check` only checks
    /// that its folder takes new files.
    #[serde(default)]
    pub thread_scope_vcd: Option<String>,
    /// How many of `thread_scope_vcd`'s numbered files are kept: the oldest beyond it are
    /// removed at `run` (default 10, 1 to 1000).
    #[serde(default)]
    pub thread_scope_vcd_keep: Option<u32>,
    /// Hold CPU wake-up latency at this many µs while running (`/dev/cpu_dma_latency`).
    #[serde(default)]
    pub cpu_dma_latency_us: Option<u32>,
    /// Path of the control socket (default: the service's /run/hwgw/hwgw.sock, else a
    /// per-user path; see [`crate::socket`]).
    #[serde(default)]
    pub control_socket: Option<String>,
    /// Most control clients connected at once (default 64, 1 to 1024).
    #[serde(default)]
    pub control_clients: Option<u32>,
    /// Seconds a control client may stay silent before it is disconnected (default 600,
    /// 1 to 86400).
    #[serde(default)]
    pub control_idle_s: Option<f64>,
    /// IO cards.
    #[serde(default, rename = "card")]
    pub cards: Vec<CardConfig>,
    /// Extra names for devices.
    #[serde(default, rename = "alias")]
    pub aliases: Vec<AliasConfig>,
    /// Logical devices (sensors, drives, axes) over the cards' devices.
    #[serde(default, rename = "logical")]
    pub logical: Vec<crate::logical::LogicalConfig>,
    /// Components, started in this order (stopped in reverse).
    #[serde(default, rename = "component")]
    pub components: Vec<ComponentConfig>,
    /// Port-to-port connections.
    #[serde(default, rename = "connection")]
    pub connections: Vec<ConnectionConfig>,
    /// This gateway in a Zenoh name space with others: what it publishes, imports and
    /// serves (off when absent: nothing listens, nothing is sent).
    #[serde(default)]
    pub zenoh: Option<ZenohSection>,
    /// Every other top-level key, as written: a server's section by its server type's
    /// name (`[modbus_server]`: serve chosen devices as a Modbus TCP register table), or
    /// anything else, which the build refuses (see [`crate::servers`]).
    #[serde(flatten)]
    pub servers: BTreeMap<String, toml::Value>,
}

/// The top-level keys of a deployment besides its server sections.
pub const DEPLOYMENT_KEYS: [&str; 13] = [
    "thread_scope",
    "thread_scope_vcd",
    "thread_scope_vcd_keep",
    "cpu_dma_latency_us",
    "control_socket",
    "control_clients",
    "control_idle_s",
    "card",
    "alias",
    "logical",
    "component",
    "connection",
    "zenoh",
];

/// What the deployment's `[zenoh]` section is in this build.
#[cfg(feature = "zenoh")]
pub type ZenohSection = scaleout::ZenohConfig;

/// What the deployment's `[zenoh]` section is in this build (one without the `zenoh`
/// feature: refused when given).
#[cfg(not(feature = "zenoh"))]
pub type ZenohSection = toml::Value;

/// One IO card: a driver and its section.
///
/// Besides the keys below a card has exactly one more: its driver's section,
/// `[card.<driver>]`, kept in [`sections`](Self::sections) as written.
#[derive(Debug, Clone, PartialEq)]
pub struct CardConfig {
    /// The card's name: its devices are registered under it.
    pub name: String,
    /// Which driver runs it: one of the driver types of the build ("sim", "modbus",
    /// "socketcan", or a user's).
    pub driver: String,
    /// Period of the card's bus cycle, ms.
    pub period_ms: f64,
    /// Period at which IO components sample the card's inputs into ports, ms (default: the
    /// card's period).
    pub sample_period_ms: Option<f64>,
    /// Safe values of the analog outputs, channel by channel (shorthand for
    /// `[card.outputs] safe`).
    pub safe_analog_out: Option<Vec<f64>>,
    /// Digital outputs whose safe value is on; given, every other digital output's safe
    /// value is off (shorthand for `[card.outputs] safe`).
    pub safe_digital_out_on: Option<Vec<u32>>,
    /// The output policy: safe values or `"keep"` by port, the default, the output
    /// watchdog (see [`crate::outputs`]).
    pub outputs: crate::outputs::OutputsConfig,
    /// Where the card's own activity thread runs (its bus component):
    /// `{ policy = "fifo", priority = 60, cpus = [1] }`; default SCHED_OTHER.
    pub thread: rtt::ThreadOptions,
    /// Names for the card's channels: the IO components' ports are called by them
    /// (unnamed channels keep `ch0…`/`bit0…`, or the driver's names).
    pub names: ChannelNames,
    /// What the card's sampling IO components make of missed readings (a device stale or
    /// offline): `{ warn_after = 1, error_after = 5 }` warns at the first and goes to
    /// RunTimeError at the fifth in a row ([`rtt::faults`]); not given, neither (the
    /// devices' health tells).
    pub faults: Option<rtt::faults::FaultPolicy>,
    /// Every other key of the card, as written: its driver's section (`sim = {…}`,
    /// `[card.modbus]`), and anything else, which the build refuses.
    pub sections: BTreeMap<String, toml::Value>,
}

/// The keys of a card besides its driver section.
pub const CARD_KEYS: [&str; 10] = [
    "name",
    "driver",
    "period_ms",
    "sample_period_ms",
    "safe_analog_out",
    "safe_digital_out_on",
    "outputs",
    "thread",
    "names",
    "faults",
];

impl<'de> Deserialize<'de> for CardConfig {
    fn deserialize<D: de::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        d.deserialize_map(CardVisitor)
    }
}

struct CardVisitor;

/// Sets a field once; a key given twice is an error.
fn once<T, E: de::Error>(slot: &mut Option<T>, key: &'static str, value: T) -> Result<(), E> {
    if slot.is_some() {
        return Err(E::duplicate_field(key));
    }
    *slot = Some(value);
    Ok(())
}

impl<'de> Visitor<'de> for CardVisitor {
    type Value = CardConfig;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a card table")
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<CardConfig, A::Error> {
        let (mut name, mut driver, mut period, mut sample) = (None, None, None, None);
        let (mut safe_ao, mut safe_do, mut thread, mut names) = (None, None, None, None);
        let (mut outputs, mut faults) = (None, None);
        let mut sections = BTreeMap::new();
        while let Some(key) = map.next_key::<String>()? {
            match key.as_str() {
                "name" => once(&mut name, "name", map.next_value()?)?,
                "driver" => once(&mut driver, "driver", map.next_value()?)?,
                "period_ms" => once(&mut period, "period_ms", map.next_value()?)?,
                "sample_period_ms" => once(&mut sample, "sample_period_ms", map.next_value()?)?,
                "safe_analog_out" => once(&mut safe_ao, "safe_analog_out", map.next_value()?)?,
                "safe_digital_out_on" => {
                    once(&mut safe_do, "safe_digital_out_on", map.next_value()?)?
                }
                "outputs" => once(&mut outputs, "outputs", map.next_value()?)?,
                "thread" => once(&mut thread, "thread", map.next_value()?)?,
                "names" => once(&mut names, "names", map.next_value()?)?,
                "faults" => once(&mut faults, "faults", map.next_value()?)?,
                _ => {
                    let value: toml::Value = map.next_value()?;
                    sections.insert(key, value);
                }
            }
        }
        Ok(CardConfig {
            name: name.ok_or_else(|| de::Error::missing_field("name"))?,
            driver: driver.ok_or_else(|| de::Error::missing_field("driver"))?,
            period_ms: period.unwrap_or_else(default_card_period),
            sample_period_ms: sample,
            safe_analog_out: safe_ao,
            safe_digital_out_on: safe_do,
            outputs: outputs.unwrap_or_default(),
            thread: thread.unwrap_or_default(),
            names: names.unwrap_or_default(),
            faults,
            sections,
        })
    }
}

fn default_card_period() -> f64 {
    10.0
}

/// Another name for a registered device.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AliasConfig {
    /// The interface.
    pub interface: device_interface::Interface,
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
    NonPeriodic {
        /// How long its thread spins for the next trigger before it parks, µs (default
        /// 20; 0: park at once; at most 10000).
        #[serde(default)]
        spin_us: Option<u32>,
        /// "other" or "fifo".
        #[serde(default)]
        policy: rtt::SchedPolicy,
        /// Priority (1..=99 for fifo).
        #[serde(default)]
        priority: i32,
        /// CPUs to run on.
        #[serde(default)]
        cpus: Vec<usize>,
    },
    /// When a file descriptor the component watches is ready, or after `timeout_ms`.
    FileDescriptor {
        /// Step anyway after this long without events, ms; not given: wait for ever.
        #[serde(default)]
        timeout_ms: Option<f64>,
        /// "other" or "fifo".
        #[serde(default)]
        policy: rtt::SchedPolicy,
        /// Priority (1..=99 for fifo).
        #[serde(default)]
        priority: i32,
        /// CPUs to run on.
        #[serde(default)]
        cpus: Vec<usize>,
    },
    /// No thread of its own: stepped by component `master` right after each of its steps,
    /// on its thread, in the order the slaves are written.
    Slave {
        /// The component that steps it.
        master: String,
    },
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
                    ..rtt::ThreadOptions::default()
                },
                timing: rtt::Timing::Absolute,
                max_overruns: *max_overruns,
            },
            ActivityConfig::NonPeriodic {
                spin_us,
                policy,
                priority,
                cpus,
            } => rtt::ActivitySpec::NonPeriodic {
                thread: rtt::ThreadOptions {
                    spin_us: spin_us.unwrap_or(rtt::activity::DEFAULT_SPIN_US),
                    policy: *policy,
                    priority: *priority,
                    cpus: cpus.clone(),
                },
            },
            ActivityConfig::FileDescriptor {
                timeout_ms,
                policy,
                priority,
                cpus,
            } => rtt::ActivitySpec::FileDescriptor {
                timeout: timeout_ms.map(millis),
                thread: rtt::ThreadOptions {
                    policy: *policy,
                    priority: *priority,
                    cpus: cpus.clone(),
                    ..rtt::ThreadOptions::default()
                },
            },
            ActivityConfig::Slave { .. } => rtt::ActivitySpec::Slave,
        }
    }
}

/// A duration from milliseconds (negative and NaN count as zero, too large as the longest
/// duration; the build refuses them all: see [`crate::checks::period`]).
pub fn millis(ms: f64) -> Duration {
    Duration::try_from_secs_f64((ms / 1000.0).max(0.0)).unwrap_or(Duration::MAX)
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
    /// Property files (TOML, relative to the deployment's folder), applied in order
    /// before `properties` (the manual's readProperties): a site's values over a base's.
    #[serde(default)]
    pub properties_file: Vec<String>,
    /// Values for its properties (checked against the component's own property bag).
    #[serde(default)]
    pub properties: toml::Table,
    /// Start it after configuring (default true).
    #[serde(default = "yes")]
    pub start: bool,
    /// What its requirements are bound to, by requirement: a service to
    /// `"component.service"` (`camera = "cam0.camera"`), devices to their names
    /// (`valves = ["press", "aux"]`). A required service not named here is bound to the one
    /// component providing a service of its name.
    #[serde(default)]
    pub requires: BTreeMap<String, Binding>,
    /// Names it knows other components by: `{ device = "press_io" }` (RTT's peers, its
    /// `Context::peer("device")` finds `press_io`; `cd device` in `browse` goes there).
    #[serde(default)]
    pub peers: BTreeMap<String, String>,
    /// A digest of the files it reads when it is built (its property files, a script's
    /// `file`), taken when the deployment is read: a reload rebuilds a component whose
    /// files changed though its table did not.
    #[serde(skip)]
    pub files_digest: FilesDigest,
}

/// A digest of the files a component reads; one not taken (a deployment edited at run
/// time, not read from its file) equals any, so that it rebuilds nothing by itself.
#[derive(Debug, Clone, Copy, Default)]
pub struct FilesDigest(pub Option<u64>);

impl PartialEq for FilesDigest {
    fn eq(&self, other: &Self) -> bool {
        match (self.0, other.0) {
            (Some(a), Some(b)) => a == b,
            _ => true,
        }
    }
}

impl ComponentConfig {
    /// The files this component reads when it is built, relative to `base`.
    pub fn files_read(&self, base: &Path) -> Vec<std::path::PathBuf> {
        let mut files: Vec<_> = self.properties_file.iter().map(|f| base.join(f)).collect();
        if self.kind == script::TYPE
            && let Some(toml::Value::String(f)) = self.properties.get("file")
        {
            files.push(base.join(f));
        }
        files
    }
}

/// What one requirement is bound to.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(
    untagged,
    expecting = "a \"component.service\" or device name, or a list of device names"
)]
pub enum Binding {
    /// A provider's service (`cam0.camera`), or one device.
    One(String),
    /// Devices, in order.
    Many(Vec<String>),
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

/// Splits `component.port` where `is_component` says the component ends: component and
/// port names may both hold dots (`sim0.ai.ch0`, a service's port `cam0.camera.frames`),
/// so the first split from the right whose left side is a component is it; with none,
/// the last dot.
pub fn split_port_among<'a>(
    address: &'a str,
    is_component: &dyn Fn(&str) -> bool,
) -> Option<(&'a str, &'a str)> {
    address
        .rmatch_indices('.')
        .map(|(i, _)| (&address[..i], &address[i + 1..]))
        .filter(|(c, p)| !c.is_empty() && !p.is_empty())
        .find(|(c, _)| is_component(c))
        .or_else(|| split_port(address))
}

/// Splits `component.port` at the last dot.
pub fn split_port(address: &str) -> Option<(&str, &str)> {
    address
        .rsplit_once('.')
        .filter(|(c, p)| !c.is_empty() && !p.is_empty())
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
        let source = Source::new(file, text);
        let locate =
            |span: Option<std::ops::Range<usize>>| span.map(|s| source.locate_offset(s.start));
        let de = toml::de::Deserializer::parse(text).map_err(|e| {
            ConfigError::Invalid(vec![Problem::new(locate(e.span()), "", e.message().trim())])
        })?;
        // NaN and the infinities, wherever they are, named as what they are (a setting
        // would take them for anything from "no value" to "the longest time").
        let not_numbers = source.non_finite();
        if !not_numbers.is_empty() {
            return Err(ConfigError::Invalid(not_numbers));
        }
        let mut d: Deployment = serde_path_to_error::deserialize(de).map_err(|e| {
            // toml::Spanned shows up in serde's path as a private field name.
            let path = e
                .path()
                .to_string()
                .replace(".$__serde_spanned_private_value", "");
            let inner = e.into_inner();
            ConfigError::Invalid(vec![Problem::new(
                locate(inner.span()),
                if path == "." { "" } else { &path },
                inner.message().trim(),
            )])
        })?;
        // Only a deployment read from its file: one edited at run time has no folder.
        if Path::new(file).is_file() {
            let base = Path::new(file).parent().unwrap_or(Path::new(""));
            for c in &mut d.components {
                c.files_digest = FilesDigest(Some(digest(&c.files_read(base))));
            }
        }
        Ok(d)
    }
}

/// A digest of the files' contents: regular files only, opened without waiting (never a
/// FIFO's writer), at most [`script::load::MAX_FILE`] bytes each read; a file that
/// cannot be read counts as its error.
fn digest(files: &[std::path::PathBuf]) -> u64 {
    use std::hash::{Hash, Hasher};
    use std::io::Read;
    let mut h = std::collections::hash_map::DefaultHasher::new();
    for f in files {
        let read =
            script::open_regular(std::fs::OpenOptions::new().read(true), f, 0).and_then(|file| {
                let mut bytes = Vec::new();
                file.take(script::load::MAX_FILE + 1)
                    .read_to_end(&mut bytes)?;
                Ok(bytes)
            });
        match read {
            Ok(bytes) => bytes.hash(&mut h),
            Err(e) => e.to_string().hash(&mut h),
        }
    }
    h.finish()
}
