//! The edge node's life: connect with the NDEATH of the session as the will, subscribe to
//! the commands, wait for the primary host where there is one, publish the births, then
//! every sample period what changed (`publish`); on a lost link start again (a new
//! session, `bdSeq` one more, a fresh birth with the newest values — nothing is queued
//! for a link that is down), on stop send the NDEATH and leave cleanly.
//!
//! The connection's event loop runs on a task of its own and hands its events over a
//! channel: the session waits on the channel, the sample period and the stop together,
//! and no write of the event loop is ever cut off halfway by them.

use crate::commands::{self, Book, Job, Origin, Outcome, Refusal};
use crate::link::{self, Outbox, Seeing, Seen, Will};
use crate::model::Group;
use crate::sparkplug::{self, NodeCommand, Topics};
use device_interface::{Registry, Status};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::SyncSender;
use std::sync::{Arc, Mutex};
use std::time::Duration;
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
    pub subscriptions_refused: AtomicU64,
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
    pub json: Vec<Vec<JsonState>>,
    pub topics: Option<Topics>,
    /// The session's `bdSeq`, and the next message's `seq`.
    pub bd_seq: u8,
    pub seq: u8,
    /// The Sparkplug births of this session are out (the NBIRTH: the DBIRTHs follow
    /// each device as it is online).
    pub born: bool,
    /// A rebirth was asked for: made at the next period, once however often asked.
    pub rebirth_asked: bool,
    /// An NBIRTH went out in this session: the host holds this `bdSeq`, and hwgw leaving
    /// owes it the NDEATH.
    pub announced: bool,
    /// The newest STATE timestamp of the primary host.
    state_ts: u64,
    /// Connections made so far.
    connections: u64,
}

