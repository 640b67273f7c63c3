//! The edge node's life: connect with the NDEATH of the session as the will, subscribe to
//! the commands, wait for the primary host where there is one, publish the births, then
//! every sample period what changed; on a lost link start again (a new session, `bdSeq`
//! one more, a fresh birth with the newest values — nothing is queued for a link that is
//! down), on stop send the NDEATH and leave cleanly.

use crate::commands::{self, Book, Job, Origin};
use crate::link::{self, Client, Events, Seen, Will};
use crate::model::{self, Group, Value};
use crate::sparkplug::{self, NodeCommand, Topics};
use device_interface::{Registry, Status};
use serde_json::json;
use std::sync::Arc;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::SyncSender;
use std::time::{Duration, Instant};
use tokio::sync::watch;

/// The counters of the link, for `hwgw status`.
#[derive(Default)]
pub(crate) struct Counters {
    pub connected: AtomicBool,
    pub host_online: AtomicBool,
    pub published: AtomicU64,
    pub dropped: AtomicU64,
    pub reconnects: AtomicU64,
    pub births: AtomicU64,
    pub bad_messages: AtomicU64,
    pub bd_seq: AtomicU64,
    pub last_error: Mutex<Option<String>>,
}

/// Everything a session runs with.
pub(crate) struct Node {
    pub settings: crate::config::Settings,
    pub tls: Option<Arc<rustls::ClientConfig>>,
    pub groups: Vec<Group>,
    pub registry: Arc<Registry>,
    pub counters: Arc<Counters>,
    pub book: Arc<Book>,
    pub jobs: SyncSender<Job>,
    /// Each metric's JSON topic state (group, metric order).
    json: Vec<Vec<JsonState>>,
    topics: Option<Topics>,
    /// The session's `bdSeq`, and the next message's `seq`.
    bd_seq: u8,
    seq: u8,
    /// The newest STATE timestamp of the primary host.
    state_ts: u64,
}

/// A metric's JSON topic: the device status last published, and whether its newest
/// value is still to be published (its message was not queued).
#[derive(Debug, Clone, Copy, Default)]
struct JsonState {
    status: Option<Status>,
    pending: bool,
}

/// Why a session ended.
enum End {
    Stop,
    Lost,
    HostOffline,
}

/// The longest wait between two attempts to connect.
const BACKOFF_MAX: Duration = Duration::from_secs(10);
/// How long a leaving session waits for its NDEATH to go out.
const LEAVE: Duration = Duration::from_secs(2);

impl Node {
    /// A node of `groups`.
    pub(crate) fn new(
        settings: crate::config::Settings,
        tls: Option<Arc<rustls::ClientConfig>>,
        groups: Vec<Group>,
        registry: Arc<Registry>,
        (counters, book, jobs): (Arc<Counters>, Arc<Book>, SyncSender<Job>),
    ) -> Node {
        let topics = settings
            .sparkplug
            .as_ref()
            .map(|s| Topics::new(&s.group, &s.node));
        let json = groups
            .iter()
            .map(|g| vec![JsonState::default(); g.metrics.len()])
            .collect();
        Node {
            settings,
            tls,
            groups,
            registry,
            counters,
            book,
            jobs,
            json,
            topics,
            bd_seq: 0,
            seq: 0,
            state_ts: 0,
        }
    }

