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
    /// What a client must bring to publish (`?token=` or `Authorization: Bearer`).
    pub token: Option<String>,
    /// Pages of these origins may connect (a browser names the page; a program does not).
    pub origins: Vec<String>,
    /// Host names it answers to besides addresses and `localhost`.
    pub hosts: Vec<String>,
    /// What writes wait for the gateway in.
    pub pool: crate::guard::Blocking,
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
            token: None,
            origins: Vec::new(),
            hosts: Vec::new(),
            pool: crate::guard::Blocking::new(),
            queue: 32,
            max_message: 64 * 1024,
            counters: Counters::default(),
            next_client: AtomicU64::new(1),
        }
    }
}

/// What a handshake found: may the client publish.
#[derive(Default)]
struct Admitted {
    writes: std::sync::atomic::AtomicBool,
}

/// The handshake's answer to `req`: the Foxglove subprotocol chosen, or the refusal (not a
/// Foxglove client, a host the server does not answer to, a page of a site not listed in
/// `origins`); whether it brought the token is left in `admitted`.
#[allow(
    clippy::result_large_err,
    reason = "tungstenite's handshake callback has this signature"
)]
fn handshake(
    shared: &Shared,
    admitted: &Admitted,
    req: &Request,
    mut resp: Response,
) -> Result<Response, ErrorResponse> {
    let refuse = |status: hyper::StatusCode, why: &str| {
        let mut e = ErrorResponse::new(Some(format!("{why}\n")));
        *e.status_mut() = status;
        e
    };
    let header = |name: &str| req.headers().get(name).and_then(|v| v.to_str().ok());
    if !crate::guard::host_allowed(header("host"), &shared.hosts) {
        return Err(refuse(
            hyper::StatusCode::MISDIRECTED_REQUEST,
            "this server answers to its address, localhost and its configured hosts",
        ));
    }
    // A browser says which page opened the connection; a program says nothing.
    if let Some(origin) = header("origin")
        && !shared.origins.iter().any(|o| o == origin)
    {
        return Err(refuse(
            hyper::StatusCode::FORBIDDEN,
            "a page of this origin may not connect (origins = [...] lists those that may)",
        ));
    }
    let offered = req
        .headers()
        .get_all("sec-websocket-protocol")
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .map(str::trim)
        .find(|p| wire::SUBPROTOCOLS.contains(p));
    let Some(chosen) = offered.and_then(|p| p.parse().ok()) else {
        return Err(refuse(
            hyper::StatusCode::BAD_REQUEST,
            "a Foxglove client: Sec-WebSocket-Protocol foxglove.websocket.v1",
        ));
    };
    resp.headers_mut().insert("sec-websocket-protocol", chosen);
    if let Some(token) = &shared.token {
        let bearer = header("authorization").and_then(|v| v.strip_prefix("Bearer "));
        let query = req.uri().query().into_iter().flat_map(|q| q.split('&'));
        let given = bearer
            .into_iter()
            .chain(query.filter_map(|kv| kv.strip_prefix("token=")));
        let matches = given
            .into_iter()
            .any(|g| crate::guard::same(g.as_bytes(), token.as_bytes()));
        admitted.writes.store(matches, Ordering::Relaxed);
    }
    Ok(resp)
}

/// Takes a client out of the hub however its connection ends (closed, or aborted at
/// the server's stop).
struct Leave<'a>(&'a Hub, u64);

impl Drop for Leave<'_> {
    fn drop(&mut self) {
        self.0.leave(self.1);
    }
}

