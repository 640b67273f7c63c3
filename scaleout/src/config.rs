//! The `[zenoh]` section: the gateway's name in the shared name space, how it meets the
//! others, what it imports, and the times that make a remote device stale or offline.
//!
//! Every number and list a user types here is bounded (see the constants; NaN and the
//! infinities are named as such), and every endpoint is parsed by Zenoh itself at check
//! time and its address checked — an IP address parsed strictly, the port in range, a host
//! name resolved ([`check_address`]) — so a bad one is named before anything opens.
//! Nothing here opens a socket: [`crate::Node::start`] does.

use device_interface::text::{Cut, Number, Quoted, non_finite};
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

/// A time in ms as a duration, moved into [`TIME_MS`] (NaN, which [`ZenohConfig::check`]
/// refuses, counts as `default`: nothing here panics).
fn ms(v: Option<f64>, default: f64) -> Duration {
    let v = v.filter(|v| !v.is_nan()).unwrap_or(default);
    Duration::from_secs_f64(v.clamp(TIME_MS.0, TIME_MS.1) / 1000.0)
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
                    "{} cannot name a gateway: use 1 to {MAX_NAME} letters, digits, '_' or '-'",
                    Quoted(&self.name)
                ),
            );
        }
        for (key, list) in [("listen", &self.listen), ("connect", &self.connect)] {
            if list.len() > MAX_ENDPOINTS {
                bad(key, format!("at most {MAX_ENDPOINTS} endpoints"));
            }
            for (i, e) in list.iter().enumerate() {
                if let Err(m) = self.endpoint(e, key == "listen") {
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
        let mut times_ok = true;
        for (key, v) in [
            ("publish_ms", self.publish_ms),
            ("stale_ms", self.stale_ms),
            ("offline_ms", self.offline_ms),
            ("lease_ms", self.lease_ms),
            ("request_timeout_ms", self.request_timeout_ms),
        ] {
            let Some(v) = v else { continue };
            let why = match non_finite(v) {
                Some(why) => format!("{why}: give {} ..= {} ms", TIME_MS.0, TIME_MS.1),
                None if !(TIME_MS.0..=TIME_MS.1).contains(&v) => format!(
                    "{} ms is outside {} ..= {} ms",
                    Number(v),
                    TIME_MS.0,
                    TIME_MS.1
                ),
                None => continue,
            };
            times_ok = false;
            bad(key, why);
        }
        let t = self.times();
        if times_ok && t.stale > t.offline {
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
                        "{} cannot be published (no '*', '$', '?', '#', white space or empty parts)",
                        Quoted(e)
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
                    format!("{} cannot name a gateway", Quoted(&im.gateway)),
                );
            } else if im.gateway == self.name {
                bad(
                    &format!("{at}.gateway"),
                    format!(
                        "{} is this gateway: use the device's own name",
                        Quoted(&im.gateway)
                    ),
                );
            }
            if !is_key_name(&im.device) {
                bad(
                    &format!("{at}.device"),
                    format!(
                        "{} cannot be a remote device's name (no '*', '$', '?', '#', \
                         white space or empty parts)",
                        Quoted(&im.device)
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
                        Cut(&im.local_name())
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

    /// Endpoint `e` parsed by Zenoh, one this build can use, and its address one that
    /// can be reached (`listen`: one to listen on, where port 0 picks a free port).
    fn endpoint(&self, e: &str, listen: bool) -> Result<(), String> {
        let shown = Quoted(e);
        let ep = zenoh::config::EndPoint::from_str(e).map_err(|err| {
            format!(
                "{shown} is not a Zenoh endpoint ({}); e.g. \"tcp/127.0.0.1:7447\"",
                error_text(&err.to_string())
            )
        })?;
        match ep.protocol().as_str() {
            "tcp" => {}
            "tls" if self.tls.is_some() => {}
            "tls" => {
                return Err(format!(
                    "{shown} is a TLS endpoint: give [zenoh.tls] root_ca (and cert, key to listen)"
                ));
            }
            p => {
                return Err(format!(
                    "{shown}: this build speaks tcp and tls, not {}; a router can bridge to others",
                    Quoted(p)
                ));
            }
        }
        check_address(ep.address().as_str(), listen).map_err(|err| format!("{shown}: {err}"))
    }
}

/// Why the `host:port` of a `tcp/` or `tls/` endpoint cannot be reached.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum AddressError {
    /// No `:port` after the host.
    #[error("expected host:port (e.g. 127.0.0.1:7447, [::1]:7447, gw-b.local:7447)")]
    NoPort,
    /// A port that is not a number in range.
    #[error("port {port}: expected {lowest} to 65535")]
    Port {
        /// The port as written (cut when long).
        port: String,
        /// The lowest port accepted (0 to listen: a free port is picked).
        lowest: u16,
    },
    /// Nothing before the port.
    #[error("no host before the port")]
    NoHost,
    /// A host of numbers and dots that is not an IPv4 address.
    #[error("{0} is not an IPv4 address (four numbers 0 to 255, e.g. 127.0.0.1)")]
    Ipv4(String),
    /// A host in brackets that is not an IPv6 address.
    #[error("[{0}] is not an IPv6 address (e.g. [::1]:7447)")]
    Ipv6(String),
    /// An IPv6 address without brackets.
    #[error("an IPv6 address is written in brackets before the port: [{0}]:port")]
    Unbracketed(String),
    /// A host name with characters no host name has.
    #[error("{0} is not a host name (letters, digits, '-' and '.')")]
    HostName(String),
    /// A host name the system's resolver does not know.
    #[error("host {host} does not resolve: {reason}")]
    Unresolved {
        /// The host (cut when long).
        host: String,
        /// The resolver's answer.
        reason: String,
    },
}

/// Checks the `host:port` address of a `tcp/` or `tls/` endpoint: the port 1 to 65535
/// (0 too when `listen`: a free port is picked); an IP address parsed strictly (a host
/// whose last part is a number must be an IPv4 address; an IPv6 one is in brackets); a
/// host name resolved now with the system's resolver (`getaddrinfo`), so a name that does
/// not resolve is found by `hwgw check`, not by a link that never comes up.
pub fn check_address(address: &str, listen: bool) -> Result<(), AddressError> {
    let (host, port) = address.rsplit_once(':').ok_or(AddressError::NoPort)?;
    let lowest = u16::from(!listen);
    let port = match port.parse::<u16>() {
        Ok(p) if p >= lowest && port.bytes().all(|b| b.is_ascii_digit()) => p,
        _ => {
            return Err(AddressError::Port {
                port: Cut(port).to_string(),
                lowest,
            });
        }
    };
    if host.is_empty() {
        return Err(AddressError::NoHost);
    }
    if let Some(inner) = host.strip_prefix('[').and_then(|h| h.strip_suffix(']')) {
        // A link-local address may name its interface: [fe80::1%eth0].
        let (ip, scope) = inner.split_once('%').unwrap_or((inner, "x"));
        return match ip.parse::<std::net::Ipv6Addr>() {
            Ok(_) if !scope.is_empty() => Ok(()),
            _ => Err(AddressError::Ipv6(Cut(inner).to_string())),
        };
    }
    if host.contains(':') {
        return Err(AddressError::Unbracketed(Cut(host).to_string()));
    }
    let last = host.rsplit('.').next().unwrap_or(host);
    if !last.is_empty() && last.bytes().all(|b| b.is_ascii_digit()) {
        return host
            .parse::<std::net::Ipv4Addr>()
            .map(|_| ())
            .map_err(|_| AddressError::Ipv4(Cut(host).to_string()));
    }
    let label_ok = |l: &str| {
        (1..=63).contains(&l.len())
            && !l.starts_with('-')
            && !l.ends_with('-')
            && l.bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_')
    };
    let name = host.strip_suffix('.').unwrap_or(host);
    if name.len() > 253 || !name.split('.').all(label_ok) {
        return Err(AddressError::HostName(Quoted(host).to_string()));
    }
    match std::net::ToSocketAddrs::to_socket_addrs(&(host, port)).map(|mut a| a.next()) {
        Ok(Some(_)) => Ok(()),
        Ok(None) => Err(AddressError::Unresolved {
            host: host.to_string(),
            reason: "no address".into(),
        }),
        Err(e) => Err(AddressError::Unresolved {
            host: host.to_string(),
            reason: e
                .to_string()
                .trim_start_matches("failed to lookup address information: ")
                .to_string(),
        }),
    }
}

/// A Zenoh error's text without the source location it ends with (` at /…/file.rs:N.`).
pub fn error_text(e: &str) -> &str {
    e.split_once(" at /")
        .map_or(e, |(text, _)| text)
        .trim_end_matches(':')
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;

    fn section(extra: &str) -> ZenohConfig {
        toml::from_str(&format!(
            "name = \"A\"\nlisten = [\"tcp/127.0.0.1:7447\"]\n{extra}"
        ))
        .unwrap()
    }

    #[test]
    fn times_that_are_not_numbers_are_named_and_never_panic() {
        for key in [
            "publish_ms",
            "stale_ms",
            "offline_ms",
            "lease_ms",
            "request_timeout_ms",
        ] {
            for (v, want) in [
                ("nan", "is NaN: give 1 ..= 3600000 ms"),
                ("inf", "is infinite: give 1 ..= 3600000 ms"),
                ("-inf", "is infinite: give 1 ..= 3600000 ms"),
                ("1e308", "1e308 ms is outside 1 ..= 3600000 ms"),
            ] {
                let c = section(&format!("{key} = {v}"));
                assert_eq!(
                    c.check(Path::new(".")),
                    vec![(key.to_string(), want.to_string())],
                    "{key} = {v}"
                );
                // What a caller that skipped the check gets: bounded times, no panic.
                let t = c.times();
                assert!(t.publish >= Duration::from_millis(1), "{key} = {v}");
            }
        }
    }

    #[test]
    fn addresses_parse_strictly_and_resolve() {
        for ok in [
            "127.0.0.1:7447",
            "[::1]:7447",
            "[fe80::1%eth0]:7447",
            "localhost:7447",
        ] {
            assert_eq!(check_address(ok, false), Ok(()), "{ok}");
        }
        assert_eq!(
            check_address("127.0.0.1:0", true),
            Ok(()),
            "listen on a free port"
        );
        for (bad, want) in [
            (
                "999.1.1.1:7447",
                "999.1.1.1 is not an IPv4 address (four numbers 0 to 255, e.g. 127.0.0.1)",
            ),
            ("1.2.3:7447", "1.2.3 is not an IPv4 address"),
            ("0x7f.1:7447", "0x7f.1 is not an IPv4 address"),
            ("127.0.0.1:99999", "port 99999: expected 1 to 65535"),
            ("127.0.0.1:0", "port 0: expected 1 to 65535"),
            ("127.0.0.1:+80", "port +80: expected 1 to 65535"),
            ("127.0.0.1", "expected host:port"),
            (":7447", "no host before the port"),
            ("[::g]:7447", "[::g] is not an IPv6 address"),
            ("::1:7447", "an IPv6 address is written in brackets"),
            ("a b:7447", "\"a b\" is not a host name"),
            (
                "nosuchhost.invalid:7447",
                "host nosuchhost.invalid does not resolve: ",
            ),
        ] {
            let e = check_address(bad, false).unwrap_err().to_string();
            assert!(e.starts_with(want), "{bad}: {e}");
        }
        let long = format!("127.0.0.1:{}", "9".repeat(200));
        let e = check_address(&long, true).unwrap_err().to_string();
        assert!(e.len() < 150 && e.contains("… (200 characters)"), "{e}");
    }

    #[test]
    fn endpoints_that_cannot_be_reached_are_refused() {
        let c = section("connect = [\"tcp/999.1.1.1:7447\", \"tcp/127.0.0.1:99999\"]");
        let got = c.check(Path::new("."));
        assert_eq!(
            got,
            vec![
                (
                    "connect[0]".to_string(),
                    "\"tcp/999.1.1.1:7447\": 999.1.1.1 is not an IPv4 address (four numbers 0 \
                     to 255, e.g. 127.0.0.1)"
                        .to_string()
                ),
                (
                    "connect[1]".to_string(),
                    "\"tcp/127.0.0.1:99999\": port 99999: expected 1 to 65535".to_string()
                ),
            ]
        );
    }
}
