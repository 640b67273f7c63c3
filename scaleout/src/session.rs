//! The Zenoh session of a node, opened from the `[zenoh]` section with every default that
//! would reach beyond it turned off, and the few ways the node uses it.
//!
//! Zenoh's defaults listen on every interface and scout by UDP multicast (even without the
//! UDP transport); here nothing listens but `listen`, multicast scouting is off, gossip is
//! as configured, a link is dropped after `lease_ms` of silence, a peer may send at most
//! [`crate::config::MAX_MESSAGE`] bytes, a bad or busy `listen` endpoint fails
//! the open at once, and `connect` endpoints are retried in the background (so an absent
//! peer never blocks start-up).

use crate::config::{MAX_MESSAGE, Mode, ZenohConfig};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use zenoh::Wait;
use zenoh::handlers::{FifoChannel, RingChannel, RingChannelHandler};
use zenoh::pubsub::Subscriber;
use zenoh::query::{Query, Queryable};

/// How many requests of each kind may wait for a serving thread; beyond, the oldest is
/// dropped (its asker times out).
pub const QUEUE: usize = 64;

/// An open session and what the node declared on it.
#[derive(Clone)]
pub struct Session {
    /// The Zenoh session.
    pub inner: zenoh::Session,
    declared: Arc<Mutex<Vec<Declared>>>,
}

enum Declared {
    Subscriber(#[allow(dead_code, reason = "held: dropping it undeclares")] Subscriber<()>),
    Queryable(#[allow(dead_code, reason = "held: dropping it undeclares")] Queryable<()>),
}

/// Requests of one kind, waiting to be served.
pub struct Queue(Queryable<RingChannelHandler<Query>>);

impl Queue {
    /// The next request and its payload, waiting at most `timeout`.
    pub fn next(&self, timeout: Duration) -> Option<(Query, Vec<u8>)> {
        let q = self.0.recv_timeout(timeout).ok().flatten()?;
        let bytes = q
            .payload()
            .map(|p| p.to_bytes().into_owned())
            .unwrap_or_default();
        Some((q, bytes))
    }
}

/// Answers `query` with `reply` (bytes) or an error text.
pub fn answer(query: &Query, reply: Result<Vec<u8>, String>) {
    let sent = match reply {
        Ok(bytes) => query.reply(query.key_expr().clone(), bytes).wait(),
        Err(e) => query.reply_err(e.into_bytes()).wait(),
    };
    if let Err(e) = sent {
        tracing::debug!("zenoh: answering {}: {e}", query.key_expr());
    }
}

fn ms(d: Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX)
}

/// The Zenoh configuration of `cfg`, as JSON5 insertions.
fn settings(cfg: &ZenohConfig) -> Vec<(&'static str, String)> {
    let json = |v: &dyn erased::Ser| v.json();
    let t = cfg.times();
    let mut s = vec![
        (
            "mode",
            json(&match cfg.mode {
                Mode::Peer => "peer",
                Mode::Client => "client",
            }),
        ),
        ("listen/endpoints", json(&cfg.listen)),
        ("listen/timeout_ms", "0".into()),
        ("listen/exit_on_failure", "true".into()),
        ("connect/endpoints", json(&cfg.connect)),
        // -1 with exit_on_failure false: tried in the background until it comes (0
        // would try once and never again; exit_on_failure true would block the open).
        ("connect/timeout_ms", "-1".into()),
        ("connect/exit_on_failure", "false".into()),
        (
            "connect/retry",
            r#"{"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}"#.into(),
        ),
        ("scouting/multicast/enabled", "false".into()),
        ("scouting/gossip/enabled", json(&cfg.gossip)),
        ("transport/link/tx/lease", ms(t.lease).to_string()),
        ("transport/link/tx/keep_alive", "4".into()),
        (
            "transport/link/rx/max_message_size",
            MAX_MESSAGE.to_string(),
        ),
        ("adminspace/enabled", "false".into()),
        // Samples are published express (see `Publishers::put`), each in a batch of its
        // own: a period's burst, one sample a device, must find a batch free, or Zenoh
        // drops it when the link's thread has not sent the last burst within 1 ms (8
        // samples of 10 000 lost in one bench run at Zenoh's default of 2). Batches
        // are allocated as used, up to this (Zenoh's most).
        ("transport/link/tx/queue/size/data", "16".into()),
    ];
    if let Some(tls) = &cfg.tls {
        let path = |p: &std::path::Path| json(&p.display().to_string());
        s.push(("transport/link/tls/root_ca_certificate", path(&tls.root_ca)));
        if let (Some(c), Some(k)) = (&tls.cert, &tls.key) {
            s.push(("transport/link/tls/listen_certificate", path(c)));
            s.push(("transport/link/tls/listen_private_key", path(k)));
            if tls.mtls {
                s.push(("transport/link/tls/connect_certificate", path(c)));
                s.push(("transport/link/tls/connect_private_key", path(k)));
            }
        }
        s.push(("transport/link/tls/enable_mtls", json(&tls.mtls)));
    }
    s
}

/// JSON of a few plain types, without a generic parameter in [`settings`]' table.
mod erased {
    pub trait Ser {
        fn json(&self) -> String;
    }
    impl<T: serde::Serialize + ?Sized> Ser for T {
        fn json(&self) -> String {
            serde_json::to_string(self).unwrap_or_default()
        }
    }
}

/// Why a session could not be opened.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SessionError {
    /// Zenoh refused a setting made from the section.
    #[error("zenoh setting {key} = {value}: {why}")]
    Setting {
        /// Zenoh's key.
        key: &'static str,
        /// The value given.
        value: String,
        /// Zenoh's error.
        why: String,
    },
    /// Zenoh could not open the session.
    #[error("cannot open the session (listen {listen:?}, connect {connect:?}): {why}")]
    Open {
        /// The endpoints to listen on.
        listen: Vec<String>,
        /// The endpoints to connect to.
        connect: Vec<String>,
        /// Zenoh's error.
        why: String,
    },
}

