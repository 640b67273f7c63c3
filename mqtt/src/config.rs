//! The `[server.mqtt]` section, typed and checked: the broker and how to reach it, what is
//! published and how often, and the two ways of publishing — a Sparkplug B edge node
//! (`[server.mqtt.sparkplug]`) and plain JSON topics (`[server.mqtt.json]`).
//!
//! ```
//! use mqtt::MqttConfig;
//!
//! let c: MqttConfig = toml::from_str(r#"
//!     broker = "127.0.0.1:1883"
//!     deadband = 0.01
//!     [sparkplug]
//!     group = "plant1"
//!     node = "line3"
//!     [json]
//!     prefix = "hwgw"
//! "#)?;
//! assert_eq!(c.sample_period_ms, 100);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use device_interface::text::Number;
use driver_api::CardError;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// `[server.mqtt]`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MqttConfig {
    /// The broker, `host:port` (1883 is MQTT's port, 8883 MQTT over TLS).
    pub broker: String,
    /// The MQTT client id (default `hwgw-` and the Sparkplug node id, or without
    /// Sparkplug `hwgw-` and the host's name: two gateways on one broker must differ).
    #[serde(default)]
    pub client_id: Option<String>,
    /// `"3.1.1"` (default; what Sparkplug 3.0 names) or `"5"`.
    #[serde(default)]
    pub version: Version,
    /// Keep-alive, s (5–3600, default 30): a broker hears nothing this long and a half and
    /// publishes the will (the NDEATH).
    #[serde(default = "default_keep_alive")]
    pub keep_alive_s: u64,
    /// User name for the broker.
    #[serde(default)]
    pub username: Option<String>,
    /// A file holding the password (relative to the deployment's folder; the first line,
    /// without its line end): the password is not in the deployment.
    #[serde(default)]
    pub password_file: Option<String>,
    /// TLS to the broker.
    #[serde(default)]
    pub tls: Option<TlsConfig>,
    /// How often values are read and compared, ms (10–60000, default 100).
    #[serde(default = "default_sample")]
    pub sample_period_ms: u64,
    /// A metric is published at most this often, ms (0–3600000, default 0: every change).
    #[serde(default)]
    pub min_period_ms: u64,
    /// A metric is published at least this often even unchanged, ms (0: only on change;
    /// else at least `sample_period_ms`, at most 86400000).
    #[serde(default)]
    pub max_period_ms: u64,
    /// An analog value is published when it moved more than this from the value last
    /// published (default 0: any change).
    #[serde(default)]
    pub deadband: f64,
    /// Deadbands of single channels, by port (`"sim0.ai.ch0" = 0.05`).
    #[serde(default)]
    pub deadbands: BTreeMap<String, f64>,
    /// The devices published, by registry name (`sim0`); default every device of the
    /// five channel interfaces.
    #[serde(default)]
    pub devices: Vec<String>,
    /// Outputs may be written: Sparkplug DCMD and the JSON `set` topics, each write with
    /// the checks `hwgw set` passes. The broker's access control says who may publish
    /// them.
    #[serde(default)]
    pub allow_writes: bool,
    /// Messages the client's queue holds towards the broker (16–65536, default 4096);
    /// when it is full a message is not queued and is counted as dropped (its metric's
    /// newest value goes with the next message or birth).
    #[serde(default = "default_queue")]
    pub queue: usize,
    /// Bytes the queue towards the broker holds, KiB (64-1048576, default 8192): a
    /// message that would take it beyond is not queued (counted as dropped, its metrics'
    /// newest values go later), so a slow broker holds this much, never minutes of old
    /// data; a message bigger than this goes when the queue is empty.
    #[serde(default = "default_queue_kib")]
    pub queue_kib: u64,
    /// A Sparkplug B edge node.
    #[serde(default)]
    pub sparkplug: Option<SparkplugConfig>,
    /// Plain JSON topics.
    #[serde(default)]
    pub json: Option<JsonConfig>,
}

/// The MQTT protocol version.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
pub enum Version {
    /// MQTT 3.1.1.
    #[default]
    #[serde(rename = "3.1.1")]
    V311,
    /// MQTT 5.
    #[serde(rename = "5")]
    V5,
}