/// Serves one connection until it ends.
pub async fn serve(shared: Arc<Shared>, conn: crate::http::Conn) {
    let peer = conn
        .get_ref()
        .peer_addr()
        .map(|a| a.to_string())
        .unwrap_or_default();
    let config = WebSocketConfig::default()
        .max_message_size(Some(shared.max_message))
        .max_frame_size(Some(shared.max_message));
    let admitted = Admitted::default();
    #[allow(
        clippy::result_large_err,
        reason = "tungstenite's handshake callback has this signature"
    )]
    let pick = |req: &Request, resp: Response| handshake(&shared, &admitted, req, resp);
    let accepting = tokio_tungstenite::accept_hdr_async_with_config(conn, pick, Some(config));
    let ws = match tokio::time::timeout(HANDSHAKE, accepting).await {
        Ok(Ok(ws)) => ws,
        _ => {
            let refused = &shared.counters.handshakes_refused;
            refused.fetch_add(1, Ordering::Relaxed);
            return;
        }
    };
    let writes = admitted.writes.load(Ordering::Relaxed) && !shared.inputs.is_empty();
    let (mut sink, mut stream) = ws.split();
    let (tx, mut rx) = mpsc::channel(shared.queue);
    let client = Arc::new(Client {
        id: shared.next_client.fetch_add(1, Ordering::Relaxed),
        peer,
        tx,
        subscriptions: Default::default(),
        sent: AtomicU64::new(0),
        dropped: AtomicU64::new(0),
        queued_bytes: Default::default(),
    });
    client.tell(wire::server_info(&shared.name, writes, &shared.session));
    let _leave = Leave(&shared.hub, client.id);
    // Joined with the channels of the moment: a stream that begins later tells it anew.
    let channels = shared.hub.join(client.clone());
    if !channels.list.is_empty() {
        client.tell(wire::advertise(&channels.list));
    }
    let writer = async {
        while let Some(out) = rx.recv().await {
            let sent = match out {
                Out::Text(t) => sink.send(Message::text(t)).await,
                Out::Frames(frames, bytes) => {
                    let mut r = Ok(());
                    for f in frames {
                        r = sink.feed(Message::binary(f)).await;
                        if r.is_err() {
                            break;
                        }
                    }
                    client.queued_bytes.fetch_sub(bytes, Ordering::Relaxed);
                    if r.is_ok() { sink.flush().await } else { r }
                }
            };
            if sent.is_err() {
                break;
            }
        }
        let _ = sink.close().await;
    };
    let reader = read(&shared, &client, writes, &mut stream);
    tokio::select! {
        () = writer => {}
        () = reader => {}
    }
}

/// The client's messages until it goes, misbehaves or cannot be told.
async fn read<S>(shared: &Shared, client: &Client, writes: bool, stream: &mut S)
where
    S: futures_util::Stream<Item = Result<Message, tokio_tungstenite::tungstenite::Error>> + Unpin,
{
    let mut bad = 0u64;
    let mut published: HashMap<u32, ClientChannel> = HashMap::new();
    while let Some(m) = stream.next().await {
        let outcome = match m {
            Ok(Message::Text(t)) => op(shared, client, writes, &mut published, t.as_str()),
            Ok(Message::Binary(b)) => publish(shared, client, &published, &b).await,
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
    writes: bool,
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
            if !writes {
                let refused = &shared.counters.writes_refused;
                refused.fetch_add(1, Ordering::Relaxed);
                return Err("publishing needs the deployment's token: connect to \
                            ws://HOST:PORT/?token=TOKEN"
                    .into());
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

/// A client's message on one of its channels: `{"value": …}` set on the channel's input,
/// as `hwgw set` sets it, one at a time. A frame that is not the protocol is the caller's
/// error; a write refused (by the gateway, or not `{"value": …}`) is told to the client
/// here and counted, but is no misbehaviour.
async fn publish(
    shared: &Shared,
    client: &Client,
    published: &HashMap<u32, ClientChannel>,
    frame: &[u8],
) -> Result<(), String> {
    let (id, payload) = wire::client_message(frame).ok_or("not a message data frame")?;
    let channel = published
        .get(&id)
        .ok_or_else(|| format!("channel {id} was not advertised"))?;
    let target = shared
        .inputs
        .get(&channel.topic)
        .cloned()
        .ok_or_else(|| format!("{}: not an input this server takes", channel.topic))?;
    let refused = |why: String| {
        shared
            .counters
            .writes_refused
            .fetch_add(1, Ordering::Relaxed);
        client.tell(wire::status(Level::Error, &why));
        Ok(())
    };
    let value = match serde_json::from_slice::<Value>(payload) {
        Ok(Value::Object(mut m)) if m.contains_key("value") => {
            m.remove("value").unwrap_or(Value::Null)
        }
        _ => return refused(format!("{}: a message is {{\"value\": …}}", channel.topic)),
    };
    let control = shared.control.clone();
    let request =
        json!({"cmd": "set", "component": target.component, "port": target.port, "value": value});
    match shared.pool.run(move || control.request(request)).await {
        Some(Ok(_)) => {
            shared.counters.writes.fetch_add(1, Ordering::Relaxed);
            Ok(())
        }
        Some(Err(e)) => refused(format!("{}: {e}", channel.topic)),
        None => refused(format!(
            "{}: the write could not be carried out",
            channel.topic
        )),
    }
}