/// Opens the session of `cfg`.
pub fn open(cfg: &ZenohConfig) -> Result<Session, SessionError> {
    let mut z = zenoh::Config::default();
    for (key, value) in settings(cfg) {
        z.insert_json5(key, &value)
            .map_err(|e| SessionError::Setting {
                key,
                value: value.clone(),
                why: crate::config::error_text(&e.to_string()).to_string(),
            })?;
    }
    let inner = zenoh::open(z).wait().map_err(|e| SessionError::Open {
        listen: cfg.listen.clone(),
        connect: cfg.connect.clone(),
        why: crate::config::error_text(&e.to_string()).to_string(),
    })?;
    Ok(Session {
        inner,
        declared: Arc::default(),
    })
}

impl Session {
    /// Answers `key`'s queries with `f()`'s catalogue, on Zenoh's own threads (it only
    /// reads the registry).
    pub fn declare_catalogue<C: serde::Serialize>(
        &self,
        gw: &str,
        f: impl Fn() -> C + Send + Sync + 'static,
    ) -> zenoh::Result<()> {
        let q = self
            .inner
            .declare_queryable(crate::wire::service_key(gw, "catalogue"))
            .callback(move |q: Query| answer(&q, Ok(crate::wire::to_bytes(&f()))))
            .wait()?;
        self.hold(Declared::Queryable(q));
        Ok(())
    }

    /// Requests on `key`, for a thread to serve.
    pub fn queue(&self, key: &str) -> zenoh::Result<Queue> {
        Ok(Queue(
            self.inner
                .declare_queryable(key.to_string())
                .with(RingChannel::new(QUEUE))
                .wait()?,
        ))
    }

    /// Calls `f(key, payload)` for every sample matching `key_expr`, on Zenoh's threads.
    pub fn subscribe(
        &self,
        key_expr: &str,
        f: impl Fn(&str, &[u8]) + Send + Sync + 'static,
    ) -> zenoh::Result<()> {
        let s = self
            .inner
            .declare_subscriber(key_expr.to_string())
            .callback(move |sample: zenoh::sample::Sample| {
                f(sample.key_expr().as_str(), &sample.payload().to_bytes())
            })
            .wait()?;
        self.hold(Declared::Subscriber(s));
        Ok(())
    }

    fn hold(&self, d: Declared) {
        self.declared
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .push(d);
    }