/// `[server.mqtt.tls]`: files relative to the deployment's folder.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsConfig {
    /// The CA certificates (PEM) the broker's certificate must chain to.
    pub ca: String,
    /// hwgw's client certificate chain (PEM), for a broker that asks for one.
    #[serde(default)]
    pub cert: Option<String>,
    /// The client certificate's private key (PEM).
    #[serde(default)]
    pub key: Option<String>,
}

/// `[server.mqtt.sparkplug]`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SparkplugConfig {
    /// The Sparkplug group id.
    pub group: String,
    /// The edge node id.
    pub node: String,
    /// What a Sparkplug device is: `"card"` (default; its metrics `ai/ch0`, `do/bit3`) or
    /// `"device"` (each IO component, `sim0.ai`, its metrics `ch0`).
    #[serde(default)]
    pub device_per: DevicePer,
    /// The primary host application's id: births wait until its STATE says online, and
    /// while it is offline nothing is published (values are held, the newest of each).
    #[serde(default)]
    pub primary_host: Option<String>,
}

/// What one Sparkplug device stands for.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DevicePer {
    /// A card (a registry name's devices).
    #[default]
    Card,
    /// An IO component: one interface of a card.
    Device,
}

/// `[server.mqtt.json]`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JsonConfig {
    /// The topics' first level (default `hwgw`): `hwgw/sim0.ai/ch0`.
    #[serde(default = "default_prefix")]
    pub prefix: String,
}

fn default_keep_alive() -> u64 {
    30
}
fn default_sample() -> u64 {
    100
}
fn default_queue() -> usize {
    4096
}
fn default_queue_kib() -> u64 {
    8192
}
fn default_prefix() -> String {
    "hwgw".into()
}

/// The section checked: what the server runs with.
#[derive(Debug, Clone)]
pub struct Settings {
    /// Broker host.
    pub host: String,
    /// Broker port.
    pub port: u16,
    /// Client id.
    pub client_id: String,
    /// Protocol version.
    pub version: Version,
    /// Keep-alive.
    pub keep_alive: Duration,
    /// User name and password.
    pub credentials: Option<(String, String)>,
    /// TLS files, resolved.
    pub tls: Option<TlsFiles>,
    /// Sampling period.
    pub sample: Duration,
    /// Shortest time between two reports of a metric.
    pub min_period: Duration,
    /// Longest time between two reports of a metric (`None`: on change only).
    pub max_period: Option<Duration>,
    /// Queue towards the broker, messages.
    pub queue: usize,
    /// Queue towards the broker, bytes.
    pub queue_bytes: usize,
    /// Writes allowed.
    pub allow_writes: bool,
    /// Sparkplug.
    pub sparkplug: Option<SparkplugConfig>,
    /// JSON topics' prefix.
    pub json: Option<String>,
}

/// TLS files, resolved against the deployment's folder.
#[derive(Debug, Clone)]
pub struct TlsFiles {
    /// CA certificates.
    pub ca: PathBuf,
    /// Client certificate and key.
    pub client: Option<(PathBuf, PathBuf)>,
}

