//! The `[server.opcua]` section, typed and checked: where the server listens, its
//! security (endpoints, certificates, users and roles), what it serves and its limits.
//!
//! ```
//! use opcua::OpcuaConfig;
//!
//! let c: OpcuaConfig = toml::from_str(r#"
//!     listen = "127.0.0.1:4840"
//!     pki_dir = "opcua-pki"
//!     allow_writes = true
//! "#)?;
//! assert_eq!(c.sample_period_ms, 10);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use driver_api::CardError;
use serde::Deserialize;
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// `[server.opcua]`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OpcuaConfig {
    /// Where the server listens, `address:port` (4840 is OPC UA's port).
    pub listen: String,
    /// The endpoints offered (default all five): `"none"`, `"basic256sha256_sign"`,
    /// `"basic256sha256_sign_encrypt"`, `"aes128_sha256_rsaoaep_sign"`,
    /// `"aes128_sha256_rsaoaep_sign_encrypt"`. `"none"` on an address other than loopback
    /// needs `allow_none_remote`.
    #[serde(default = "default_security")]
    pub security: Vec<Security>,
    /// Offer the unsecured endpoint on an address other than loopback.
    #[serde(default)]
    pub allow_none_remote: bool,
    /// The server's certificate store, relative to the deployment's folder: its
    /// certificate `own/cert.der` and key `private/private.pem` (made on first start when
    /// neither is there, never over one that is); a client's certificate that is not
    /// trusted is refused and put in `rejected/`: moved to `trusted/`, it is trusted.
    pub pki_dir: String,
    /// What a client without a user name may do: `"none"` (it may not connect),
    /// `"read_only"` (default) or `"operator"`.
    #[serde(default = "default_anonymous")]
    pub anonymous: Role,
    /// A TOML file of users (relative to the deployment's folder), readable by its owner
    /// only: `[users.NAME]` with `password` and `role` (`"read_only"` or `"operator"`).
    /// User names are taken on the signed and encrypted endpoints only, never in clear.
    #[serde(default)]
    pub users_file: Option<String>,
    /// Outputs may be written (by operators), through the checks `hwgw set` passes.
    #[serde(default)]
    pub allow_writes: bool,
    /// Operations of components may be called (by operators).
    #[serde(default)]
    pub allow_calls: bool,
    /// How often channel values are read from the devices, ms (1–60000, default 10): the
    /// shortest sampling interval a monitored item gets.
    #[serde(default = "default_sample")]
    pub sample_period_ms: u64,
    /// The devices served, by registry name (`sim0`); default every device of the five
    /// channel interfaces.
    #[serde(default)]
    pub devices: Vec<String>,
    /// The server's application URI (default `urn:hwgw:` and the host's name); it is in
    /// the certificate made on first start.
    #[serde(default)]
    pub application_uri: Option<String>,
    /// Limits.
    #[serde(default)]
    pub limits: LimitsConfig,
}

/// `[server.opcua.limits]`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LimitsConfig {
    /// Sessions at once (1–1000, default 20).
    #[serde(default = "default_sessions")]
    pub sessions: usize,
    /// Subscriptions of a session (1–1000, default 5).
    #[serde(default = "default_subscriptions")]
    pub subscriptions_per_session: usize,
    /// Monitored items of a subscription (1–100000, default 20000).
    #[serde(default = "default_items")]
    pub monitored_items_per_subscription: usize,
    /// Values a monitored item queues (1–1000, default 10).
    #[serde(default = "default_queue")]
    pub queue_size: usize,
    /// Notifications a subscription holds for its client (100–1000000, default 100000).
    #[serde(default = "default_queued")]
    pub queued_notifications: usize,
    /// A message's size, KiB (64–65536, default 4096).
    #[serde(default = "default_message_kib")]
    pub message_kib: usize,
    /// Notifications one publish response carries, at most (100–100000; default as many
    /// as fit in a message at 256 bytes each, 16384 for 4096 KiB): lower it for a client
    /// that takes shorter arrays; the rest go in the next responses.
    #[serde(default)]
    pub notifications_per_publish: Option<usize>,
    /// A session nobody uses ends after this, s (1–3600, default 60).
    #[serde(default = "default_session_timeout")]
    pub session_timeout_s: u64,
}

