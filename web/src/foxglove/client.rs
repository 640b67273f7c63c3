//! One Foxglove client's connection: the WebSocket handshake (the Foxglove subprotocol
//! required, within a time limit), `serverInfo` and `advertise`, then its subscriptions,
//! and — where the deployment allows — its writes to input ports, one at a time, each
//! through the gateway's `set` (the checks `hwgw set` passes; the output policy's).
//!
//! Bounded: a message larger than the server takes closes the connection (the WebSocket
//! layer refuses it before it is whole); so does a queue too full to take a control
//! message, and a client that keeps sending what is not the protocol.

use super::hub::{Client, Hub, Out};
use super::wire::{self, ClientChannel, ClientOp, Level};
use driver_api::ControlLink;
use futures_util::{SinkExt, StreamExt};
use serde_json::{Value, json};
use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;
use tokio::sync::mpsc;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tokio_tungstenite::tungstenite::protocol::WebSocketConfig;

/// What every connection shares.
pub struct Shared {
    /// The server's name in `serverInfo`.
    pub name: String,
    /// The session id in `serverInfo` (changes when the server starts again).
    pub session: String,
    /// Where the samples come from.
    pub hub: Arc<Hub>,
    /// The gateway, for writes.
    pub control: ControlLink,
    /// The input ports clients may publish to, by topic (none: no publishing).
    pub inputs: HashMap<String, Input>,
    /// A client's queue, batches.
    pub queue: usize,
    /// The largest message a client may send, bytes.
    pub max_message: usize,
    /// Counters.
    pub counters: Counters,
    next_client: AtomicU64,
}

/// A Foxglove server's counters beyond its connections'.
#[derive(Debug, Default)]
pub struct Counters {
    /// Handshakes refused (no Foxglove subprotocol, not a WebSocket, too slow).
    pub handshakes_refused: AtomicU64,
    /// Client messages that are not the protocol (or not allowed).
    pub bad_messages: AtomicU64,
    /// Clients closed for sending too many of those, or too large a message.
    pub closed_misbehaving: AtomicU64,
    /// Clients closed for a queue too full to take a control message.
    pub closed_slow: AtomicU64,
    /// Writes carried out.
    pub writes: AtomicU64,
    /// Writes refused (not allowed, not a listed input port, refused by the gateway).
    pub writes_refused: AtomicU64,
}

/// An input port a client may publish to.
#[derive(Debug, Clone)]
pub struct Input {
    /// Its component.
    pub component: String,
    /// Its name.
    pub port: String,
}

/// How long a handshake may take.
const HANDSHAKE: Duration = Duration::from_secs(5);
/// Bad messages a client may send before it is closed.
const BAD_LIMIT: u64 = 100;
/// Channels a client may advertise.
const MAX_CLIENT_CHANNELS: usize = 64;

impl Shared {
    /// The shared state of a server's connections; clients publish to `inputs`.
    pub fn new(
        name: &str,
        hub: Arc<Hub>,
        control: ControlLink,
        inputs: HashMap<String, Input>,
    ) -> Shared {
        let session = format!("{:x}", std::process::id());
        Shared {
            name: name.to_string(),
            session,
            hub,
            control,
            inputs,
            queue: 32,
            max_message: 64 * 1024,
            counters: Counters::default(),
            next_client: AtomicU64::new(1),
        }
    }
}