impl MqttConfig {
    /// The section checked, files resolved against `base`; every problem at its key.
    pub fn settings(&self, base: &Path) -> Result<Settings, Vec<CardError>> {
        let mut problems = Vec::new();
        let (host, port) = broker(&self.broker)
            .map_err(|e| problems.push(e))
            .ok()
            .unzip();
        let mut bound = |key: &str, v: u64, lo: u64, hi: u64, unit: &str| {
            if !(lo..=hi).contains(&v) {
                problems.push(CardError::at(key, format!("{v}: {lo}-{hi} {unit}")));
            }
        };
        bound("keep_alive_s", self.keep_alive_s, 5, 3600, "s");
        bound("sample_period_ms", self.sample_period_ms, 10, 60_000, "ms");
        bound("min_period_ms", self.min_period_ms, 0, 3_600_000, "ms");
        bound("queue", self.queue as u64, 16, 65_536, "messages");
        bound("queue_kib", self.queue_kib, 64, 1 << 20, "KiB");
        if self.max_period_ms != 0 {
            bound(
                "max_period_ms",
                self.max_period_ms,
                self.sample_period_ms.max(self.min_period_ms),
                86_400_000,
                "ms (0: on change only; else at least sample_period_ms and min_period_ms)",
            );
        }
        deadband("deadband", self.deadband, &mut problems);
        for (port, d) in &self.deadbands {
            deadband(&format!("deadbands.{port}"), *d, &mut problems);
        }
        if self.sparkplug.is_none() && self.json.is_none() {
            problems.push(CardError::new(
                "nothing to publish: give [server.mqtt.sparkplug], [server.mqtt.json] or both",
            ));
        }
        if let Some(s) = &self.sparkplug {
            sparkplug_ids(s, &mut problems);
        }
        if let Some(j) = &self.json
            && let Err(why) = topic_level(&j.prefix, true)
        {
            problems.push(CardError::at("json.prefix", why));
        }
        let client_id = self
            .client_id
            .clone()
            .unwrap_or_else(|| match &self.sparkplug {
                Some(s) => format!("hwgw-{}", s.node),
                None => "hwgw".into(),
            });
        if client_id.is_empty() || client_id.len() > 65_535 {
            problems.push(CardError::at("client_id", "1-65535 bytes"));
        }
        let credentials = self.credentials(base, &mut problems);
        let tls = self.tls.as_ref().map(|t| tls_files(t, base, &mut problems));
        let (Some(host), Some(port), true) = (host, port, problems.is_empty()) else {
            return Err(problems);
        };
        Ok(Settings {
            host,
            port,
            client_id,
            version: self.version,
            keep_alive: Duration::from_secs(self.keep_alive_s),
            credentials,
            tls: tls.flatten(),
            sample: Duration::from_millis(self.sample_period_ms),
            min_period: Duration::from_millis(self.min_period_ms),
            max_period: (self.max_period_ms > 0).then(|| Duration::from_millis(self.max_period_ms)),
            queue: self.queue,
            queue_bytes: (self.queue_kib as usize) << 10,
            allow_writes: self.allow_writes,
            sparkplug: self.sparkplug.clone(),
            json: self.json.as_ref().map(|j| j.prefix.clone()),
        })
    }

    fn credentials(&self, base: &Path, problems: &mut Vec<CardError>) -> Option<(String, String)> {
        let password = match &self.password_file {
            None => String::new(),
            Some(f) => match std::fs::read_to_string(base.join(f)) {
                Ok(text) => text.lines().next().unwrap_or("").to_string(),
                Err(e) => {
                    problems.push(CardError::at("password_file", format!("{f:?}: {e}")));
                    return None;
                }
            },
        };
        match (&self.username, &self.password_file) {
            (Some(u), _) => Some((u.clone(), password)),
            (None, Some(_)) => {
                problems.push(CardError::at(
                    "password_file",
                    "a password needs a username",
                ));
                None
            }
            (None, None) => None,
        }
    }
}

/// `host:port`, or the problem at key `broker`.
fn broker(s: &str) -> Result<(String, u16), CardError> {
    let bad = |why: &str| {
        CardError::at(
            "broker",
            format!("{s:?}: {why} (host:port, e.g. 127.0.0.1:1883)"),
        )
    };
    let (host, port) = s.rsplit_once(':').ok_or_else(|| bad("no port"))?;
    let host = host.trim_start_matches('[').trim_end_matches(']');
    if host.is_empty() {
        return Err(bad("no host"));
    }
    let port: u16 = port.parse().map_err(|_| bad("the port is not 1-65535"))?;
    if port == 0 {
        return Err(bad("the port is not 1-65535"));
    }
    Ok((host.to_string(), port))
}

fn deadband(key: &str, d: f64, problems: &mut Vec<CardError>) {
    let why = match device_interface::text::non_finite(d) {
        Some(w) => format!("{w}: give a finite deadband"),
        None if d < 0.0 => format!("{}: a deadband is not negative", Number(d)),
        None => return,
    };
    problems.push(CardError::at(key, why));
}

/// Sparkplug ids: a topic level each (no `/`, `+`, `#`), not empty.
fn sparkplug_ids(s: &SparkplugConfig, problems: &mut Vec<CardError>) {
    let ids = [("sparkplug.group", &s.group), ("sparkplug.node", &s.node)];
    let host = s
        .primary_host
        .as_ref()
        .map(|h| ("sparkplug.primary_host", h));
    for (key, id) in ids.into_iter().chain(host) {
        if let Err(why) = topic_level(id, false) {
            problems.push(CardError::at(key, why));
        }
    }
}

