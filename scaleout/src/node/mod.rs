//! The node: this gateway's Zenoh session, what it serves and what it imports.
//!
//! Built with the deployment (the imported devices registered, nothing opened), started
//! with the gateway's servers, stopped first at stop — so no remote write races the safe
//! values. Started, it runs these threads, none of them real-time:
//!
//! - `hwgw-zn-pub`: every `publish_ms`, one [`Sample`](crate::wire::Sample) per local
//!   device;
//! - `hwgw-zn-tx`: the writes of this gateway's components to others' outputs, each sent
//!   once, as soon as it is made (the remote output watchdog sees what the writer does);
//! - `hwgw-zn-wr` and `hwgw-zn-ctl`: the writes and control requests of other gateways,
//!   from bounded queues (a flood loses the oldest, never grows memory);
//! - `hwgw-zn-imp`: asks each imported gateway for its catalogue until it answers.

use crate::config::{Times, ZenohConfig};
use crate::local;
use crate::ports::{Export, Link, PortBatch};
use crate::remote::{Image, Proxy};
use crate::session::{self, Session};
use crate::wire::{self, Catalogue};
use device_interface::{Interface, Registry};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use zenoh::Wait;

mod report;
mod threads;

pub use report::{ImportReport, LinkReport, NodeCounts, NodeReport, StatusSummary};

/// Most gateways `ls --all` lists (each answers with its catalogue).
pub const MAX_GATEWAYS: usize = 256;

/// Answers a control request of another gateway: the request (JSON, as on the control
/// socket, without `id`) to the reply body.
pub type ControlHandler = Arc<dyn Fn(serde_json::Value) -> serde_json::Value + Send + Sync>;

/// Why something of the node failed.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    /// The node is not started.
    #[error("zenoh is not started")]
    NotStarted,
    /// Zenoh refused or failed.
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// No gateway answered in time.
    #[error("gateway {gateway:?} did not answer within {ms} ms (is it up, and connected?)")]
    NoAnswer {
        /// The gateway asked.
        gateway: String,
        /// How long we waited.
        ms: u128,
    },
    /// The answer was not what the protocol says.
    #[error("gateway {gateway:?} answered something unreadable: {message}")]
    BadAnswer {
        /// The gateway.
        gateway: String,
        /// What was wrong.
        message: String,
    },
    /// An imported device could not be registered under its local name.
    #[error("{name}: {source}")]
    Import {
        /// Its local name, `<gateway>/<device>`.
        name: String,
        /// Why the registry refused it.
        #[source]
        source: device_interface::RegistryError,
    },
}

/// Counters of the node, for `hwgw status`.
#[derive(Debug, Default)]
struct Counters {
    published: AtomicU64,
    publish_failed: AtomicU64,
    writes_served: AtomicU64,
    writes_refused: AtomicU64,
    writes_repeated: AtomicU64,
    controls_served: AtomicU64,
    bad_messages: AtomicU64,
}

/// What runs while the node is started.
struct Running {
    session: Session,
    threads: Vec<JoinHandle<()>>,
    address: String,
}

/// This gateway on Zenoh.
pub struct Node {
    cfg: ZenohConfig,
    times: Times,
    registry: Arc<Registry>,
    images: Vec<Arc<Image>>,
    control: Arc<Mutex<Option<ControlHandler>>>,
    counters: Arc<Counters>,
    stop: Arc<AtomicBool>,
    running: Mutex<Option<Running>>,
    exports: Mutex<Vec<Arc<Export>>>,
    links: Mutex<Vec<Arc<Link>>>,
    /// This run's number (see [`Catalogue::run`]).
    run: u64,
    /// Set when another gateway answers to this one's name: what it is.
    twin: Arc<Mutex<Option<String>>>,
}

