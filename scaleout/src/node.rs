//! The node: this gateway's Zenoh session, what it serves and what it imports.
//!
//! Built with the deployment (the imported devices registered, nothing opened), started
//! with the gateway's servers, stopped first at stop — so no remote write races the safe
//! values. Started, it runs these threads, none of them real-time:
//!
//! - `hwgw-zn-pub`: every `publish_ms`, one [`Sample`](crate::wire::Sample) per local
//!   device;
//! - `hwgw-zn-tx`: the outputs this gateway drives on others, sent at once when written
//!   and again every `publish_ms` (so the remote output watchdog sees them alive);
//! - `hwgw-zn-wr` and `hwgw-zn-ctl`: the writes and control requests of other gateways,
//!   from bounded queues (a flood loses the oldest, never grows memory);
//! - `hwgw-zn-imp`: asks each imported gateway for its catalogue until it answers.

use crate::config::{Times, ZenohConfig};
use crate::local;
use crate::ports::{Export, Link, PortBatch};
use crate::remote::{Image, Proxy};
use crate::session::{self, Session};
use crate::wire::{self, Catalogue, Write, WriteReply};
use device_interface::time::{Clock, MonotonicClock};
use device_interface::{Interface, Registry};
use serde::Serialize;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use zenoh::Wait;

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
}

/// Counters of the node, for `hwgw status`.
#[derive(Debug, Default)]
struct Counters {
    published: AtomicU64,
    publish_failed: AtomicU64,
    writes_served: AtomicU64,
    writes_refused: AtomicU64,
    controls_served: AtomicU64,
    bad_messages: AtomicU64,
}

/// The node's state and counters, for `hwgw status`.
#[derive(Debug, Clone, Serialize)]
pub struct NodeReport {
    /// This gateway's name.
    pub name: String,
    /// Its Zenoh id, once started.
    pub zid: Option<String>,
    /// The peers (or routers) it is connected to now.
    pub peers: Vec<String>,
    /// Samples published.
    pub published: u64,
    /// Publications that failed.
    pub publish_failed: u64,
    /// Writes of other gateways carried out / refused.
    pub writes_served: u64,
    /// Writes of other gateways refused (some value).
    pub writes_refused: u64,
    /// Control requests of other gateways answered.
    pub controls_served: u64,
    /// Messages that did not parse.
    pub bad_messages: u64,
    /// Every imported interface.
    pub imports: Vec<ImportReport>,
    /// Every connection from another gateway's port.
    pub links: Vec<LinkReport>,
}

/// A connection from another gateway's port, for `hwgw status`.
#[derive(Debug, Clone, Serialize)]
pub struct LinkReport {
    /// `B/follow.out -> local.in`.
    pub connection: String,
    /// Samples written into the local port.
    pub received: u64,
    /// Batches lost on the way.
    pub lost_batches: u64,
    /// Samples the remote export dropped.
    pub remote_dropped: u64,
    /// Samples the local port refused.
    pub refused: u64,
}

/// One imported interface, for `hwgw status`.
#[derive(Debug, Clone, Serialize)]
pub struct ImportReport {
    /// Its name here (`B/sim0`).
    pub name: String,
    /// Its interface.
    pub interface: Interface,
    /// Samples received, lost on the way, refused.
    pub received: u64,
    /// Samples missing from the sequence.
    pub lost: u64,
    /// Samples refused.
    pub refused: u64,
    /// Writes sent, acknowledged, refused.
    pub writes_sent: u64,
    /// Writes acknowledged.
    pub writes_acked: u64,
    /// Writes refused.
    pub writes_refused: u64,
    /// Its last problem.
    pub problem: Option<String>,
}

/// The node's counters as `hwgw status` shows them: the imports summed, their problems
/// listed (each import's own counters are in [`NodeReport`]).
#[derive(Debug, Clone, Serialize)]
pub struct StatusSummary {
    /// Peers and routers connected now (their Zenoh ids).
    pub peers: Vec<String>,
    /// Samples published.
    pub published: u64,
    /// Publications that failed.
    pub publish_failed: u64,
    /// Writes of other gateways carried out.
    pub writes_served: u64,
    /// ... of which some value was refused.
    pub writes_refused: u64,
    /// Control requests of other gateways answered.
    pub controls_served: u64,
    /// Messages that did not parse.
    pub bad_messages: u64,
    /// Samples of imported devices taken.
    pub imported_received: u64,
    /// ... missing from their sequence.
    pub imported_lost: u64,
    /// ... refused (shape unknown or not matching).
    pub imported_refused: u64,
    /// Writes sent to other gateways.
    pub writes_sent: u64,
    /// ... that they acknowledged.
    pub writes_acked: u64,
    /// Each import's problem.
    pub problems: Vec<String>,
    /// Each connection from another gateway's port and its counters.
    pub links: Vec<String>,
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
    control: Mutex<Option<ControlHandler>>,
    counters: Arc<Counters>,
    stop: Arc<AtomicBool>,
    running: Mutex<Option<Running>>,
    exports: Mutex<Vec<Arc<Export>>>,
    links: Mutex<Vec<Arc<Link>>>,
}