/// Why a name cannot be an MQTT topic level of hwgw's.
#[derive(Debug, thiserror::Error)]
pub enum TopicError {
    /// Empty or too long.
    #[error("{0:?}: 1-256 bytes")]
    Length(String),
    /// A character MQTT gives a meaning (`+`, `#`, `/` within a level, NUL).
    #[error("{text:?}: {c:?} is not allowed in a topic level")]
    Char {
        /// The name.
        text: String,
        /// The character.
        c: char,
    },
    /// Two slashes in a row, or one at an end.
    #[error("{0:?}: an empty topic level")]
    EmptyLevel(String),
}

/// `Ok` when `s` may be one MQTT topic level of hwgw's (or, with `levels`, several).
pub(crate) fn topic_level(s: &str, levels: bool) -> Result<(), TopicError> {
    if s.is_empty() || s.len() > 256 {
        return Err(TopicError::Length(s.into()));
    }
    if let Some(c) = s
        .chars()
        .find(|&c| matches!(c, '+' | '#' | '\0') || (!levels && c == '/'))
    {
        return Err(TopicError::Char { text: s.into(), c });
    }
    if levels && s.split('/').any(str::is_empty) {
        return Err(TopicError::EmptyLevel(s.into()));
    }
    Ok(())
}

fn tls_files(t: &TlsConfig, base: &Path, problems: &mut Vec<CardError>) -> Option<TlsFiles> {
    let file = |key: &str, f: &str, problems: &mut Vec<CardError>| {
        let p = base.join(f);
        match std::fs::metadata(&p) {
            Ok(m) if m.is_file() => Some(p),
            Ok(_) => {
                problems.push(CardError::at(key, format!("{f:?} is not a file")));
                None
            }
            Err(e) => {
                problems.push(CardError::at(key, format!("{f:?}: {e}")));
                None
            }
        }
    };
    let ca = file("tls.ca", &t.ca, problems);
    let client = match (&t.cert, &t.key) {
        (Some(c), Some(k)) => file("tls.cert", c, problems).zip(file("tls.key", k, problems)),
        (None, None) => None,
        (Some(_), None) => {
            problems.push(CardError::at(
                "tls.key",
                "a client certificate needs its key",
            ));
            None
        }
        (None, Some(_)) => {
            problems.push(CardError::at(
                "tls.cert",
                "a key needs its client certificate",
            ));
            None
        }
    };
    Some(TlsFiles { ca: ca?, client })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings(extra: &str) -> Result<Settings, Vec<CardError>> {
        let c: MqttConfig = toml::from_str(&format!("broker = \"b:1883\"\n{extra}\n[json]"))
            .unwrap_or_else(|e| panic!("{e}"));
        c.settings(Path::new("/nonexistent"))
    }

    fn keys(r: Result<Settings, Vec<CardError>>) -> Vec<String> {
        r.err()
            .unwrap_or_default()
            .iter()
            .map(|e| e.key.clone().unwrap_or_default())
            .collect()
    }

    #[test]
    fn defaults_and_bounds() {
        let s = settings("").unwrap_or_else(|e| panic!("{e:?}"));
        assert_eq!((s.host.as_str(), s.port), ("b", 1883));
        assert!(s.client_id.starts_with("hwgw"), "{}", s.client_id);
        assert_eq!(s.max_period, None);
        for (extra, key) in [
            ("keep_alive_s = 4", "keep_alive_s"),
            ("sample_period_ms = 9", "sample_period_ms"),
            ("queue = 15", "queue"),
            ("max_period_ms = 50", "max_period_ms"),
            ("deadband = -1.0", "deadband"),
            ("deadbands = { \"a.b\" = nan }", "deadbands.a.b"),
            ("password_file = \"p\"", "password_file"),
        ] {
            let k = keys(settings(extra));
            assert!(k.iter().any(|e| e.starts_with(key)), "{extra}: {k:?}");
        }
    }

    #[test]
    fn broker_and_topic_levels() {
        assert!(broker("h").is_err());
        assert!(broker("h:0").is_err());
        assert!(broker(":1").is_err());
        assert_eq!(broker("[::1]:8883").ok(), Some(("::1".into(), 8883)));
        assert!(topic_level("a/b", true).is_ok());
        assert!(topic_level("a/b", false).is_err());
        assert!(topic_level("a//b", true).is_err());
        assert!(topic_level("x+", true).is_err());
    }
}
