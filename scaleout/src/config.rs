//! The `[zenoh]` section: the gateway's name in the shared name space, how it meets the
//! others, what it imports, and the times that make a remote device stale or offline.
//!
//! Every number and list a user types here is bounded (see the constants), and every
//! endpoint is parsed by Zenoh itself at check time, so a bad one is named before anything
//! opens. Nothing here opens a socket: [`crate::Node::start`] does.

use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Duration;

/// Longest gateway or device name part, bytes.
pub const MAX_NAME: usize = 64;
/// Most endpoints in `listen` or `connect`.
pub const MAX_ENDPOINTS: usize = 32;
/// Most `[[zenoh.import]]` entries.
pub const MAX_IMPORTS: usize = 256;
/// Most `export` entries.
pub const MAX_EXPORTS: usize = 1024;
/// Samples an exported port holds between two publications; beyond, they are dropped and
/// counted.
pub const EXPORT_BUFFER: usize = 1024;
/// Most channels (or bits) one imported interface may declare: a sample of a device this
/// big is about 256 KiB of JSON, under the transport's message bound.
pub const MAX_CHANNELS: u32 = 4096;
/// The largest message a peer may send us, bytes: room for the largest sample (4096
/// channels, about 100 KiB of JSON) and a forwarded `status` of a big gateway (Zenoh's own
/// default is 1 GiB; a hostile peer could make us allocate that).
pub const MAX_MESSAGE: usize = 4 * 1024 * 1024;

/// The `[zenoh]` section of a deployment.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZenohConfig {
    /// This gateway's name in the shared name space: its keys are `hwgw/<name>/…` and
    /// other gateways call its devices `<name>/<device>`.
    pub name: String,
    /// `peer` (default: meets the others directly) or `client` (through a router).
    #[serde(default)]
    pub mode: Mode,
    /// Where this gateway listens for the others (`tcp/127.0.0.1:7447`,
    /// `tls/host:7447`). Nothing listens unless given.
    #[serde(default)]
    pub listen: Vec<String>,
    /// Which gateways or routers this one connects to; retried until they are up.
    #[serde(default)]
    pub connect: Vec<String>,
    /// Certificates for `tls/` endpoints.
    #[serde(default)]
    pub tls: Option<TlsConfig>,
    /// Tell the peers met about each other (Zenoh gossip scouting). Default false: only
    /// the endpoints written here are used.
    #[serde(default)]
    pub gossip: bool,
    /// How often the devices and exported ports are published, ms (default 10); the
    /// imported devices' IO components sample at this period too.
    #[serde(default)]
    pub publish_ms: Option<f64>,
    /// A remote device whose last sample is older than this is stale, ms (default 5
    /// publish periods).
    #[serde(default)]
    pub stale_ms: Option<f64>,
    /// ... and offline, ms (default 1000).
    #[serde(default)]
    pub offline_ms: Option<f64>,
    /// How long the link to a peer may be silent before Zenoh closes it, ms (default
    /// 2000; Zenoh's own is 10 000).
    #[serde(default)]
    pub lease_ms: Option<f64>,
    /// Remote control requests (`hwgw get B/…`) wait this long for an answer, ms
    /// (default 2000).
    #[serde(default)]
    pub request_timeout_ms: Option<f64>,
    /// Devices of other gateways used here, by name.
    #[serde(default)]
    pub import: Vec<ImportConfig>,
    /// Output ports published for other gateways to connect to: `component.port`, or
    /// `component` for all its output ports.
    #[serde(default)]
    pub export: Vec<String>,
}

/// One remote device used here: it is registered as `<gateway>/<device>` under each
/// interface given, with the number of channels (bits) this deployment expects. The shape
/// is checked against the remote gateway's own once connected; a device that does not
/// match stays offline and says why.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImportConfig {
    /// The gateway that has the device (its `[zenoh] name`).
    pub gateway: String,
    /// The device's name there.
    pub device: String,
    /// Analog inputs expected.
    #[serde(default)]
    pub analog_in: Option<u32>,
    /// Analog outputs expected.
    #[serde(default)]
    pub analog_out: Option<u32>,
    /// Digital inputs expected.
    #[serde(default)]
    pub digital_in: Option<u32>,
    /// Digital outputs expected.
    #[serde(default)]
    pub digital_out: Option<u32>,
    /// The device is an encoder there too.
    #[serde(default)]
    pub encoder: bool,
}

impl ImportConfig {
    /// The name the device has here: `<gateway>/<device>`.
    pub fn local_name(&self) -> String {
        format!("{}/{}", self.gateway, self.device)
    }
}