/// Serves one connection until it ends.
pub async fn serve(shared: Arc<Shared>, tcp: tokio::net::TcpStream) {
    let peer = tcp.peer_addr().map(|a| a.to_string()).unwrap_or_default();
    let _ = tcp.set_nodelay(true);
    let config = WebSocketConfig::default()
        .max_message_size(Some(shared.max_message))
        .max_frame_size(Some(shared.max_message));
    #[allow(
        clippy::result_large_err,
        reason = "tungstenite's handshake callback has this signature"
    )]
    let pick = |req: &Request, mut resp: Response| -> Result<Response, ErrorResponse> {
        let offered = req
            .headers()
            .get_all("sec-websocket-protocol")
            .iter()
            .filter_map(|v| v.to_str().ok())
            .flat_map(|v| v.split(','))
            .map(str::trim)
            .find(|p| wire::SUBPROTOCOLS.contains(p))
            .map(str::to_string);
        match offered.and_then(|p| p.parse().ok()) {
            Some(p) => {
                resp.headers_mut().insert("sec-websocket-protocol", p);
                Ok(resp)
            }
            None => {
                let mut e = ErrorResponse::new(Some(
                    "a Foxglove client: Sec-WebSocket-Protocol foxglove.websocket.v1\n".into(),
                ));
                *e.status_mut() = hyper::StatusCode::BAD_REQUEST;
                Err(e)
            }
        }
    };
    let handshake = tokio_tungstenite::accept_hdr_async_with_config(tcp, pick, Some(config));
    let ws = match tokio::time::timeout(HANDSHAKE, handshake).await {
        Ok(Ok(ws)) => ws,
        _ => {
            shared
                .counters
                .handshakes_refused
                .fetch_add(1, Ordering::Relaxed);
            return;
        }
    };
    let (mut sink, mut stream) = ws.split();
    let (tx, mut rx) = mpsc::channel(shared.queue);
    let client = Arc::new(Client {
        id: shared.next_client.fetch_add(1, Ordering::Relaxed),
        peer,
        tx,
        subscriptions: Default::default(),
        sent: AtomicU64::new(0),
        dropped: AtomicU64::new(0),
    });
    client.tell(wire::server_info(
        &shared.name,
        !shared.inputs.is_empty(),
        &shared.session,
    ));
    let channels = shared.hub.channels();
    if !channels.list.is_empty() {
        client.tell(wire::advertise(&channels.list));
    }
    shared.hub.join(client.clone());
    let writer = async {
        while let Some(out) = rx.recv().await {
            let sent = match out {
                Out::Text(t) => sink.send(Message::text(t)).await,
                Out::Frames(frames) => {
                    let mut r = Ok(());
                    for f in frames {
                        r = sink.feed(Message::binary(f)).await;
                        if r.is_err() {
                            break;
                        }
                    }
                    if r.is_ok() { sink.flush().await } else { r }
                }
            };
            if sent.is_err() {
                break;
            }
        }
        let _ = sink.close().await;
    };
    let reader = read(&shared, &client, &mut stream);
    tokio::select! {
        () = writer => {}
        () = reader => {}
    }
    shared.hub.leave(client.id);
}

/// The client's messages until it goes, misbehaves or cannot be told.
async fn read<S>(shared: &Shared, client: &Client, stream: &mut S)
where
    S: futures_util::Stream<Item = Result<Message, tokio_tungstenite::tungstenite::Error>> + Unpin,
{
    let mut bad = 0u64;
    let mut published: HashMap<u32, ClientChannel> = HashMap::new();
    while let Some(m) = stream.next().await {
        let outcome = match m {
            Ok(Message::Text(t)) => op(shared, client, &mut published, t.as_str()),
            Ok(Message::Binary(b)) => publish(shared, &published, &b).await,
            Ok(Message::Close(_)) => return,
            Ok(_) => Ok(()),
            Err(_) => {
                // Too large, or not WebSocket: the connection cannot go on.
                shared
                    .counters
                    .closed_misbehaving
                    .fetch_add(1, Ordering::Relaxed);
                return;
            }
        };
        if let Err(why) = outcome {
            shared.counters.bad_messages.fetch_add(1, Ordering::Relaxed);
            bad += 1;
            if bad >= BAD_LIMIT {
                shared
                    .counters
                    .closed_misbehaving
                    .fetch_add(1, Ordering::Relaxed);
                client.tell(wire::status(Level::Error, "too many bad messages: closing"));
                return;
            }
            if !client.tell(wire::status(Level::Error, &why)) {
                shared.counters.closed_slow.fetch_add(1, Ordering::Relaxed);
                return;
            }
        }
    }
}

