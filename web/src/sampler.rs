//! The live values of a page: one reader per server reads the listed ports (`get`, as
//! `hwgw get` does) every sample period while anyone listens, and hands each change to
//! every live stream as a Server-Sent Event. A stream holds a few events; one that is not
//! read loses the newer ones (counted), and never slows the reader or the gateway.

use crate::config::PortRef;
use crate::http::Body;
use bytes::Bytes;
use driver_api::ControlLink;
use http_body::Frame;
use serde_json::{Map, Value, json};
use std::convert::Infallible;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::sync::mpsc;

/// Events a stream holds for its client before it loses the newer ones.
const QUEUE: usize = 16;

/// A comment line that keeps an idle stream open, and finds a client that left.
const KEEP_ALIVE: Duration = Duration::from_secs(10);

/// Sends in a row a stream may find full before it is ended (at 10 Hz, 5 s).
const FULL_LIMIT: u32 = 50;

/// The streams of a server and what they lost.
#[derive(Default)]
pub(crate) struct Streams {
    /// Each stream, with how many sends in a row found it full.
    clients: Mutex<Vec<(mpsc::Sender<Bytes>, u32)>>,
    /// Streams ended for not being read.
    pub(crate) ended_slow: AtomicU64,
    /// Events not delivered because a client's queue was full.
    pub(crate) dropped: AtomicU64,
    /// Events sent.
    pub(crate) sent: AtomicU64,
    /// The last event, for a stream that begins.
    last: Mutex<Option<Bytes>>,
}

impl Streams {
    /// A new stream: a body that yields events until the client leaves, beginning with
    /// the last values read.
    pub(crate) fn subscribe(&self) -> Body {
        let (tx, rx) = mpsc::channel(QUEUE);
        if let Some(last) = rtt::lock(&self.last).clone() {
            let _ = tx.try_send(last);
        }
        rtt::lock(&self.clients).push((tx, 0));
        http_body_util::BodyExt::boxed(Events(rx))
    }

    /// How many streams are open.
    pub(crate) fn listeners(&self) -> usize {
        let mut clients = rtt::lock(&self.clients);
        clients.retain(|(c, _)| !c.is_closed());
        clients.len()
    }

    /// `event` to every stream; a full one loses it (counted) and, full too often in a
    /// row, is ended; a closed one is let go.
    fn send(&self, event: Bytes) {
        let mut clients = rtt::lock(&self.clients);
        clients.retain_mut(|(c, full)| match c.try_send(event.clone()) {
            Ok(()) => {
                self.sent.fetch_add(1, Ordering::Relaxed);
                *full = 0;
                true
            }
            Err(mpsc::error::TrySendError::Full(_)) => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
                *full += 1;
                let keep = *full < FULL_LIMIT;
                if !keep {
                    self.ended_slow.fetch_add(1, Ordering::Relaxed);
                }
                keep
            }
            Err(mpsc::error::TrySendError::Closed(_)) => false,
        });
    }
}

/// A stream's body: its queued events.
struct Events(mpsc::Receiver<Bytes>);

impl http_body::Body for Events {
    type Data = Bytes;
    type Error = Infallible;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Infallible>>> {
        self.0.poll_recv(cx).map(|e| e.map(|b| Ok(Frame::data(b))))
    }
}

/// Reads `ports` through `control` every `period` while a stream is open, and sends
/// every change to `streams`; runs until the runtime ends.
pub(crate) async fn run(
    control: ControlLink,
    ports: Arc<Vec<PortRef>>,
    period: Duration,
    streams: Arc<Streams>,
) {
    let mut tick = tokio::time::interval(period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut previous = Value::Null;
    let mut quiet = tokio::time::Instant::now();
    loop {
        tick.tick().await;
        if streams.listeners() == 0 {
            continue;
        }
        let (c, p) = (control.clone(), ports.clone());
        let Ok(values) = tokio::task::spawn_blocking(move || read(&c, &p)).await else {
            continue;
        };
        if values != previous {
            let event = format!("data: {}\n\n", json!({ "values": values }));
            let event = Bytes::from(event);
            *rtt::lock(&streams.last) = Some(event.clone());
            streams.send(event);
            previous = values;
            quiet = tokio::time::Instant::now();
        } else if quiet.elapsed() >= KEEP_ALIVE {
            streams.send(Bytes::from_static(b": alive\n\n"));
            quiet = tokio::time::Instant::now();
        }
    }
}

/// Every port's value now: `{"component.port": value}`, or `{"error": …}` for one that
/// could not be read.
pub(crate) fn read(control: &ControlLink, ports: &[PortRef]) -> Value {
    let mut out = Map::new();
    for p in ports {
        let request = json!({"cmd": "get", "component": p.component, "port": p.port});
        let v = match control.request(request) {
            Ok(v) => v,
            Err(e) => json!({ "error": e.to_string() }),
        };
        out.insert(p.name(), v);
    }
    Value::Object(out)
}