impl Node {
    /// The node of `cfg` (checked with [`ZenohConfig::check`]): every imported device is
    /// registered in `registry` as `<gateway>/<device>` (owner `zenoh:<gateway>`), offline
    /// until its gateway is heard. Nothing is opened.
    pub fn new(cfg: ZenohConfig, registry: Arc<Registry>) -> Result<Node, NodeError> {
        let times = cfg.times();
        let mut images = Vec::new();
        for im in &cfg.import {
            let (name, owner) = (im.local_name(), local::owner_of(&im.gateway));
            let mut image = |i: Interface, n: u32| {
                let img = Arc::new(Image::new(i, &im.gateway, &im.device, n, times));
                images.push(img.clone());
                Arc::new(Proxy(img))
            };
            let r = &registry;
            let done = [
                im.analog_in.map(|n| {
                    r.analog_in()
                        .register(&name, &owner, image(Interface::AnalogIn, n))
                }),
                im.analog_out.map(|n| {
                    r.analog_out()
                        .register(&name, &owner, image(Interface::AnalogOut, n))
                }),
                im.digital_in.map(|n| {
                    r.digital_in()
                        .register(&name, &owner, image(Interface::DigitalIn, n))
                }),
                im.digital_out.map(|n| {
                    r.digital_out()
                        .register(&name, &owner, image(Interface::DigitalOut, n))
                }),
                im.encoder.then(|| {
                    r.encoder()
                        .register(&name, &owner, image(Interface::Encoder, 2))
                }),
            ];
            for e in done.into_iter().flatten() {
                e.map_err(|source| NodeError::Import {
                    name: name.clone(),
                    source,
                })?;
            }
        }
        Ok(Node {
            cfg,
            times,
            registry,
            images,
            control: Arc::default(),
            counters: Arc::default(),
            stop: Arc::new(AtomicBool::new(false)),
            running: Mutex::new(None),
            exports: Mutex::default(),
            links: Mutex::default(),
            run: threads::run_number(),
            twin: Arc::default(),
        })
    }

    /// This gateway's name.
    pub fn name(&self) -> &str {
        &self.cfg.name
    }

    /// The gateways this one imports devices from.
    pub fn imported_gateways(&self) -> Vec<String> {
        let mut v: Vec<String> = self.cfg.import.iter().map(|i| i.gateway.clone()).collect();
        v.sort();
        v.dedup();
        v
    }

    /// The registry owners of imported devices, one per gateway imported from.
    pub fn import_owners(&self) -> Vec<String> {
        self.imported_gateways()
            .iter()
            .map(|g| local::owner_of(g))
            .collect()
    }

    /// Publishes an exported port from the next start on.
    pub fn export(&self, e: Export) {
        lock(&self.exports).push(Arc::new(e));
    }

    /// Feeds a local input port from another gateway's port from the next start on.
    pub fn link(&self, l: Link) {
        lock(&self.links).push(Arc::new(l));
    }

    /// Sets what answers other gateways' control requests (none: they are refused).
    pub fn set_control(&self, handler: ControlHandler) {
        *self.control.lock().unwrap_or_else(|p| p.into_inner()) = Some(handler);
    }

    /// The imported interfaces' images (for benchmarks and tests: when each sample came).
    pub fn images(&self) -> &[Arc<Image>] {
        &self.images
    }

    /// Opens the session and starts serving and importing; returns where it listens (or
    /// what it connects to). A peer not up yet is not waited for: it is connected to when
    /// it comes, and the catalogue thread reports it until then.
    pub fn start(&self) -> Result<String, NodeError> {
        let mut running = self.running.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(r) = running.as_ref() {
            return Ok(r.address.clone());
        }
        self.stop.store(false, Ordering::Release);
        let session = session::open(&self.cfg).map_err(|e| NodeError::Zenoh(e.to_string()))?;
        let threads = match self.spawn(&session) {
            Ok(t) => t,
            Err(e) => {
                self.stop.store(true, Ordering::Release);
                let _ = session.inner.close().wait();
                return Err(e);
            }
        };
        let address = if self.cfg.listen.is_empty() {
            format!("nowhere (connects to {})", self.cfg.connect.join(", "))
        } else {
            self.cfg.listen.join(", ")
        };
        *running = Some(Running {
            session,
            threads,
            address: address.clone(),
        });
        Ok(address)
    }

    fn spawn(&self, s: &Session) -> Result<Vec<JoinHandle<()>>, NodeError> {
        let mut threads = Vec::new();
        self.serve(s, &mut threads)?;
        if !self.images.is_empty() {
            self.import(s, &mut threads)?;
        }
        Ok(threads)
    }