/// A JSON operation of the client's.
fn op(
    shared: &Shared,
    client: &Client,
    published: &mut HashMap<u32, ClientChannel>,
    text: &str,
) -> Result<(), String> {
    let op: ClientOp = serde_json::from_str(text).map_err(|e| format!("not understood: {e}"))?;
    let channels = shared.hub.channels();
    match op {
        ClientOp::Subscribe { subscriptions } => {
            let mut subs = rtt::lock(&client.subscriptions);
            let mut unknown = Vec::new();
            for s in subscriptions {
                if channels.list.iter().any(|c| c.id == s.channel_id) {
                    subs.retain(|_, sub| *sub != s.id);
                    subs.insert(s.channel_id, s.id);
                } else {
                    unknown.push(s.channel_id);
                }
            }
            if unknown.is_empty() {
                Ok(())
            } else {
                Err(format!("no channels {unknown:?}"))
            }
        }
        ClientOp::Unsubscribe { subscription_ids } => {
            rtt::lock(&client.subscriptions).retain(|_, sub| !subscription_ids.contains(sub));
            Ok(())
        }
        ClientOp::Advertise { channels: list } => {
            if shared.inputs.is_empty() {
                shared
                    .counters
                    .writes_refused
                    .fetch_add(1, Ordering::Relaxed);
                return Err("this server takes no writes (allow_writes = false)".into());
            }
            for c in list {
                if c.encoding != "json" {
                    return Err(format!(
                        "{}: only json is taken, not {:?}",
                        c.topic, c.encoding
                    ));
                }
                if !shared.inputs.contains_key(&c.topic) {
                    let topics: Vec<&String> = shared.inputs.keys().collect();
                    return Err(format!(
                        "{}: not an input this server takes; it takes {topics:?}",
                        c.topic
                    ));
                }
                if published.len() >= MAX_CLIENT_CHANNELS && !published.contains_key(&c.id) {
                    return Err(format!("at most {MAX_CLIENT_CHANNELS} channels a client"));
                }
                published.insert(c.id, c);
            }
            Ok(())
        }
        ClientOp::Unadvertise { channel_ids } => {
            published.retain(|id, _| !channel_ids.contains(id));
            Ok(())
        }
    }
}

/// A client's message on one of its channels: `{"value": …}` set on the channel's port,
/// as `hwgw set` sets it; the client hears of a refusal.
async fn publish(
    shared: &Shared,
    published: &HashMap<u32, ClientChannel>,
    frame: &[u8],
) -> Result<(), String> {
    let (id, payload) = wire::client_message(frame).ok_or("not a message data frame")?;
    let channel = published
        .get(&id)
        .ok_or_else(|| format!("channel {id} was not advertised"))?;
    let refuse = |why: String| {
        shared
            .counters
            .writes_refused
            .fetch_add(1, Ordering::Relaxed);
        Err(why)
    };
    let Some(target) = shared.inputs.get(&channel.topic).cloned() else {
        return refuse(format!("{}: not an input this server takes", channel.topic));
    };
    let value = match serde_json::from_slice::<Value>(payload) {
        Ok(Value::Object(mut m)) if m.contains_key("value") => {
            m.remove("value").unwrap_or(Value::Null)
        }
        _ => return refuse(format!("{}: a message is {{\"value\": …}}", channel.topic)),
    };
    let control = shared.control.clone();
    let request =
        json!({"cmd": "set", "component": target.component, "port": target.port, "value": value});
    let done = tokio::task::spawn_blocking(move || control.request(request)).await;
    match done {
        Ok(Ok(_)) => {
            shared.counters.writes.fetch_add(1, Ordering::Relaxed);
            Ok(())
        }
        Ok(Err(e)) => refuse(format!("{}: {e}", channel.topic)),
        Err(e) => refuse(format!("{}: {e}", channel.topic)),
    }
}