/// A metric's JSON topic: the device status and value last published, and whether its
/// newest value is still to be published (its message was not queued).
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct JsonState {
    pub status: Option<Status>,
    pub pending: bool,
    /// The value last published, and when.
    pub sent: Option<(crate::model::Value, std::time::Instant)>,
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
            born: false,
            rebirth_asked: false,
            announced: false,
            state_ts: 0,
            connections: 0,
        }
    }

    /// Runs sessions until `stop` turns true.
    pub(crate) async fn run(mut self, mut stop: watch::Receiver<bool>) {
        let mut backoff = Duration::from_millis(200);
        while !*stop.borrow() {
            let (client, events) =
                link::session(&self.settings, self.tls.as_ref(), Some(self.will()));
            let (mut seen, task) = events.spawn();
            let mut out = Outbox::new(client, self.settings.queue_bytes);
            let (end, connected) = self.session(&mut out, &mut seen, &mut stop).await;
            task.abort();
            self.counters.connected.store(false, Ordering::Relaxed);
            self.born = false;
            self.announced = false;
            self.rebirth_asked = false;
            for g in &mut self.groups {
                g.born = false;
            }
            if connected {
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

    pub(crate) fn status_topic(&self) -> String {
        format!("{}/status", self.settings.json.as_deref().unwrap_or("hwgw"))
    }

    /// One session; whether it got connected.
    async fn session(
        &mut self,
        out: &mut Outbox,
        seen: &mut Seeing,
        stop: &mut watch::Receiver<bool>,
    ) -> (End, bool) {
        // Connected, or why not.
        loop {
            tokio::select! {
                _ = stop.changed() => return (End::Stop, false),
                r = seen.recv() => match r {
                    Some(Ok(Seen::Connected)) => break,
                    Some(Ok(_)) => {}
                    Some(Err(e)) => {
                        self.failed(&e.to_string());
                        return (End::Lost, false);
                    }
                    None => return (End::Lost, false),
                }
            }
        }
        self.counters.connected.store(true, Ordering::Relaxed);
        if self.connections > 0 {
            self.counters.reconnects.fetch_add(1, Ordering::Relaxed);
        }
        self.connections += 1;
        *rtt::lock(&self.counters.last_error) = None;
        tracing::info!(
            "MQTT: connected to {}:{}",
            self.settings.host,
            self.settings.port
        );
        out.client().subscribe(&self.subscriptions());
        let primary = self
            .settings
            .sparkplug
            .as_ref()
            .and_then(|s| s.primary_host.clone());
        let mut host_online = primary.is_none();
        self.counters
            .host_online
            .store(host_online, Ordering::Relaxed);
        if self.settings.json.is_some() {
            out.publish(self.status_topic(), true, true, b"online".to_vec());
        }
        self.first_values(out, host_online);
        let mut tick = tokio::time::interval(self.settings.sample);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        loop {
            tokio::select! {
                _ = stop.changed() => {
                    self.leave(out, seen, true).await;
                    return (End::Stop, true);
                }
                r = seen.recv() => match r {
                    Some(Err(e)) => {
                        self.failed(&e.to_string());
                        return (End::Lost, true);
                    }
                    None => return (End::Lost, true),
                    Some(Ok(Seen::Published)) => {
                        out.published();
                        self.counters.published.fetch_add(1, Ordering::Relaxed);
                    }
                    Some(Ok(Seen::Subscribed(refused))) if refused > 0 => {
                        self.counters.subscriptions_refused.fetch_add(refused as u64, Ordering::Relaxed);
                        self.failed(&format!("the broker refused {refused} of hwgw's subscriptions (its access control?)"));
                    }
                    Some(Ok(Seen::Message(topic, payload, retain))) => {
                        match self.message(&topic, &payload, retain, primary.as_deref()) {
                            Some(true) if !host_online => {
                                host_online = true;
                                self.counters.host_online.store(true, Ordering::Relaxed);
                                self.rebirth_asked = true;
                            }
                            Some(false) if host_online => {
                                // The primary host went away: leave, and come back with
                                // a new session once it is online again.
                                self.counters.host_online.store(false, Ordering::Relaxed);
                                self.leave(out, seen, false).await;
                                return (End::HostOffline, true);
                            }
                            _ => {}
                        }
                    }
                    Some(Ok(_)) => {}
                },
                _ = tick.tick() => {
                    if std::mem::take(&mut self.rebirth_asked) && host_online {
                        self.rebirth(out);
                    }
                    self.publish_changes(out);
                    self.publish_outcomes(out);
                }
            }
        }
    }

    fn failed(&self, e: &str) {
        tracing::warn!("MQTT: {}:{}: {e}", self.settings.host, self.settings.port);
        *rtt::lock(&self.counters.last_error) = Some(e.to_string());
    }

    /// Sends the NDEATH (an intentional leave) and, when hwgw stops (`last`), the JSON
    /// status; disconnects cleanly: reads on until the broker closes the connection, so
    /// that nothing unread is left when it is dropped (a socket closed with unread bytes
    /// is reset, and a broker may lose the DISCONNECT with it and publish the will too).
    async fn leave(&mut self, out: &mut Outbox, seen: &mut Seeing, last: bool) {
        // Whatever the byte budget: and when the NDEATH cannot be queued at all, the
        // connection is dropped without a DISCONNECT, so the broker publishes the will.
        let mut owed = true;
        if let (Some(t), true) = (&self.topics, self.announced) {
            let ndeath = sparkplug::ndeath(self.bd_seq);
            owed = out.publish_now(t.node("NDEATH"), true, false, ndeath);
        }
        if self.settings.json.is_some() && last {
            owed &= out.publish_now(self.status_topic(), true, true, b"offline".to_vec());
        }
        if !owed {
            return;
        }
        out.client().disconnect();
        let deadline = tokio::time::sleep(LEAVE);
        tokio::pin!(deadline);
        loop {
            tokio::select! {
                _ = &mut deadline => break,
                r = seen.recv() => match r {
                    Some(Ok(Seen::Published)) => {
                        self.counters.published.fetch_add(1, Ordering::Relaxed);
                    }
                    Some(Ok(_)) => {}
                    Some(Err(_)) | None => break,
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
        topic: &str,
        payload: &[u8],
        retain: bool,
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
                    Ok(_) if retain => self.bad(topic, "a retained NCMD"),
                    Ok(cmds) if cmds.contains(&NodeCommand::Rebirth) => self.rebirth_asked = true,
                    Ok(_) => {}
                    Err(e) => self.bad(topic, &e.to_string()),
                }
                return None;
            }
            if let Some(device) = t.dcmd_device(topic) {
                let origin = Origin::Sparkplug(device.to_string());
                let job = self.writable(retain).and_then(|()| {
                    let writes = sparkplug::dcmd(payload)
                        .map_err(|e| Refusal::NotSparkplug(e.to_string()))?;
                    let registry = &self.registry;
                    commands::dcmd(&self.groups, device, &writes, |g| g.statuses(registry))
                });
                self.submit(origin, job);
                return None;
            }
        }
        if let Some(p) = &self.settings.json
            && topic.ends_with("/set")
        {
            let registry = &self.registry;
            let job = self.writable(retain).and_then(|()| {
                commands::json_set(&self.groups, p, topic, payload, |g| g.statuses(registry))
            });
            self.submit(Origin::Json(topic.into()), job);
            return None;
        }
        self.bad(topic, "not a topic hwgw serves");
        None
    }

    /// `Ok` when a command may be carried out at all.
    fn writable(&self, retain: bool) -> Result<(), Refusal> {
        if !self.settings.allow_writes {
            Err(Refusal::NotAllowed)
        } else if retain {
            Err(Refusal::Retained)
        } else {
            Ok(())
        }
    }

    fn submit(&self, origin: Origin, job: Result<Job, Refusal>) {
        match job {
            Ok(job) => self.book.submit(&self.jobs, job),
            Err(why) => self.book.record(Outcome {
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
}