impl Default for LimitsConfig {
    fn default() -> Self {
        LimitsConfig {
            sessions: default_sessions(),
            subscriptions_per_session: default_subscriptions(),
            monitored_items_per_subscription: default_items(),
            queue_size: default_queue(),
            queued_notifications: default_queued(),
            message_kib: default_message_kib(),
            notifications_per_publish: None,
            session_timeout_s: default_session_timeout(),
        }
    }
}

/// An endpoint's security: its policy and mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Security {
    /// No security.
    None,
    /// Basic256Sha256, signed.
    Basic256sha256Sign,
    /// Basic256Sha256, signed and encrypted.
    Basic256sha256SignEncrypt,
    /// Aes128_Sha256_RsaOaep, signed.
    Aes128Sha256RsaoaepSign,
    /// Aes128_Sha256_RsaOaep, signed and encrypted.
    Aes128Sha256RsaoaepSignEncrypt,
}

impl Security {
    /// Its name in the section.
    pub fn name(self) -> &'static str {
        match self {
            Security::None => "none",
            Security::Basic256sha256Sign => "basic256sha256_sign",
            Security::Basic256sha256SignEncrypt => "basic256sha256_sign_encrypt",
            Security::Aes128Sha256RsaoaepSign => "aes128_sha256_rsaoaep_sign",
            Security::Aes128Sha256RsaoaepSignEncrypt => "aes128_sha256_rsaoaep_sign_encrypt",
        }
    }
}

/// What a user may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    /// Nothing (only for `anonymous`: no anonymous sessions).
    None,
    /// Browse, read and subscribe.
    ReadOnly,
    /// Also write outputs and call operations (where the section allows them).
    Operator,
}

fn default_security() -> Vec<Security> {
    vec![
        Security::None,
        Security::Basic256sha256Sign,
        Security::Basic256sha256SignEncrypt,
        Security::Aes128Sha256RsaoaepSign,
        Security::Aes128Sha256RsaoaepSignEncrypt,
    ]
}
fn default_anonymous() -> Role {
    Role::ReadOnly
}
fn default_sample() -> u64 {
    10
}
fn default_sessions() -> usize {
    20
}
fn default_subscriptions() -> usize {
    5
}
fn default_items() -> usize {
    20_000
}
fn default_queue() -> usize {
    10
}
fn default_queued() -> usize {
    100_000
}
fn default_message_kib() -> usize {
    4096
}
fn default_session_timeout() -> u64 {
    60
}

/// A user of the users file (its password not shown when debugged).
#[derive(Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct User {
    /// The password.
    pub password: String,
    /// The role: `"read_only"` or `"operator"`.
    pub role: Role,
}