    /// What others ask of this gateway, and what it publishes.
    fn serve(&self, s: &Session, threads: &mut Vec<JoinHandle<()>>) -> Result<(), NodeError> {
        let (gw, reg, run) = (self.cfg.name.clone(), self.registry.clone(), self.run);
        s.declare_catalogue(&self.cfg.name, move || local::catalogue(&gw, run, &reg))
            .map_err(zerr)?;
        let (sess, gw, twin, stop, times) = (
            s.clone(),
            self.cfg.name.clone(),
            self.twin.clone(),
            self.stop.clone(),
            self.times,
        );
        threads.push(spawn("hwgw-zn-name", move || {
            threads::watch_name(&sess, &gw, run, &twin, times, &stop)
        })?);
        let writes = s
            .queue(&wire::service_key(&self.cfg.name, "write"))
            .map_err(zerr)?;
        let (gw, reg, c, stop) = (
            self.cfg.name.clone(),
            self.registry.clone(),
            self.counters.clone(),
            self.stop.clone(),
        );
        threads.push(spawn("hwgw-zn-wr", move || {
            threads::serve_writes(&gw, &reg, &writes, &c, &stop)
        })?);
        let control = s
            .queue(&wire::service_key(&self.cfg.name, "control"))
            .map_err(zerr)?;
        let (h, c, stop) = (
            self.control.clone(),
            self.counters.clone(),
            self.stop.clone(),
        );
        threads.push(spawn("hwgw-zn-ctl", move || {
            threads::serve_control(&h, &control, &c, &stop)
        })?);
        let (sess, reg, c, stop, period) = (
            s.clone(),
            self.registry.clone(),
            self.counters.clone(),
            self.stop.clone(),
            self.times.publish,
        );
        let gw = self.cfg.name.clone();
        let exports = lock(&self.exports).clone();
        threads.push(spawn("hwgw-zn-pub", move || {
            threads::publish(&gw, &sess, &reg, &exports, period, &c, &stop)
        })?);
        Ok(())
    }

    /// What this gateway uses of others: their devices' samples, their ports, and its
    /// writes to them.
    fn import(&self, s: &Session, threads: &mut Vec<JoinHandle<()>>) -> Result<(), NodeError> {
        for link in lock(&self.links).iter() {
            let (l, c) = (link.clone(), self.counters.clone());
            s.subscribe(link.key(), move |key, bytes| {
                match wire::parse::<PortBatch>(bytes) {
                    Ok(b) => l.take(b),
                    Err(e) => {
                        if c.bad_messages.fetch_add(1, Ordering::Relaxed) == 0 {
                            tracing::warn!("zenoh: a batch on {key} does not parse: {e}");
                        }
                    }
                }
            })
            .map_err(zerr)?;
        }
        let by_key: HashMap<String, Vec<Arc<Image>>> =
            self.images.iter().fold(HashMap::new(), |mut m, img| {
                let key = wire::sample_key(img.gateway(), img.interface(), img.device());
                m.entry(key).or_default().push(img.clone());
                m
            });
        let gateways = self.imported_gateways();
        for gw in &gateways {
            let (by_key, c) = (by_key.clone(), self.counters.clone());
            s.subscribe(&format!("hwgw/{gw}/dev/**"), move |key, bytes| {
                threads::take_sample(&by_key, key, bytes, &c)
            })
            .map_err(zerr)?;
        }
        let (tx, rx) = crossbeam_channel::bounded(1);
        for img in &self.images {
            img.set_wake(tx.clone());
        }
        let (sess, images, stop, me, times) = (
            s.clone(),
            self.images.clone(),
            self.stop.clone(),
            self.cfg.name.clone(),
            self.times,
        );
        let run = self.run;
        threads.push(spawn("hwgw-zn-tx", move || {
            threads::send_writes(&me, run, &sess, &images, &rx, times, &stop)
        })?);
        let (sess, images, stop, times) = (
            s.clone(),
            self.images.clone(),
            self.stop.clone(),
            self.times,
        );
        threads.push(spawn("hwgw-zn-imp", move || {
            threads::import(&sess, &gateways, &images, times, &stop)
        })?);
        Ok(())
    }

    /// Stops serving and publishing, and closes the session; waits for the threads.
    /// Idempotent.
    pub fn stop(&self) {
        for img in &self.images {
            img.hold();
        }
        let Some(r) = self
            .running
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take()
        else {
            return;
        };
        self.stop.store(true, Ordering::Release);
        r.session.undeclare_all();
        for t in r.threads {
            let _ = t.join();
        }
        if let Err(e) = r.session.inner.close().wait() {
            tracing::warn!("zenoh: closing the session: {e}");
        }
    }