    /// Runs sessions until `stop` turns true.
    pub(crate) async fn run(mut self, mut stop: watch::Receiver<bool>) {
        let mut backoff = Duration::from_millis(200);
        let mut sessions = 0u64;
        while !*stop.borrow() {
            let will = self.will();
            let (client, events) = link::session(&self.settings, self.tls.as_ref(), Some(will));
            let (end, connected) = self.session(&client, events, &mut stop).await;
            self.counters.connected.store(false, Ordering::Relaxed);
            for g in &mut self.groups {
                g.born = false;
            }
            if connected {
                sessions += 1;
                backoff = Duration::from_millis(200);
                self.bd_seq = self.bd_seq.wrapping_add(1);
                self.counters
                    .bd_seq
                    .store(self.bd_seq.into(), Ordering::Relaxed);
            }
            match end {
                End::Stop => break,
                End::HostOffline => {}
                End::Lost => {
                    tokio::select! {
                        _ = tokio::time::sleep(backoff) => {}
                        _ = stop.changed() => {}
                    }
                    backoff = (backoff * 2).min(BACKOFF_MAX);
                }
            }
            if sessions > 0 && !*stop.borrow() {
                self.counters.reconnects.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// The will of the next session: its NDEATH, or the JSON status `offline`.
    fn will(&self) -> Will {
        match &self.topics {
            Some(t) => Will {
                topic: t.node("NDEATH"),
                payload: sparkplug::ndeath(self.bd_seq),
                retain: false,
            },
            None => Will {
                topic: self.status_topic(),
                payload: b"offline".to_vec(),
                retain: true,
            },
        }
    }

    fn status_topic(&self) -> String {
        format!("{}/status", self.settings.json.as_deref().unwrap_or("hwgw"))
    }

    /// One session; whether it got connected.
    async fn session(
        &mut self,
        client: &Client,
        mut events: Events,
        stop: &mut watch::Receiver<bool>,
    ) -> (End, bool) {
        // Connected, or why not.
        loop {
            tokio::select! {
                _ = stop.changed() => return (End::Stop, false),
                r = events.poll() => match r {
                    Ok(Seen::Connected) => break,
                    Ok(_) => {}
                    Err(e) => {
                        self.failed(&e);
                        return (End::Lost, false);
                    }
                }
            }
        }
        self.counters.connected.store(true, Ordering::Relaxed);
        *rtt::lock(&self.counters.last_error) = None;
        tracing::info!(
            "MQTT: connected to {}:{}",
            self.settings.host,
            self.settings.port
        );
        client.subscribe(&self.subscriptions());
        let primary = self
            .settings
            .sparkplug
            .as_ref()
            .and_then(|s| s.primary_host.clone());
        let mut host_online = primary.is_none();
        self.counters
            .host_online
            .store(host_online, Ordering::Relaxed);
        let mut born = false;
        if host_online {
            self.births(client);
            born = true;
        }
        if self.settings.json.is_some() {
            client.publish(self.status_topic(), true, true, b"online".to_vec());
        }
        let mut tick = tokio::time::interval(self.settings.sample);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        loop {
            tokio::select! {
                _ = stop.changed() => {
                    self.leave(client, &mut events, born).await;
                    return (End::Stop, true);
                }
                r = events.poll() => match r {
                    Err(e) => {
                        self.failed(&e);
                        return (End::Lost, true);
                    }
                    Ok(Seen::Published) => {
                        self.counters.published.fetch_add(1, Ordering::Relaxed);
                    }
                    Ok(Seen::Message(topic, payload)) => {
                        match self.message(client, &topic, &payload, primary.as_deref()) {
                            Some(true) if !host_online => {
                                host_online = true;
                                self.counters.host_online.store(true, Ordering::Relaxed);
                                self.births(client);
                                born = true;
                            }
                            Some(false) if host_online => {
                                // The primary host went away: leave, and come back with
                                // a new session once it is online again.
                                self.counters.host_online.store(false, Ordering::Relaxed);
                                self.leave(client, &mut events, born).await;
                                return (End::HostOffline, true);
                            }
                            _ => {}
                        }
                    }
                    Ok(_) => {}
                },
                _ = tick.tick() => {
                    if born {
                        self.publish_changes(client);
                    }
                    self.publish_outcomes(client, born);
                }
            }
        }
    }

    fn failed(&self, e: &str) {
        tracing::warn!("MQTT: {}:{}: {e}", self.settings.host, self.settings.port);
        *rtt::lock(&self.counters.last_error) = Some(e.to_string());
    }

    /// Sends the NDEATH (an intentional leave) and the JSON status, disconnects cleanly:
    /// reads on until the broker closes the connection, so that nothing unread is left
    /// when it is dropped (a socket closed with unread bytes is reset, and a broker may
    /// lose the DISCONNECT with it and publish the will as well).
    async fn leave(&mut self, client: &Client, events: &mut Events, born: bool) {
        if let (Some(t), true) = (&self.topics, born) {
            client.publish(
                t.node("NDEATH"),
                true,
                false,
                sparkplug::ndeath(self.bd_seq),
            );
        }
        if self.settings.json.is_some() {
            client.publish(self.status_topic(), true, true, b"offline".to_vec());
        }
        client.disconnect();
        let deadline = tokio::time::sleep(LEAVE);
        tokio::pin!(deadline);
        loop {
            tokio::select! {
                _ = &mut deadline => break,
                r = events.poll() => match r {
                    Ok(Seen::Published) => { self.counters.published.fetch_add(1, Ordering::Relaxed); }
                    Ok(_) => {}
                    Err(_) => break,
                }
            }
        }
    }

    fn subscriptions(&self) -> Vec<String> {
        let mut s = Vec::new();
        if let Some(t) = &self.topics {
            s.push(t.node("NCMD"));
            s.push(t.device("DCMD", "+"));
        }
        if let Some(h) = self
            .settings
            .sparkplug
            .as_ref()
            .and_then(|s| s.primary_host.as_ref())
        {
            s.push(Topics::state(h));
        }
        if let Some(p) = &self.settings.json {
            s.push(format!("{p}/+/+/set"));
        }
        s
    }

    /// Handles a message: `Some(online)` for the primary host's STATE.
    fn message(
        &mut self,
        client: &Client,
        topic: &str,
        payload: &[u8],
        primary: Option<&str>,
    ) -> Option<bool> {
        if let Some(h) = primary
            && topic == Topics::state(h)
        {
            return self.state(payload);
        }
        if let Some(t) = &self.topics {
            if topic == t.node("NCMD") {
                match sparkplug::ncmd(payload) {
                    Ok(cmds) if cmds.contains(&NodeCommand::Rebirth) => self.rebirth(client),
                    Ok(_) => {}
                    Err(e) => self.bad(topic, &e.to_string()),
                }
                return None;
            }
            if let Some(device) = t.dcmd_device(topic) {
                let device = device.to_string();
                let job = sparkplug::dcmd(payload)
                    .map_err(|e| format!("not a Sparkplug B payload: {e}"))
                    .and_then(|w| {
                        commands::dcmd(&self.groups, &device, &w, self.settings.allow_writes)
                    });
                self.submit(Origin::Sparkplug(device), job);
                return None;
            }
        }
        if let Some(p) = &self.settings.json
            && topic.ends_with("/set")
        {
            let job =
                commands::json_set(&self.groups, p, topic, payload, self.settings.allow_writes);
            self.submit(Origin::Json(topic.into()), job);
            return None;
        }
        self.bad(topic, "not a topic hwgw serves");
        None
    }

    fn submit(&self, origin: Origin, job: Result<Job, String>) {
        match job {
            Ok(job) => self.book.submit(&self.jobs, job),
            Err(why) => self.book.record(commands::Outcome {
                origin,
                result: Err(why),
            }),
        }
    }

    fn bad(&self, topic: &str, why: &str) {
        tracing::debug!("MQTT: {topic}: {why}");
        self.counters.bad_messages.fetch_add(1, Ordering::Relaxed);
    }

    /// A Sparkplug 3.0 STATE message: `{"online": …, "timestamp": …}`; an older one than
    /// the newest seen is ignored.
    fn state(&mut self, payload: &[u8]) -> Option<bool> {
        let v: serde_json::Value = match serde_json::from_slice(payload) {
            Ok(v) => v,
            Err(e) => {
                self.bad("STATE", &e.to_string());
                return None;
            }
        };
        let (Some(online), Some(ts)) = (v["online"].as_bool(), v["timestamp"].as_u64()) else {
            self.bad("STATE", "no online and timestamp");
            return None;
        };
        if ts < self.state_ts {
            return None;
        }
        self.state_ts = ts;
        Some(online)
    }

    /// Queues a Sparkplug message made with `self.seq`: the next `seq` once it is queued.
    fn send(&mut self, client: &Client, topic: String, payload: Vec<u8>) -> bool {
        let ok = client.publish(topic, false, false, payload);
        if ok {
            self.seq = self.seq.wrapping_add(1);
        } else {
            self.counters.dropped.fetch_add(1, Ordering::Relaxed);
        }
        ok
    }

    /// NBIRTH and a DBIRTH per online device, and the JSON topics' state, all with the
    /// values now.
    fn births(&mut self, client: &Client) {
        let now = Instant::now();
        let t = sparkplug::now_ms();
        let writes = self.settings.allow_writes;
        if let Some(topics) = self.topics.clone() {
            self.seq = 0;
            let refused = self.book.refused.load(Ordering::Relaxed);
            let last = rtt::lock(&self.book.last_refusal).clone();
            let bd = self.bd_seq;
            self.send(
                client,
                topics.node("NBIRTH"),
                sparkplug::nbirth(bd, refused, &last),
            );
            self.counters.births.fetch_add(1, Ordering::Relaxed);
        }
        for gi in 0..self.groups.len() {
            let values: Vec<Option<Value>> = self.groups[gi]
                .metrics
                .iter()
                .map(|m| m.source.read().ok())
                .collect();
            let statuses = self.groups[gi].statuses(&self.registry);
            if let Some(topics) = self.topics.clone() {
                let g = &self.groups[gi];
                if !model::online(&statuses) {
                    continue;
                }
                let topic = topics.device("DBIRTH", &g.id);
                let payload = sparkplug::dbirth(self.seq, g, &values, writes);
                if !self.send(client, topic, payload) {
                    continue;
                }
                self.groups[gi].born = true;
            }
            for (mi, v) in values.iter().enumerate() {
                if let Some(v) = v {
                    self.groups[gi].metrics[mi].sent = Some((*v, now));
                }
                let status = statuses[self.groups[gi].metrics[mi].device];
                self.publish_json(client, (gi, mi), *v, status, t);
            }
        }
    }

    fn rebirth(&mut self, client: &Client) {
        self.publish_changes(client);
        self.births(client);
    }

    /// What changed since it was last published, and devices gone or back.
    fn publish_changes(&mut self, client: &Client) {
        let now = Instant::now();
        let t = sparkplug::now_ms();
        let (min, max) = (self.settings.min_period, self.settings.max_period);
        let writes = self.settings.allow_writes;
        for gi in 0..self.groups.len() {
            let statuses = self.groups[gi].statuses(&self.registry);
            if let Some(topics) = self.topics.clone() {
                let online = model::online(&statuses);
                let g = &self.groups[gi];
                if g.born && !online {
                    let topic = topics.device("DDEATH", &g.id);
                    if self.send(client, topic, sparkplug::ddeath(self.seq)) {
                        self.groups[gi].born = false;
                    }
                } else if !g.born && online {
                    let values: Vec<Option<Value>> =
                        g.metrics.iter().map(|m| m.source.read().ok()).collect();
                    let payload = sparkplug::dbirth(self.seq, g, &values, writes);
                    if self.send(client, topics.device("DBIRTH", &g.id), payload) {
                        let g = &mut self.groups[gi];
                        g.born = true;
                        for (m, v) in g.metrics.iter_mut().zip(values) {
                            m.sent = v.map(|v| (v, now));
                        }
                    }
                    continue;
                }
            }
            let g = &self.groups[gi];
            let changes: Vec<(usize, Value)> = g
                .metrics
                .iter()
                .enumerate()
                .filter_map(|(i, m)| {
                    m.source
                        .read()
                        .ok()
                        .filter(|v| m.due(*v, now, min, max))
                        .map(|v| (i, v))
                })
                .collect();
            if let (Some(topics), true, false) = (&self.topics, g.born, changes.is_empty()) {
                let list: Vec<_> = changes
                    .iter()
                    .map(|(i, v)| (&g.metrics[*i], *v, t))
                    .collect();
                let topic = topics.device("DDATA", &g.id);
                let payload = sparkplug::ddata(self.seq, &list);
                if !self.send(client, topic, payload) {
                    // Not queued: these values go with the next message.
                    continue;
                }
            }
            for (i, v) in &changes {
                self.groups[gi].metrics[*i].sent = Some((*v, now));
            }
            if self.settings.json.is_some() {
                let mut new: Vec<Option<Value>> = vec![None; self.groups[gi].metrics.len()];
                for (i, v) in &changes {
                    new[*i] = Some(*v);
                }
                for (mi, v) in new.into_iter().enumerate() {
                    let status = statuses[self.groups[gi].metrics[mi].device];
                    self.publish_json(client, (gi, mi), v, status, t);
                }
            }
        }
    }

    /// A JSON topic's state when its value `v` is new, its device's status changed, or
    /// its newest value is still to be published; a message not queued is counted and
    /// tried again with the newest value at the next tick.
    fn publish_json(
        &mut self,
        client: &Client,
        (gi, mi): (usize, usize),
        v: Option<Value>,
        status: Status,
        t: u64,
    ) {
        let Some(prefix) = &self.settings.json else {
            return;
        };
        let m = &self.groups[gi].metrics[mi];
        let state = &mut self.json[gi][mi];
        if v.is_none() && state.status == Some(status) && !state.pending {
            return;
        }
        let value = v
            .or(m.sent.map(|s| s.0))
            .map_or(serde_json::Value::Null, Value::json);
        let body = json!({"value": value, "status": status.to_string(), "t": t});
        let topic = format!("{prefix}/{}/{}", m.component, m.port);
        if client.publish(topic, false, true, body.to_string().into_bytes()) {
            *state = JsonState {
                status: Some(status),
                pending: false,
            };
        } else {
            state.pending = true;
            self.counters.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// What became of the commands since the last tick.
    fn publish_outcomes(&mut self, client: &Client, born: bool) {
        let outcomes: Vec<_> = rtt::lock(&self.book.outcomes).drain(..).collect();
        let mut refused = false;
        for o in outcomes {
            match &o.origin {
                Origin::Sparkplug(_) => refused |= o.result.is_err(),
                Origin::Json(topic) => {
                    let body = match &o.result {
                        Ok(()) => json!({"ok": true}),
                        Err(why) => json!({"ok": false, "error": why}),
                    };
                    if !client.publish(
                        format!("{topic}/result"),
                        true,
                        false,
                        body.to_string().into_bytes(),
                    ) {
                        self.counters.dropped.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
        }
        if let (true, true, Some(topics)) = (refused, born, self.topics.clone()) {
            let n = self.book.refused.load(Ordering::Relaxed);
            let last = rtt::lock(&self.book.last_refusal).clone();
            let payload = sparkplug::ndata_refusal(self.seq, n, &last);
            self.send(client, topics.node("NDATA"), payload);
        }
    }
}