/// How this gateway takes part.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// Meets other peers directly (listen and/or connect).
    #[default]
    Peer,
    /// Connects to routers (or peers) and routes through them; listens nowhere.
    Client,
}

/// Certificates for TLS links (`tls/` endpoints).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsConfig {
    /// The CA that signed the peers' certificates (PEM).
    pub root_ca: PathBuf,
    /// This gateway's certificate (PEM), for listening and, with `mtls`, connecting.
    #[serde(default)]
    pub cert: Option<PathBuf>,
    /// Its private key (PEM).
    #[serde(default)]
    pub key: Option<PathBuf>,
    /// Both sides show a certificate (mutual TLS).
    #[serde(default)]
    pub mtls: bool,
}

/// The times of a node, from the section and its defaults.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Times {
    /// Publication period.
    pub publish: Duration,
    /// Age from which a remote device is stale.
    pub stale: Duration,
    /// Age from which it is offline.
    pub offline: Duration,
    /// Zenoh's link lease.
    pub lease: Duration,
    /// Remote request timeout.
    pub request: Duration,
}

/// Bounds of the times, ms.
const TIME_MS: (f64, f64) = (1.0, 3_600_000.0);

fn ms(v: Option<f64>, default: f64) -> Duration {
    Duration::from_secs_f64(v.unwrap_or(default).clamp(TIME_MS.0, TIME_MS.1) / 1000.0)
}