impl Node {
    /// The node of `cfg` (checked with [`ZenohConfig::check`]): every imported device is
    /// registered in `registry` as `<gateway>/<device>` (owner `zenoh:<gateway>`), offline
    /// until its gateway is heard. Nothing is opened.
    pub fn new(cfg: ZenohConfig, registry: Arc<Registry>) -> Result<Node, String> {
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
                e.map_err(|e| format!("{name}: {e}"))?;
            }
        }
        Ok(Node {
            cfg,
            times,
            registry,
            images,
            control: Mutex::new(None),
            counters: Arc::default(),
            stop: Arc::new(AtomicBool::new(false)),
            running: Mutex::new(None),
            exports: Mutex::default(),
            links: Mutex::default(),
        })
    }

    /// This gateway's name.
    pub fn name(&self) -> &str {
        &self.cfg.name
    }

    /// The registry owners of imported devices, one per gateway imported from.
    pub fn import_owners(&self) -> Vec<String> {
        let mut v: Vec<String> = self
            .cfg
            .import
            .iter()
            .map(|i| local::owner_of(&i.gateway))
            .collect();
        v.sort();
        v.dedup();
        v
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
        let session = session::open(&self.cfg).map_err(NodeError::Zenoh)?;
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
        let z =
            |e: zenoh::Error| NodeError::Zenoh(crate::config::error_text(&e.to_string()).into());
        let mut threads = Vec::new();
        let spawn = |name: &str, f: Box<dyn FnOnce() + Send>| {
            std::thread::Builder::new()
                .name(name.into())
                .spawn(f)
                .map_err(|e| NodeError::Zenoh(format!("cannot start thread {name}: {e}")))
        };
        // What others ask of us.
        let (gw, reg) = (self.cfg.name.clone(), self.registry.clone());
        s.declare_catalogue(&self.cfg.name, move || local::catalogue(&gw, &reg))
            .map_err(z)?;
        let writes = s
            .queue(&wire::service_key(&self.cfg.name, "write"))
            .map_err(z)?;
        let (gw, reg, c, stop) = (
            self.cfg.name.clone(),
            self.registry.clone(),
            self.counters.clone(),
            self.stop.clone(),
        );
        threads.push(spawn(
            "hwgw-zn-wr",
            Box::new(move || serve_writes(&gw, &reg, &writes, &c, &stop)),
        )?);
        let control = s
            .queue(&wire::service_key(&self.cfg.name, "control"))
            .map_err(z)?;
        let handler = self
            .control
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone();
        let (c, stop) = (self.counters.clone(), self.stop.clone());
        threads.push(spawn(
            "hwgw-zn-ctl",
            Box::new(move || serve_control(handler, &control, &c, &stop)),
        )?);
        // What we publish.
        let (sess, reg, c, stop, period) = (
            s.clone(),
            self.registry.clone(),
            self.counters.clone(),
            self.stop.clone(),
            self.times.publish,
        );
        let gw = self.cfg.name.clone();
        let exports = lock(&self.exports).clone();
        threads.push(spawn(
            "hwgw-zn-pub",
            Box::new(move || publish(&gw, &sess, &reg, &exports, period, &c, &stop)),
        )?);
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
            .map_err(z)?;
        }
        // What we import.
        if !self.images.is_empty() {
            let by_key: HashMap<String, Vec<Arc<Image>>> =
                self.images.iter().fold(HashMap::new(), |mut m, img| {
                    let key = wire::sample_key(img.gateway(), img.interface(), img.device());
                    m.entry(key).or_default().push(img.clone());
                    m
                });
            let c = self.counters.clone();
            let mut gateways: Vec<String> = self
                .images
                .iter()
                .map(|i| i.gateway().to_string())
                .collect();
            gateways.sort();
            gateways.dedup();
            for gw in &gateways {
                let (by_key, c) = (by_key.clone(), c.clone());
                s.subscribe(&format!("hwgw/{gw}/dev/**"), move |key, bytes| {
                    take_sample(&by_key, key, bytes, &c)
                })
                .map_err(z)?;
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
            threads.push(spawn(
                "hwgw-zn-tx",
                Box::new(move || send_writes(&me, &sess, &images, &rx, times, &stop)),
            )?);
            let (sess, images, stop, times) = (
                s.clone(),
                self.images.clone(),
                self.stop.clone(),
                self.times,
            );
            threads.push(spawn(
                "hwgw-zn-imp",
                Box::new(move || import(&sess, &gateways, &images, times, &stop)),
            )?);
        }
        Ok(threads)
    }

    /// Stops serving and publishing, and closes the session; waits for the threads.
    /// Idempotent.
    pub fn stop(&self) {
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
            .ask(&key, wire::to_bytes(request), self.times.request)
            .map_err(|e| NodeError::Zenoh(e.to_string()))?;
        let Some(bytes) = replies.into_iter().next() else {
            return Err(NodeError::NoAnswer {
                gateway: gateway.to_string(),
                ms: self.times.request.as_millis(),
            });
        };
        wire::parse(&bytes).map_err(|message| NodeError::BadAnswer {
            gateway: gateway.to_string(),
            message,
        })
    }

    /// Every gateway of the name space that answers within the request timeout, with
    /// its catalogue (this one included).
    pub fn gateways(&self) -> Result<Vec<Catalogue>, NodeError> {
        let s = self.session()?;
        let replies = s
            .ask("hwgw/*/@/catalogue", Vec::new(), self.times.request)
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
            name: self.cfg.name.clone(),
            zid,
            peers,
            published: l(&c.published),
            publish_failed: l(&c.publish_failed),
            writes_served: l(&c.writes_served),
            writes_refused: l(&c.writes_refused),
            controls_served: l(&c.controls_served),
            bad_messages: l(&c.bad_messages),
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

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Drop for Node {
    fn drop(&mut self) {
        self.stop();
    }
}

fn take_sample(by_key: &HashMap<String, Vec<Arc<Image>>>, key: &str, bytes: &[u8], c: &Counters) {
    let Some(images) = by_key.get(key) else {
        return;
    };
    match wire::parse::<wire::Sample>(bytes) {
        Ok(s) => {
            let now = MonotonicClock.now().as_nanos();
            for img in images {
                img.take(&s, now);
            }
        }
        Err(e) => {
            if c.bad_messages.fetch_add(1, Ordering::Relaxed) == 0 {
                tracing::warn!("zenoh: a sample on {key} does not parse: {e}");
            }
        }
    }
}

fn publish(
    gw: &str,
    s: &Session,
    registry: &Registry,
    exports: &[Arc<Export>],
    period: Duration,
    c: &Counters,
    stop: &AtomicBool,
) {
    let mut seq: HashMap<(Interface, String), u64> = HashMap::new();
    let mut publishers = s.publishers();
    let mut next = Instant::now();
    while !stop.load(Ordering::Acquire) {
        for e in exports {
            if let Some(batch) = e.drain() {
                match publishers.put(e.key(), wire::to_bytes(&batch)) {
                    Ok(()) => c.published.fetch_add(1, Ordering::Relaxed),
                    Err(_) => c.publish_failed.fetch_add(1, Ordering::Relaxed),
                };
            }
        }
        for (i, name) in local::local_devices(registry) {
            let n = seq.entry((i, name.clone())).or_insert(0);
            *n += 1;
            let Some(sample) = local::sample(registry, i, &name, *n) else {
                continue;
            };
            let key = wire::sample_key(gw, i, &name);
            match publishers.put(&key, wire::to_bytes(&sample)) {
                Ok(()) => c.published.fetch_add(1, Ordering::Relaxed),
                Err(e) => {
                    if c.publish_failed.fetch_add(1, Ordering::Relaxed) == 0 {
                        tracing::warn!("zenoh: publishing {key}: {e}");
                    }
                    0
                }
            };
        }
        next += period;
        let now = Instant::now();
        if next <= now {
            // Behind (a slow host): skip the missed periods rather than burst.
            next = now + period;
        }
        std::thread::sleep(next - now);
    }
}

fn serve_writes(
    gw: &str,
    registry: &Registry,
    queue: &session::Queue,
    c: &Counters,
    stop: &AtomicBool,
) {
    while !stop.load(Ordering::Acquire) {
        let Some((query, bytes)) = queue.next(Duration::from_millis(50)) else {
            continue;
        };
        let answer = wire::parse::<Write>(&bytes).and_then(|w| local::write(gw, registry, &w));
        let reply = match answer {
            Ok(r) => {
                c.writes_served.fetch_add(1, Ordering::Relaxed);
                if !r.refused.is_empty() {
                    c.writes_refused.fetch_add(1, Ordering::Relaxed);
                }
                Ok(wire::to_bytes(&r))
            }
            Err(e) => {
                c.bad_messages.fetch_add(1, Ordering::Relaxed);
                Err(e)
            }
        };
        session::answer(&query, reply);
    }
}

fn serve_control(
    handler: Option<ControlHandler>,
    queue: &session::Queue,
    c: &Counters,
    stop: &AtomicBool,
) {
    while !stop.load(Ordering::Acquire) {
        let Some((query, bytes)) = queue.next(Duration::from_millis(50)) else {
            continue;
        };
        let reply = match (&handler, wire::parse::<serde_json::Value>(&bytes)) {
            (None, _) => Err("this gateway takes no control requests over zenoh".to_string()),
            (_, Err(e)) => {
                c.bad_messages.fetch_add(1, Ordering::Relaxed);
                Err(format!("not a control request: {e}"))
            }
            (Some(h), Ok(req)) => {
                c.controls_served.fetch_add(1, Ordering::Relaxed);
                Ok(wire::to_bytes(&h(req)))
            }
        };
        session::answer(&query, reply);
    }
}

fn send_writes(
    me: &str,
    s: &Session,
    images: &[Arc<Image>],
    wake: &crossbeam_channel::Receiver<()>,
    times: Times,
    stop: &AtomicBool,
) {
    let mut refresh = Instant::now() + times.publish;
    while !stop.load(Ordering::Acquire) {
        let _ = wake.recv_timeout(refresh.saturating_duration_since(Instant::now()));
        let force = Instant::now() >= refresh;
        if force {
            refresh = Instant::now() + times.publish;
        }
        for img in images {
            let Some(values) = img.to_send(force) else {
                continue;
            };
            let w = Write {
                protocol: wire::PROTOCOL,
                writer: me.to_string(),
                interface: img.interface(),
                device: img.device().to_string(),
                values,
            };
            img.counters.writes_sent.fetch_add(1, Ordering::Relaxed);
            let key = wire::service_key(img.gateway(), "write");
            let answered = img.clone();
            let sent =
                s.ask_then(
                    &key,
                    wire::to_bytes(&w),
                    times.request,
                    move |answer| match answer.and_then(wire::parse::<WriteReply>) {
                        Ok(r) => answered.answered(&r.refused),
                        Err(e) => answered.failed(&e),
                    },
                );
            if let Err(e) = sent {
                tracing::debug!("zenoh: write to {key}: {e}");
            }
        }
    }
}

fn import(
    s: &Session,
    gateways: &[String],
    images: &[Arc<Image>],
    times: Times,
    stop: &AtomicBool,
) {
    let mut missing: Vec<&String> = gateways.iter().collect();
    let started = Instant::now();
    let mut reported = false;
    while !missing.is_empty() && !stop.load(Ordering::Acquire) {
        missing.retain(|gw| {
            let key = wire::service_key(gw, "catalogue");
            let replies = s.ask(&key, Vec::new(), times.request).unwrap_or_default();
            let Some(cat) = replies
                .iter()
                .find_map(|b| wire::parse::<Catalogue>(b).ok())
            else {
                return true;
            };
            if cat.protocol != wire::PROTOCOL {
                tracing::error!(
                    "zenoh: gateway {gw} speaks protocol {}, this one {}: its devices stay offline",
                    cat.protocol,
                    wire::PROTOCOL
                );
                return false;
            }
            for img in images.iter().filter(|i| i.gateway() == gw.as_str()) {
                match cat
                    .devices
                    .iter()
                    .find(|d| d.interface == img.interface() && d.name == img.device())
                {
                    Some(shape) => img.adopt(shape),
                    None => {
                        let names: Vec<&str> = cat
                            .devices
                            .iter()
                            .filter(|d| d.interface == img.interface())
                            .map(|d| d.name.as_str())
                            .collect();
                        tracing::error!(
                            "zenoh: gateway {gw} has no {} device {:?} (it has: {}); {gw}/{} stays offline",
                            wire::interface_key(img.interface()),
                            img.device(),
                            if names.is_empty() { "none".into() } else { names.join(", ") },
                            img.device()
                        );
                    }
                }
            }
            tracing::info!("zenoh: imported the devices of gateway {gw}");
            false
        });
        if !missing.is_empty() && !reported && started.elapsed() >= times.offline {
            reported = true;
            tracing::warn!(
                "zenoh: no answer yet from gateway(s) {}: their devices stay offline until they are up",
                missing
                    .iter()
                    .map(|s| s.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
        let until = Instant::now() + Duration::from_millis(500);
        while Instant::now() < until && !stop.load(Ordering::Acquire) {
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}
