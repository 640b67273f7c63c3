//! `[server.foxglove]`: the Foxglove WebSocket protocol (`foxglove.websocket.v1`, spoken by
//! hwgw from its published specification), so that Foxglove — and PlotJuggler through its
//! Foxglove bridge — show hwgw's ports live as they are.
//!
//! Every port the section lists (`ports`, and every device's with `devices = true`) is a
//! channel with a JSON Schema, named as `hwgw record` names its MCAP channels
//! (`/sim0/ai/ch0`, schema `hwgw.sample.f64`, messages `{"value": …}`), so a layout made
//! on a recording works live; with `steps = true` the activities' timing is a channel each
//! (`/activity/sim0.ai`). Samples come through a `record` stream — the recorder's stamped
//! buffer connections — opened while a client is connected: each message carries the time
//! the value was written. A slow client loses samples (counted for it), never slows the
//! server or a component. With `allow_writes = true` a client may publish `{"value": …}`
//! on a listed input port's topic: the write goes through `set`, with the checks `hwgw
//! set` passes.
//!
//! The Foxglove SDK's own server (the `foxglove` crate) was not used: it neither bounds
//! its clients nor counts what a slow client loses, and it accepts only the SDK's
//! subprotocol names.

mod client;
mod hub;
pub mod wire;

use crate::config;
use crate::http::{self, Connections};
use crate::service::HttpService;
use driver_api::{CardError, ControlLink, Server, ServerContext};
use serde::Deserialize;
use serde_json::{Value, json};
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};

/// `[server.foxglove]`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FoxgloveConfig {
    /// `address:port` (default 127.0.0.1:8765, Foxglove's; another address only on
    /// purpose).
    #[serde(default = "default_listen")]
    pub listen: String,
    /// Clients at once (1–1024, default 8).
    #[serde(default = "default_clients")]
    pub max_clients: usize,
    /// Ports streamed: `component.port`, or `component` for all of its ports.
    #[serde(default)]
    pub ports: Vec<String>,
    /// Every device's IO component's ports too.
    #[serde(default)]
    pub devices: bool,
    /// The activities' steps too, a channel each.
    #[serde(default)]
    pub steps: bool,
    /// Batches of the stream (a sample batch every 50 ms or so, each client's share of
    /// it) a client's queue holds before it loses the newer ones (2–4096, default 32).
    #[serde(default = "default_queue")]
    pub queue: usize,
    /// Clients may publish to the `inputs`.
    #[serde(default)]
    pub allow_writes: bool,
    /// Input ports (`component.port`) clients may publish `{"value": …}` to, on the
    /// port's topic (`/sim0/ao/ch1`), with `allow_writes`.
    #[serde(default)]
    pub inputs: Vec<String>,
    /// What a client must bring to publish: `ws://HOST:PORT/?token=TOKEN` (Foxglove takes
    /// the URL as given) or `Authorization: Bearer TOKEN`; at least 16 characters;
    /// required with `allow_writes`.
    #[serde(default)]
    pub token: Option<String>,
    /// Web pages of these origins may connect (`https://app.foxglove.dev`); a browser
    /// says which page opens a connection, and one of another origin is refused, so a
    /// site the operator visits cannot read or write the plant. Programs (Foxglove's
    /// desktop app, PlotJuggler) name no origin and are not affected.
    #[serde(default)]
    pub origins: Vec<String>,
    /// Host names it answers to besides its addresses and `localhost`.
    #[serde(default)]
    pub hosts: Vec<String>,
}

fn default_listen() -> String {
    "127.0.0.1:8765".into()
}
fn default_clients() -> usize {
    8
}
fn default_queue() -> usize {
    32
}

/// Samples each streamed port holds between two batches of the stream.
const BUFFER: usize = 256;

/// Builds the Foxglove server of a `[server.foxglove]` section.
pub fn build(
    c: &FoxgloveConfig,
    ctx: &mut ServerContext<'_>,
) -> Result<Box<dyn Server>, Vec<CardError>> {
    let mut problems = Vec::new();
    let endpoint = config::endpoint(&c.listen, c.max_clients, &mut problems);
    if !(2..=4096).contains(&c.queue) {
        problems.push(CardError::at(
            "queue",
            format!("{}: 2-4096 batches", c.queue),
        ));
    }
    let inputs = inputs(c, ctx.runtime())
        .map_err(|p| problems.extend(p))
        .ok();
    if c.ports.is_empty() && !c.devices && !c.steps {
        problems.push(CardError::at(
            "ports",
            "nothing to stream: list ports, or give devices = true or steps = true",
        ));
    }
    for (i, p) in c.ports.iter().enumerate() {
        if let Err(why) = streamable(p, ctx.runtime()) {
            problems.push(CardError::at(format!("ports[{i}]"), why));
        }
    }
    let (Some((listen, clients)), Some(inputs), true) = (endpoint, inputs, problems.is_empty())
    else {
        return Err(problems);
    };
    let hub = Arc::new(hub::Hub::default());
    let mut shared = client::Shared::new("hwgw", hub.clone(), ctx.control().clone(), inputs);
    shared.queue = c.queue;
    shared.token = c.token.clone();
    shared.origins = c.origins.clone();
    shared.hosts = c.hosts.clone();
    let shared = Arc::new(shared);
    let ask = hub::Ask {
        ports: c.ports.clone(),
        devices: c.devices,
        steps: c.steps,
        buffer: BUFFER,
    };
    let pump = Arc::new(Pump {
        hub: hub.clone(),
        control: ctx.control().clone(),
        ask,
        thread: Mutex::new(None),
    });
    let counted = shared.clone();
    let service = HttpService::new(
        ctx.name(),
        listen,
        clients,
        &c.hosts,
        http::Handler::Raw(Arc::new(Accept(shared))),
    )
    .with_status(move || status(&counted))
    .with_hooks(pump);
    Ok(Box::new(service))
}

