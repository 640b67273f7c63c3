//! The `[server.metrics]` and `[server.web]` sections, typed and checked: where to listen
//! (127.0.0.1 unless the deployment says otherwise), how many clients, which ports.
//!
//! ```
//! use web::{MetricsConfig, WebConfig};
//!
//! let m: MetricsConfig = toml::from_str(r#"ports = ["sim0.ai.ch0"]"#)?;
//! assert_eq!(m.listen, "127.0.0.1:9464");
//! let w: WebConfig = toml::from_str(r#"
//!     listen = "127.0.0.1:8088"
//!     ports = ["sim0.ai.ch0", "sim0.ao.ch1"]
//!     allow_writes = true
//!     token = "a long secret of the deployment"
//! "#)?;
//! assert!(w.allow_writes);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use driver_api::{CardError, ServerContext};
use serde::Deserialize;
use std::net::{SocketAddr, ToSocketAddrs};
use std::time::Duration;

/// `[server.metrics]`: Prometheus `/metrics` and `/health`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MetricsConfig {
    /// `address:port` (default 127.0.0.1:9464; another address only on purpose).
    #[serde(default = "default_metrics_listen")]
    pub listen: String,
    /// Connections at once (1–1024, default 16).
    #[serde(default = "default_clients")]
    pub max_clients: usize,
    /// Ports whose values are metrics too (`component.port`): per-channel values are
    /// opt-in, so a big deployment makes no series it was not asked for.
    #[serde(default)]
    pub ports: Vec<String>,
    /// Host names it answers to besides its addresses and `localhost` (a request whose
    /// `Host` names another is refused: a web page of another site cannot reach it through
    /// a name of its own).
    #[serde(default)]
    pub hosts: Vec<String>,
}

/// `[server.web]`: the web page.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WebConfig {
    /// `address:port` (default 127.0.0.1:8088; another address only on purpose).
    #[serde(default = "default_web_listen")]
    pub listen: String,
    /// Connections at once, live streams among them (1–1024, default 32).
    #[serde(default = "default_web_clients")]
    pub max_clients: usize,
    /// Ports shown live, with a plot each (`component.port`, at most 64).
    #[serde(default)]
    pub ports: Vec<String>,
    /// How often the live ports are read, ms (10–10000, default 100).
    #[serde(default = "default_sample_ms")]
    pub sample_ms: u64,
    /// The page may set the listed input ports (device outputs), with the token.
    #[serde(default)]
    pub allow_writes: bool,
    /// What a write must carry (`Authorization: Bearer TOKEN`); at least 16 characters;
    /// required with `allow_writes`.
    #[serde(default)]
    pub token: Option<String>,
    /// Host names it answers to besides its addresses and `localhost`.
    #[serde(default)]
    pub hosts: Vec<String>,
}

fn default_metrics_listen() -> String {
    "127.0.0.1:9464".into()
}
fn default_web_listen() -> String {
    "127.0.0.1:8088".into()
}
fn default_clients() -> usize {
    16
}
fn default_web_clients() -> usize {
    32
}
fn default_sample_ms() -> u64 {
    100
}

/// How long a request's head may take to arrive.
pub const HEAD_TIMEOUT: Duration = Duration::from_secs(5);
/// The largest request head taken, bytes.
pub const MAX_HEAD: usize = 16 * 1024;
/// The most live ports of a page.
pub const MAX_PORTS: usize = 64;

/// A listed port: its component and port names.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct PortRef {
    /// The component (`sim0.ai`).
    pub component: String,
    /// Its port (`ch0`).
    pub port: String,
    /// An input port: one a write (`hwgw set`) may set.
    pub input: bool,
}

impl PortRef {
    /// `component.port`, as written.
    pub fn name(&self) -> String {
        format!("{}.{}", self.component, self.port)
    }
}

/// A section's `listen` resolved and its `max_clients` checked; each problem to
/// `problems`.
pub(crate) fn endpoint(
    listen: &str,
    max_clients: usize,
    problems: &mut Vec<CardError>,
) -> Option<(SocketAddr, usize)> {
    let address = address(listen).map_err(|e| problems.push(e)).ok();
    let clients = clients("max_clients", max_clients)
        .map_err(|e| problems.push(e))
        .ok();
    address.zip(clients)
}

/// The token writes must bring: at least 16 characters, and required with
/// `allow_writes`; the problem at key `token` to `problems`.
pub(crate) fn token(
    token: &Option<String>,
    allow_writes: bool,
    problems: &mut Vec<CardError>,
) -> Option<String> {
    match (token, allow_writes) {
        (Some(t), _) if t.chars().count() < 16 => {
            problems.push(CardError::at("token", "at least 16 characters"));
            None
        }
        (None, true) => {
            problems.push(CardError::at("token", "allow_writes needs a token"));
            None
        }
        (t, _) => t.clone(),
    }
}

/// `listen` resolved, or the problem at key `listen`.
fn address(listen: &str) -> Result<SocketAddr, CardError> {
    match listen.to_socket_addrs().map(|mut a| a.next()) {
        Ok(Some(a)) => Ok(a),
        Ok(None) => Err(CardError::at("listen", format!("{listen:?}: no address"))),
        Err(e) => Err(CardError::at(
            "listen",
            format!("{listen:?}: {e} (address:port, e.g. 127.0.0.1:9464)"),
        )),
    }
}

/// `n` within 1–1024, or the problem at `key`.
fn clients(key: &str, n: usize) -> Result<usize, CardError> {
    if (1..=1024).contains(&n) {
        Ok(n)
    } else {
        Err(CardError::at(key, format!("{n}: 1-1024")))
    }
}

/// Each of `ports` (at key `ports`) split into component and port, both found in the
/// deployment; every problem, each naming what exists.
pub(crate) fn ports(
    list: &[String],
    ctx: &ServerContext<'_>,
) -> Result<Vec<PortRef>, Vec<CardError>> {
    let mut out = Vec::new();
    let mut problems = Vec::new();
    if list.len() > MAX_PORTS {
        problems.push(CardError::at(
            "ports",
            format!("{} ports: at most {MAX_PORTS}", list.len()),
        ));
    }
    for (i, name) in list.iter().enumerate() {
        let key = format!("ports[{i}]");
        match resolve(name, ctx) {
            Ok(p) => out.push(p),
            Err(message) => problems.push(CardError::at(key, message)),
        }
    }
    if problems.is_empty() {
        Ok(out)
    } else {
        Err(problems)
    }
}

fn resolve(name: &str, ctx: &ServerContext<'_>) -> Result<PortRef, String> {
    let Some((component, port)) = name.rsplit_once('.') else {
        return Err(format!("{name:?}: component.port"));
    };
    let rt = ctx.runtime();
    let task = rt
        .component(component)
        .map_err(|e| format!("{name:?}: {e}"))?;
    let ports = task.ports();
    let Some(info) = ports.iter().find(|p| p.name == port) else {
        let names: Vec<&str> = ports.iter().map(|p| p.name.as_str()).collect();
        return Err(format!(
            "{name:?}: {component} has no port {port:?}; its ports: {}",
            names.join(", ")
        ));
    };
    Ok(PortRef {
        component: component.to_string(),
        port: port.to_string(),
        input: info.direction == rtt::info::Direction::Input,
    })
}