/// True when `s` can be one chunk of a key expression and a gateway name: letters,
/// digits, `_` and `-`, at most [`MAX_NAME`] bytes.
pub fn is_gateway_name(s: &str) -> bool {
    !s.is_empty()
        && s.len() <= MAX_NAME
        && s.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

/// True when device name `s` can be published as key chunks: no wildcard or reserved
/// characters (`*`, `$`, `?`, `#`, `@` first), no empty chunk, no white space.
pub fn is_key_name(s: &str) -> bool {
    !s.is_empty()
        && s.len() <= 4 * MAX_NAME
        && s.split('/').all(|c| {
            !c.is_empty()
                && !c.starts_with('@')
                && !c
                    .chars()
                    .any(|ch| matches!(ch, '*' | '$' | '?' | '#') || ch.is_whitespace())
        })
}

impl ZenohConfig {
    /// The times, defaults filled in.
    pub fn times(&self) -> Times {
        let publish = ms(self.publish_ms, 10.0);
        let offline = ms(self.offline_ms, 1000.0);
        Times {
            publish,
            stale: match self.stale_ms {
                Some(v) => ms(Some(v), 0.0),
                None => (publish * 5).min(offline),
            },
            offline,
            lease: ms(self.lease_ms, 2000.0),
            request: ms(self.request_timeout_ms, 2000.0),
        }
    }

    /// Every problem of the section, as (key under `zenoh`, message); file paths are
    /// relative to `base`.
    pub fn check(&self, base: &Path) -> Vec<(String, String)> {
        let mut out = Vec::new();
        let mut bad = |k: &str, m: String| out.push((k.to_string(), m));
        if !is_gateway_name(&self.name) {
            bad(
                "name",
                format!(
                    "{:?} cannot name a gateway: use 1 to {MAX_NAME} letters, digits, '_' or '-'",
                    self.name
                ),
            );
        }
        for (key, list) in [("listen", &self.listen), ("connect", &self.connect)] {
            if list.len() > MAX_ENDPOINTS {
                bad(key, format!("at most {MAX_ENDPOINTS} endpoints"));
            }
            for (i, e) in list.iter().enumerate() {
                if let Err(m) = self.endpoint(e) {
                    bad(&format!("{key}[{i}]"), m);
                }
            }
        }
        if self.mode == Mode::Client && !self.listen.is_empty() {
            bad(
                "listen",
                "a client listens nowhere: use mode = \"peer\"".into(),
            );
        }
        if self.listen.is_empty() && self.connect.is_empty() {
            bad(
                "listen",
                "nothing to listen on and nothing to connect to: give `listen` or `connect` \
                 (e.g. listen = [\"tcp/127.0.0.1:7447\"])"
                    .into(),
            );
        }
        for (key, v) in [
            ("publish_ms", self.publish_ms),
            ("stale_ms", self.stale_ms),
            ("offline_ms", self.offline_ms),
            ("lease_ms", self.lease_ms),
            ("request_timeout_ms", self.request_timeout_ms),
        ] {
            if let Some(v) = v
                && !(TIME_MS.0..=TIME_MS.1).contains(&v)
            {
                bad(
                    key,
                    format!("{v} ms is outside {} ..= {} ms", TIME_MS.0, TIME_MS.1),
                );
            }
        }
        let t = self.times();
        if t.stale > t.offline {
            bad(
                "stale_ms",
                format!(
                    "a device is stale ({} ms) before it is offline ({} ms), not after",
                    t.stale.as_millis(),
                    t.offline.as_millis()
                ),
            );
        }
        if let Some(tls) = &self.tls {
            for (key, f) in [
                ("tls.root_ca", Some(&tls.root_ca)),
                ("tls.cert", tls.cert.as_ref()),
                ("tls.key", tls.key.as_ref()),
            ] {
                if let Some(f) = f
                    && !base.join(f).is_file()
                {
                    bad(key, format!("{}: no such file", base.join(f).display()));
                }
            }
            if tls.cert.is_some() != tls.key.is_some() {
                bad("tls", "give both `cert` and `key`, or neither".into());
            }
        }
        self.check_imports(&mut bad);
        if self.export.len() > MAX_EXPORTS {
            bad("export", format!("at most {MAX_EXPORTS} exported ports"));
        }
        for (i, e) in self.export.iter().enumerate() {
            if !is_key_name(e) {
                bad(
                    &format!("export[{i}]"),
                    format!(
                        "{e:?} cannot be published (no '*', '$', '?', '#', white space or empty parts)"
                    ),
                );
            }
        }
        out
    }

    fn check_imports(&self, bad: &mut impl FnMut(&str, String)) {
        if self.import.len() > MAX_IMPORTS {
            bad("import", format!("at most {MAX_IMPORTS} imported devices"));
        }
        for (i, im) in self.import.iter().enumerate() {
            let at = format!("import[{i}]");
            if !is_gateway_name(&im.gateway) {
                bad(
                    &format!("{at}.gateway"),
                    format!("{:?} cannot name a gateway", im.gateway),
                );
            } else if im.gateway == self.name {
                bad(
                    &format!("{at}.gateway"),
                    format!(
                        "{:?} is this gateway: use the device's own name",
                        im.gateway
                    ),
                );
            }
            if !is_key_name(&im.device) {
                bad(
                    &format!("{at}.device"),
                    format!(
                        "{:?} cannot be a remote device's name (no '*', '$', '?', '#', \
                         white space or empty parts)",
                        im.device
                    ),
                );
            }
            if let Some(j) = self.import[..i]
                .iter()
                .position(|o| o.gateway == im.gateway && o.device == im.device)
            {
                bad(
                    &at,
                    format!(
                        "{} is imported twice (first as import[{j}])",
                        im.local_name()
                    ),
                );
            }
            let counts = [
                ("analog_in", im.analog_in),
                ("analog_out", im.analog_out),
                ("digital_in", im.digital_in),
                ("digital_out", im.digital_out),
            ];
            for (key, n) in counts {
                if let Some(n) = n
                    && !(1..=MAX_CHANNELS).contains(&n)
                {
                    bad(
                        &format!("{at}.{key}"),
                        format!("{n} channels: give 1 ..= {MAX_CHANNELS}"),
                    );
                }
            }
            if counts.iter().all(|(_, n)| n.is_none()) && !im.encoder {
                bad(
                    &at,
                    "no interface: give analog_in, analog_out, digital_in, digital_out \
                     (channel counts) or encoder = true"
                        .into(),
                );
            }
        }
    }

    /// Endpoint `e` parsed by Zenoh, and one this build can use.
    fn endpoint(&self, e: &str) -> Result<(), String> {
        let ep = zenoh::config::EndPoint::from_str(e).map_err(|err| {
            format!(
                "{e:?} is not a Zenoh endpoint ({}); e.g. \"tcp/127.0.0.1:7447\"",
                error_text(&err.to_string())
            )
        })?;
        match ep.protocol().as_str() {
            "tcp" => Ok(()),
            "tls" if self.tls.is_some() => Ok(()),
            "tls" => Err(format!(
                "{e:?} is a TLS endpoint: give [zenoh.tls] root_ca (and cert, key to listen)"
            )),
            p => Err(format!(
                "{e:?}: this build speaks tcp and tls, not {p:?}; a router can bridge to others"
            )),
        }
    }
}

/// A Zenoh error's text without the source location it ends with (` at /…/file.rs:N.`).
pub fn error_text(e: &str) -> &str {
    e.split_once(" at /")
        .map_or(e, |(text, _)| text)
        .trim_end_matches(':')
}