/// The section's `inputs` by topic, each an input port; every problem.
fn inputs(
    c: &FoxgloveConfig,
    rt: &rtt::Runtime,
) -> Result<std::collections::HashMap<String, client::Input>, Vec<CardError>> {
    let mut out = std::collections::HashMap::new();
    let mut problems = Vec::new();
    config::token(&c.token, c.allow_writes, &mut problems);
    match (c.allow_writes, c.inputs.is_empty()) {
        (true, true) => problems.push(CardError::at("inputs", "allow_writes needs inputs")),
        (false, false) => problems.push(CardError::at(
            "allow_writes",
            "inputs are written only with allow_writes = true",
        )),
        _ => {}
    }
    for (i, name) in c.inputs.iter().enumerate() {
        let input = name.rsplit_once('.').and_then(|(component, port)| {
            let task = rt.component(component).ok()?;
            let info = task.ports().into_iter().find(|p| p.name == port)?;
            (info.direction == rtt::info::Direction::Input).then(|| client::Input {
                component: component.into(),
                port: port.into(),
            })
        });
        match input {
            Some(input) => {
                out.insert(recording::item::port_topic(name), input);
            }
            None => problems.push(CardError::at(
                format!("inputs[{i}]"),
                format!("{name:?} is not an input port (component.port): hwgw set would refuse it"),
            )),
        }
    }
    if problems.is_empty() {
        Ok(out)
    } else {
        Err(problems)
    }
}

/// `Ok` when `name` is a component, or a component's port; else what exists.
fn streamable(name: &str, rt: &rtt::Runtime) -> Result<(), String> {
    if rt.component(name).is_ok() {
        return Ok(());
    }
    let Some((component, port)) = name.rsplit_once('.') else {
        return rt
            .component(name)
            .map(|_| ())
            .map_err(|e| format!("{name:?}: {e}"));
    };
    let task = rt
        .component(component)
        .map_err(|e| format!("{name:?}: {e}"))?;
    if task.port(port).is_ok() {
        return Ok(());
    }
    let ports: Vec<String> = task.ports().into_iter().map(|p| p.name).collect();
    Err(format!(
        "{name:?}: {component} has no port {port:?}; its ports: {}",
        ports.join(", ")
    ))
}

/// Hands each connection to the Foxglove protocol.
struct Accept(Arc<client::Shared>);

impl Connections for Accept {
    fn serve(self: Arc<Self>, conn: http::Conn) -> Pin<Box<dyn Future<Output = ()> + Send>> {
        Box::pin(client::serve(self.0.clone(), conn))
    }
}

/// The pump's thread, started and stopped with the server.
struct Pump {
    hub: Arc<hub::Hub>,
    control: ControlLink,
    ask: hub::Ask,
    thread: Mutex<Option<std::thread::JoinHandle<()>>>,
}

impl crate::service::Hooks for Pump {
    fn started(&self) -> std::io::Result<()> {
        let mut thread = rtt::lock(&self.thread);
        if thread.is_some() {
            return Ok(());
        }
        self.hub.stopping.store(false, Ordering::Release);
        let (hub, control, ask) = (self.hub.clone(), self.control.clone(), self.ask.clone());
        *thread = Some(
            std::thread::Builder::new()
                .name("hwgw-foxglove-pump".into())
                .spawn(move || hub.pump(&control, &ask))?,
        );
        Ok(())
    }

    fn stopped(&self) {
        self.hub.stop();
        if let Some(t) = rtt::lock(&self.thread).take()
            && t.join().is_err()
        {
            tracing::error!("the Foxglove pump panicked");
        }
    }
}

/// Its counters for `hwgw status`: the stream's, the clients' (each with what it lost).
fn status(shared: &client::Shared) -> serde_json::Map<String, Value> {
    let hub = &shared.hub;
    let load = |a: &std::sync::atomic::AtomicU64| Value::from(a.load(Ordering::Relaxed));
    let c = &shared.counters;
    let clients: Vec<Value> = rtt::lock(&hub.clients)
        .iter()
        .map(|c| {
            json!({
                "client": c.id, "peer": c.peer,
                "subscriptions": rtt::lock(&c.subscriptions).len(),
                "sent": load(&c.sent), "dropped": load(&c.dropped),
            })
        })
        .collect();
    let channels = hub.channels().list.len();
    let mut m = serde_json::Map::new();
    m.insert("channels".into(), Value::from(channels));
    m.insert("streams".into(), load(&hub.streams));
    m.insert("items".into(), load(&hub.items));
    m.insert("stream_lost".into(), load(&hub.stream_lost));
    m.insert("handshakes_refused".into(), load(&c.handshakes_refused));
    m.insert("bad_messages".into(), load(&c.bad_messages));
    m.insert("closed_misbehaving".into(), load(&c.closed_misbehaving));
    m.insert("closed_slow".into(), load(&c.closed_slow));
    m.insert("writes".into(), load(&c.writes));
    m.insert("writes_refused".into(), load(&c.writes_refused));
    let now: u64 = rtt::lock(&hub.clients)
        .iter()
        .map(|c| c.dropped.load(Ordering::Relaxed))
        .sum();
    let dropped = now + hub.dropped_left.load(Ordering::Relaxed);
    m.insert("dropped".into(), Value::from(dropped));
    m.insert("clients".into(), Value::Array(clients));
    if let Some(e) = rtt::lock(&hub.last_error).clone() {
        m.insert("stream_error".into(), Value::from(e));
    }
    m
}
