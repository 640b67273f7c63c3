//! Where a Foxglove server's samples come from and go to: one pump thread opens a
//! `record` stream through the gateway's control (the recorder's stamped buffer
//! connections: every sample written, with the time it was written) while a client is
//! connected, and hands each sample to every client subscribed to its channel, into that
//! client's bounded queue. A client whose queue is full loses the sample (counted for that
//! client): no client slows the pump, and the pump never slows a component.

use super::wire::{self, Channel};
use bytes::Bytes;
use driver_api::ControlLink;
use protocol::{RecordBatch, RecordStart};
use recording::Item;
use serde_json::{Value, json};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, RwLock};
use std::time::Duration;
use tokio::sync::mpsc;

/// What goes to a client's socket.
#[derive(Debug)]
pub enum Out {
    /// A JSON operation.
    Text(String),
    /// Message data frames, a batch's worth, and their bytes.
    Frames(Frames, usize),
}

/// A client's share of one batch: its frames, sent together.
pub type Frames = Vec<Bytes>;

/// A connected client, as the pump sees it.
pub struct Client {
    /// Its number, for `hwgw status`.
    pub id: u64,
    /// Its address.
    pub peer: String,
    /// Its queue to its socket (a batch of frames an entry).
    pub tx: mpsc::Sender<Out>,
    /// Its subscriptions: server channel → its subscription id.
    pub subscriptions: Mutex<HashMap<u32, u32>>,
    /// Messages queued for it.
    pub sent: AtomicU64,
    /// Messages it lost for a full queue.
    pub dropped: AtomicU64,
    /// Bytes in its queue now.
    pub queued_bytes: std::sync::atomic::AtomicUsize,
}

/// The most bytes a client's queue holds: a batch that would take it past this is lost.
pub const MAX_QUEUED_BYTES: usize = 16 << 20;

impl Client {
    /// A JSON operation for it; false when its queue is full or closed (it is too far
    /// behind to be told: it is to be closed).
    pub fn tell(&self, text: String) -> bool {
        self.tx.try_send(Out::Text(text)).is_ok()
    }
}

/// The channels of the stream, and how its items find them.
#[derive(Debug, Default)]
pub struct Channels {
    /// Every channel, ports first, then activities.
    pub list: Vec<Channel>,
    /// The channel of each port of the stream, by its number.
    ports: Vec<u32>,
    /// The channel of each activity, by its number.
    activities: Vec<u32>,
    /// UNIX time minus the stream's clock, ns.
    wall_minus_clock_ns: i128,
}

/// The clients, the channels and the pump's state.
#[derive(Default)]
pub struct Hub {
    /// The connected clients.
    pub clients: Mutex<Vec<Arc<Client>>>,
    /// Woken when a client comes or the server stops.
    wake: Condvar,
    /// The channels of the latest stream (none before one began).
    pub channels: RwLock<Arc<Channels>>,
    /// Set at stop.
    pub stopping: AtomicBool,
    /// Streams opened.
    pub streams: AtomicU64,
    /// Samples and steps the streams brought.
    pub items: AtomicU64,
    /// Samples the streams lost before they reached the server (their buffers were full):
    /// the ended streams' and the current one's.
    pub stream_lost: AtomicU64,
    /// The ended streams' part of `stream_lost`.
    lost_before: AtomicU64,
    /// What the clients that left had lost.
    pub dropped_left: AtomicU64,
    /// The last reason a stream could not begin.
    pub last_error: Mutex<Option<String>>,
    next_channel: AtomicU64,
}

/// What the pump asks for: the `record` request's fields.
#[derive(Debug, Clone)]
pub struct Ask {
    /// `component.port` or `component`, each.
    pub ports: Vec<String>,
    /// Every device's IO component's ports too.
    pub devices: bool,
    /// The activities' steps too.
    pub steps: bool,
    /// Samples held per port between batches.
    pub buffer: usize,
}