impl std::fmt::Debug for User {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("User")
            .field("password", &"****")
            .field("role", &self.role)
            .finish()
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct UsersFile {
    #[serde(default)]
    users: BTreeMap<String, User>,
}

/// The section checked: what the server runs with.
#[derive(Debug, Clone)]
pub struct Settings {
    /// The listening address.
    pub listen: SocketAddr,
    /// The endpoints, without duplicates.
    pub security: Vec<Security>,
    /// The certificate store, resolved.
    pub pki_dir: PathBuf,
    /// The anonymous role.
    pub anonymous: Role,
    /// The users by name.
    pub users: BTreeMap<String, User>,
    /// Writes allowed.
    pub allow_writes: bool,
    /// Calls allowed.
    pub allow_calls: bool,
    /// Reading period.
    pub sample: Duration,
    /// The application URI.
    pub application_uri: String,
    /// Limits.
    pub limits: LimitsConfig,
}

impl OpcuaConfig {
    /// The section checked, files resolved against `base`; every problem at its key.
    pub fn settings(&self, base: &Path) -> Result<Settings, Vec<CardError>> {
        let mut problems = Vec::new();
        let listen = match self.listen.parse::<SocketAddr>() {
            Ok(a) => Some(a),
            Err(e) => {
                problems.push(CardError::at(
                    "listen",
                    format!("{:?}: {e} (address:port, e.g. 127.0.0.1:4840)", self.listen),
                ));
                None
            }
        };
        let mut security = self.security.clone();
        security.sort();
        security.dedup();
        if security.is_empty() {
            problems.push(CardError::at("security", "no endpoint: name one at least"));
        }
        if let Some(a) = listen
            && security.contains(&Security::None)
            && !a.ip().is_loopback()
            && !self.allow_none_remote
        {
            problems.push(CardError::at(
                "security",
                format!(
                    "\"none\" on {a}, which is not loopback, lets anyone on the network in \
                     unsigned: leave it out, or set allow_none_remote = true"
                ),
            ));
        }
        if self.pki_dir.is_empty() {
            problems.push(CardError::at("pki_dir", "empty: name a folder"));
        }
        let mut bound = |key: &str, v: u64, lo: u64, hi: u64, unit: &str| {
            if !(lo..=hi).contains(&v) {
                problems.push(CardError::at(key, format!("{v}: {lo}-{hi} {unit}")));
            }
        };
        let l = &self.limits;
        bound("sample_period_ms", self.sample_period_ms, 1, 60_000, "ms");
        bound("limits.sessions", l.sessions as u64, 1, 1000, "sessions");
        bound(
            "limits.subscriptions_per_session",
            l.subscriptions_per_session as u64,
            1,
            1000,
            "subscriptions",
        );
        bound(
            "limits.monitored_items_per_subscription",
            l.monitored_items_per_subscription as u64,
            1,
            100_000,
            "items",
        );
        bound("limits.queue_size", l.queue_size as u64, 1, 1000, "values");
        bound(
            "limits.queued_notifications",
            l.queued_notifications as u64,
            100,
            1_000_000,
            "notifications",
        );
        bound(
            "limits.message_kib",
            l.message_kib as u64,
            64,
            65_536,
            "KiB",
        );
        if let Some(n) = l.notifications_per_publish {
            bound(
                "limits.notifications_per_publish",
                n as u64,
                100,
                100_000,
                "notifications",
            );
        }
        bound(
            "limits.session_timeout_s",
            l.session_timeout_s,
            1,
            3600,
            "s",
        );
        let users = match &self.users_file {
            None => BTreeMap::new(),
            Some(f) => match users(&base.join(f)) {
                Ok(u) => u,
                Err(why) => {
                    problems.push(CardError::at("users_file", format!("{f:?}: {why}")));
                    BTreeMap::new()
                }
            },
        };
        if self.anonymous == Role::None && self.users_file.is_none() {
            problems.push(CardError::at(
                "anonymous",
                "\"none\" without a users_file: nobody could connect",
            ));
        }
        if self.anonymous == Role::None && security == [Security::None] {
            problems.push(CardError::at(
                "security",
                "only \"none\", where user names are not taken, and anonymous = \"none\": \
                 nobody could connect",
            ));
        }
        let application_uri = self.application_uri.clone().unwrap_or_else(|| {
            let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
                .map(|h| h.trim().to_string())
                .unwrap_or_else(|_| "localhost".into());
            format!("urn:hwgw:{host}")
        });
        let (Some(listen), true) = (listen, problems.is_empty()) else {
            return Err(problems);
        };
        Ok(Settings {
            listen,
            security,
            pki_dir: base.join(&self.pki_dir),
            anonymous: self.anonymous,
            users,
            allow_writes: self.allow_writes,
            allow_calls: self.allow_calls,
            sample: Duration::from_millis(self.sample_period_ms),
            application_uri,
            limits: self.limits.clone(),
        })
    }
}

/// The users of file `path`: refused when others may read it (it holds passwords), when
/// it is not TOML of `[users.NAME]` tables, or a user's role is `"none"`.
fn users(path: &Path) -> Result<BTreeMap<String, User>, String> {
    use std::os::unix::fs::PermissionsExt;
    let meta = std::fs::metadata(path).map_err(|e| e.to_string())?;
    let mode = meta.permissions().mode() & 0o777;
    if mode & 0o077 != 0 {
        return Err(format!(
            "holds passwords but its mode is {mode:04o}: make it readable by its owner \
             only (chmod 600)"
        ));
    }
    let text = std::fs::read_to_string(path).map_err(|e| e.to_string())?;
    // toml's own text quotes the line, which may hold a password: its message and line
    // only.
    let file: UsersFile = toml::from_str(&text).map_err(|e| {
        let line = e.span().map_or(0, |s| {
            text[..s.start.min(text.len())].matches('\n').count() + 1
        });
        format!("line {line}: {}", e.message())
    })?;
    for (name, u) in &file.users {
        if u.role == Role::None {
            return Err(format!(
                "users.{name}.role: \"none\" is for anonymous only; a user is \"read_only\" \
                 or \"operator\""
            ));
        }
        if name.is_empty() || name.len() > 256 {
            return Err("a user name is 1-256 bytes".into());
        }
    }
    Ok(file.users)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> OpcuaConfig {
        toml::from_str(text).expect("parses")
    }

    #[test]
    fn notifications_per_publish_is_bounded() {
        let c = parse(
            "listen = \"127.0.0.1:4840\"\npki_dir = \"p\"\n[limits]\nnotifications_per_publish = 0",
        );
        let e = c.settings(Path::new("/tmp")).expect_err("refused");
        assert!(e[0].to_string().contains("100-100000"), "{e:?}");
    }

    #[test]
    fn none_off_loopback_needs_leave() {
        let c = parse("listen = \"0.0.0.0:4840\"\npki_dir = \"pki\"");
        let e = c.settings(Path::new("/tmp")).expect_err("refused");
        assert!(e[0].to_string().contains("allow_none_remote"), "{e:?}");
        let c = parse("listen = \"0.0.0.0:4840\"\npki_dir = \"pki\"\nallow_none_remote = true");
        assert!(c.settings(Path::new("/tmp")).is_ok());
        let c = parse(
            "listen = \"0.0.0.0:4840\"\npki_dir = \"pki\"\nsecurity = [\"basic256sha256_sign_encrypt\"]",
        );
        assert!(c.settings(Path::new("/tmp")).is_ok());
    }

    #[test]
    fn users_file_must_be_private() {
        let dir = std::env::temp_dir().join(format!("hwgw-opcua-users-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let f = dir.join("users.toml");
        std::fs::write(
            &f,
            "[users.ann]\npassword = \"pw\"\nrole = \"operator\"\n[users.bob]\npassword = \"x\"\nrole = \"read_only\"\n",
        )
        .expect("write");
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&f, std::fs::Permissions::from_mode(0o644)).expect("chmod");
        assert!(users(&f).expect_err("refused").contains("chmod 600"));
        std::fs::set_permissions(&f, std::fs::Permissions::from_mode(0o600)).expect("chmod");
        let u = users(&f).expect("read");
        assert_eq!(u["ann"].role, Role::Operator);
        assert_eq!(u["bob"].role, Role::ReadOnly);
        assert!(!format!("{u:?}").contains("pw"), "{u:?}");
        // A mistake on a password's line does not show the password.
        std::fs::write(
            &f,
            "[users.ann]\npasword = \"s3cret\"\nrole = \"operator\"\n",
        )
        .expect("write");
        let e = users(&f).expect_err("refused");
        assert!(e.starts_with("line 2: ") && !e.contains("s3cret"), "{e}");
        std::fs::remove_dir_all(&dir).expect("clean");
    }
}