    /// Where it listens while running.
    pub fn address(&self) -> Option<String> {
        self.running
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .map(|r| r.address.clone())
    }

    fn session(&self) -> Result<Session, NodeError> {
        self.running
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .map(|r| r.session.clone())
            .ok_or(NodeError::NotStarted)
    }

    /// Sends control request `request` (JSON, without `id`) to gateway `gateway` and
    /// returns its reply body.
    pub fn request(
        &self,
        gateway: &str,
        request: &serde_json::Value,
    ) -> Result<wire::ControlReply, NodeError> {
        let s = self.session()?;
        let key = wire::service_key(gateway, "control");
        let replies = s
            .ask(&key, wire::to_bytes(request), self.times.request, 1)
            .map_err(|e| NodeError::Zenoh(e.to_string()))?;
        let Some(bytes) = replies.into_iter().next() else {
            return Err(NodeError::NoAnswer {
                gateway: gateway.to_string(),
                ms: self.times.request.as_millis(),
            });
        };
        wire::parse(&bytes).map_err(|e| NodeError::BadAnswer {
            gateway: gateway.to_string(),
            message: e.to_string(),
        })
    }

    /// Every gateway of the name space that answers within the request timeout, with
    /// its catalogue (this one included).
    pub fn gateways(&self) -> Result<Vec<Catalogue>, NodeError> {
        let s = self.session()?;
        let replies = s
            .ask(
                "hwgw/*/@/catalogue",
                Vec::new(),
                self.times.request,
                MAX_GATEWAYS,
            )
            .map_err(|e| NodeError::Zenoh(e.to_string()))?;
        let mut out: Vec<Catalogue> = replies
            .iter()
            .filter_map(|b| wire::parse::<Catalogue>(b).ok())
            .collect();
        out.sort_by(|a, b| a.gateway.cmp(&b.gateway));
        out.dedup_by(|a, b| a.gateway == b.gateway);
        Ok(out)
    }

    /// State and counters.
    pub fn report(&self) -> NodeReport {
        let c = &self.counters;
        let l = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let (zid, peers) = match self.session() {
            Ok(s) => (Some(s.zid()), s.peers()),
            Err(_) => (None, Vec::new()),
        };
        NodeReport {
            twin: lock(&self.twin).clone(),
            name: self.cfg.name.clone(),
            zid,
            peers,
            counts: NodeCounts {
                published: l(&c.published),
                publish_failed: l(&c.publish_failed),
                writes_served: l(&c.writes_served),
                writes_refused: l(&c.writes_refused),
                writes_repeated: l(&c.writes_repeated),
                controls_served: l(&c.controls_served),
                bad_messages: l(&c.bad_messages),
            },
            imports: self
                .images
                .iter()
                .map(|i| ImportReport {
                    name: format!("{}/{}", i.gateway(), i.device()),
                    interface: i.interface(),
                    received: l(&i.counters.received),
                    lost: l(&i.counters.lost),
                    refused: l(&i.counters.refused),
                    writes_sent: l(&i.counters.writes_sent),
                    writes_acked: l(&i.counters.writes_acked),
                    writes_refused: l(&i.counters.writes_refused),
                    writes_failed: l(&i.counters.writes_failed),
                    writes_retried: l(&i.counters.writes_retried),
                    writes_pending: i.pending().len() as u64,
                    problem: i.problem(),
                })
                .collect(),
            links: lock(&self.links)
                .iter()
                .map(|k| LinkReport {
                    connection: k.label.clone(),
                    received: l(&k.received),
                    lost_batches: l(&k.lost_batches),
                    remote_dropped: l(&k.remote_dropped),
                    refused: l(&k.refused),
                })
                .collect(),
        }
    }
}

fn zerr(e: zenoh::Error) -> NodeError {
    NodeError::Zenoh(crate::config::error_text(&e.to_string()).into())
}

/// Starts thread `name` running `f`.
fn spawn(name: &str, f: impl FnOnce() + Send + 'static) -> Result<JoinHandle<()>, NodeError> {
    std::thread::Builder::new()
        .name(name.into())
        .spawn(f)
        .map_err(|e| NodeError::Zenoh(format!("cannot start thread {name}: {e}")))
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Drop for Node {
    fn drop(&mut self) {
        self.stop();
    }
}