    /// Drops every subscriber and queryable declared through [`Self::subscribe`] and
    /// [`Self::declare_catalogue`].
    pub fn undeclare_all(&self) {
        self.declared
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clear();
    }

    /// Publishers of the keys published so far: a declared publisher's key is resolved
    /// once, not at every sample.
    pub fn publishers(&self) -> Publishers {
        Publishers {
            session: self.inner.clone(),
            by_key: std::collections::HashMap::new(),
        }
    }

    /// Asks `key` and waits (at most `timeout`) for at most `max` answers, together at
    /// most four messages' worth of bytes; an error answer comes as a control error body.
    pub fn ask(
        &self,
        key: &str,
        payload: Vec<u8>,
        timeout: Duration,
        max: usize,
    ) -> zenoh::Result<Vec<Vec<u8>>> {
        // Every queryable's answer, none merged: two gateways answering on one key (the
        // same name twice) are both heard.
        let mut get = self
            .inner
            .get(key.to_string())
            .target(zenoh::query::QueryTarget::All)
            .consolidation(zenoh::query::ConsolidationMode::None)
            .timeout(timeout)
            .with(FifoChannel::new(QUEUE));
        if !payload.is_empty() {
            get = get.payload(payload);
        }
        let replies = get.wait()?;
        let mut out: Vec<Vec<u8>> = Vec::new();
        let mut bytes = 0;
        while out.len() < max && bytes < 4 * MAX_MESSAGE {
            let Ok(r) = replies.recv() else { break };
            match r.result() {
                Ok(s) => out.push(s.payload().to_bytes().into_owned()),
                Err(e) => out.push(
                    serde_json::to_vec(&serde_json::json!({
                        "error": {"kind": "failed", "message": String::from_utf8_lossy(&e.payload().to_bytes())}
                    }))
                    .unwrap_or_default(),
                ),
            }
            bytes += out.last().map_or(0, Vec::len);
        }
        Ok(out)
    }

    /// Asks `key` without waiting: `then(answer)` runs on Zenoh's threads for each answer
    /// (an error answer as `Err` with its text).
    pub fn ask_then(
        &self,
        key: &str,
        payload: Vec<u8>,
        timeout: Duration,
        then: impl Fn(Result<&[u8], String>) + Send + Sync + 'static,
    ) -> zenoh::Result<()> {
        self.inner
            .get(key.to_string())
            .payload(payload)
            .timeout(timeout)
            .callback(move |r: zenoh::query::Reply| match r.result() {
                Ok(s) => then(Ok(&s.payload().to_bytes())),
                Err(e) => then(Err(
                    String::from_utf8_lossy(&e.payload().to_bytes()).into_owned()
                )),
            })
            .wait()
    }

    /// This session's Zenoh id.
    pub fn zid(&self) -> String {
        self.inner.zid().to_string()
    }

    /// The peers and routers connected now.
    pub fn peers(&self) -> Vec<String> {
        let info = self.inner.info();
        let mut v: Vec<String> = info.peers_zid().wait().map(|z| z.to_string()).collect();
        v.extend(info.routers_zid().wait().map(|z| z.to_string()));
        v
    }
}

/// Declared publishers by key (see [`Session::publishers`]).
pub struct Publishers {
    session: zenoh::Session,
    by_key: std::collections::HashMap<String, zenoh::pubsub::Publisher<'static>>,
}

impl Publishers {
    /// Publishes `payload` on `key`, express: sent at once, never batched with others
    /// (Zenoh may hold a message back up to 1 ms for a batch when the link pushes back).
    /// Measured with the remote read bench: p99 2.2 ms batched, 0.4–1.0 ms express, for
    /// about half a point more CPU in the receiver (`docs/benchmarks.md`).
    pub fn put(&mut self, key: &str, payload: Vec<u8>) -> zenoh::Result<()> {
        if !self.by_key.contains_key(key) {
            let p = self
                .session
                .declare_publisher(key.to_string())
                .express(true)
                .wait()?;
            self.by_key.insert(key.to_string(), p);
        }
        match self.by_key.get(key) {
            Some(p) => p.put(payload).wait(),
            None => Ok(()),
        }
    }
}