impl Hub {
    /// The channels of the latest stream.
    pub fn channels(&self) -> Arc<Channels> {
        self.channels
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Adds `client`, waking the pump; the channels of the moment (under the same lock
    /// a new stream's channels are told to the clients under, so none is missed).
    pub fn join(&self, client: Arc<Client>) -> Arc<Channels> {
        let mut clients = rtt::lock(&self.clients);
        clients.push(client);
        self.wake.notify_all();
        self.channels()
    }

    /// Removes client `id`, keeping the count of what it lost.
    pub fn leave(&self, id: u64) {
        rtt::lock(&self.clients).retain(|c| {
            if c.id == id {
                let lost = c.dropped.load(Ordering::Relaxed);
                self.dropped_left.fetch_add(lost, Ordering::Relaxed);
            }
            c.id != id
        });
    }

    /// Stops the pump (its stream ends at its next batch) and lets every client go.
    pub fn stop(&self) {
        let mut clients = rtt::lock(&self.clients);
        self.stopping.store(true, Ordering::Release);
        clients.clear();
        self.wake.notify_all();
    }

    fn idle(&self) -> bool {
        self.stopping.load(Ordering::Acquire) || rtt::lock(&self.clients).is_empty()
    }

    /// The pump: until stopped, a stream while any client is connected.
    pub fn pump(&self, control: &ControlLink, ask: &Ask) {
        let request = json!({
            "cmd": "record", "ports": ask.ports, "devices": ask.devices,
            "steps": ask.steps, "buffer": ask.buffer,
        });
        while !self.stopping.load(Ordering::Acquire) {
            {
                let clients = rtt::lock(&self.clients);
                if clients.is_empty() {
                    let _ = self.wake.wait_timeout(clients, Duration::from_millis(500));
                    continue;
                }
            }
            self.streams.fetch_add(1, Ordering::Relaxed);
            let result = control.stream(request.clone(), &mut |line| self.line(line));
            let lost = self.stream_lost.load(Ordering::Relaxed);
            self.lost_before.store(lost, Ordering::Relaxed);
            if let Err(e) = result {
                *rtt::lock(&self.last_error) = Some(e.to_string());
            }
            // Not serving yet, every record stream taken, the gateway stopping, or nobody
            // left: again in a while, or when a client comes.
            let clients = rtt::lock(&self.clients);
            if !self.stopping.load(Ordering::Acquire) {
                let _ = self.wake.wait_timeout(clients, Duration::from_millis(500));
            }
        }
    }

    /// One line of the stream: its start (the channels) or a batch. False ends it.
    fn line(&self, line: Value) -> bool {
        if self.idle() {
            return false;
        }
        match line.get("records") {
            Some(batch) => match serde_json::from_value::<RecordBatch>(batch.clone()) {
                Ok(b) => self.deliver(b),
                Err(e) => tracing::warn!("foxglove: a record batch that does not parse: {e}"),
            },
            None => match serde_json::from_value::<RecordStart>(line) {
                Ok(start) => self.began(&start),
                Err(e) => {
                    tracing::warn!("foxglove: a record stream's start that does not parse: {e}");
                    return false;
                }
            },
        }
        true
    }

    /// A stream began: its channels, advertised to every client when they changed.
    fn began(&self, start: &RecordStart) {
        *rtt::lock(&self.last_error) = None;
        let old = self.channels();
        let topics = |c: &Channels| c.list.iter().map(|c| c.topic.clone()).collect::<Vec<_>>();
        let mut new = Channels {
            wall_minus_clock_ns: start.wall_minus_clock_ns,
            ..Channels::default()
        };
        let id = |topic: &str| {
            old.list
                .iter()
                .find(|c| c.topic == topic)
                .map(|c| c.id)
                .unwrap_or_else(|| self.next_channel.fetch_add(1, Ordering::Relaxed) as u32 + 1)
        };
        for p in &start.ports {
            let topic = p.topic();
            let schema = recording::item::sample_schema(&p.type_name).to_string();
            let channel = Channel {
                id: id(&topic),
                topic: topic.clone(),
                schema_name: recording::item::sample_schema_name(&p.type_name),
                schema,
            };
            new.ports.push(channel.id);
            new.list.push(channel);
        }
        let step_schema = recording::item::step_schema().to_string();
        for a in &start.activities {
            let topic = recording::item::activity_topic(a);
            let channel = Channel {
                id: id(&topic),
                topic,
                schema_name: recording::item::STEP_SCHEMA.into(),
                schema: step_schema.clone(),
            };
            new.activities.push(channel.id);
            new.list.push(channel);
        }
        let changed = topics(&old) != topics(&new);
        let gone: Vec<u32> = old
            .list
            .iter()
            .filter(|c| !new.list.iter().any(|n| n.id == c.id))
            .map(|c| c.id)
            .collect();
        let advertise = wire::advertise(&new.list);
        let clients = rtt::lock(&self.clients);
        *self.channels.write().unwrap_or_else(|p| p.into_inner()) = Arc::new(new);
        if changed {
            for c in clients.iter() {
                if !gone.is_empty() {
                    c.tell(wire::unadvertise(&gone));
                }
                c.tell(advertise.clone());
            }
        }
    }

    /// A batch's items to the clients subscribed to their channels: each client's share
    /// as one entry of its queue, or lost whole (counted) when its queue is full.
    fn deliver(&self, batch: RecordBatch) {
        let channels = self.channels();
        let lost: u64 = batch.ports_lost.iter().sum();
        let before = self.lost_before.load(Ordering::Relaxed);
        self.stream_lost.store(before + lost, Ordering::Relaxed);
        let clients = rtt::lock(&self.clients).clone();
        let subscriptions: Vec<HashMap<u32, u32>> = clients
            .iter()
            .map(|c| rtt::lock(&c.subscriptions).clone())
            .collect();
        let mut shares: Vec<Frames> = vec![Vec::new(); clients.len()];
        for item in &batch.items {
            self.items.fetch_add(1, Ordering::Relaxed);
            let (channel, payload) = match item {
                Item::Sample { port, value, .. } => (
                    channels.ports.get(*port as usize),
                    serde_json::to_vec(&recording::item::SampleMessage { value }),
                ),
                Item::Step { activity, step } => (
                    channels.activities.get(*activity as usize),
                    serde_json::to_vec(&recording::item::StepMessage::from(step)),
                ),
            };
            let (Some(&channel), Ok(payload)) = (channel, payload) else {
                continue;
            };
            let wall = i128::from(item.time_ns()) + channels.wall_minus_clock_ns;
            let time = u64::try_from(wall).unwrap_or(0);
            for (share, subs) in shares.iter_mut().zip(&subscriptions) {
                if let Some(&sub) = subs.get(&channel) {
                    share.push(Bytes::from(wire::message_data(sub, time, &payload)));
                }
            }
        }
        for (c, share) in clients.iter().zip(shares) {
            if share.is_empty() {
                continue;
            }
            let n = share.len() as u64;
            let bytes: usize = share.iter().map(Bytes::len).sum();
            let queued = c.queued_bytes.fetch_add(bytes, Ordering::Relaxed);
            let taken = queued + bytes <= MAX_QUEUED_BYTES
                && c.tx.try_send(Out::Frames(share, bytes)).is_ok();
            if taken {
                c.sent.fetch_add(n, Ordering::Relaxed);
            } else {
                c.queued_bytes.fetch_sub(bytes, Ordering::Relaxed);
                c.dropped.fetch_add(n, Ordering::Relaxed);
            }
        }
    }
}
