//! Gateway mode: requests from TCP masters for units that are not hwgw's own, forwarded to
//! a Modbus line (RTU, RTU over TCP, or another TCP unit) that hwgw's own cards poll.
//!
//! - Every line ([`LineIo`](crate::component::LineIo)) has a [`Forwarding`] queue,
//!   registered in its runtime's [`Lines`] by where the line goes; the server finds it
//!   there at each request (a card rebuilt by a reload brings a new line).
//! - The line stays one request at a time: between the polls of its own units (which come
//!   first when due) it sends the queued requests in their order of arrival. A master's
//!   connection has one request outstanding (the next is read after its reply), so the
//!   order of arrival takes every master in turn: no master starves another.
//! - The queue is bounded: a request that finds it full is answered 0x0A
//!   GatewayPathUnavailable, as is one for a line that is not running or cannot be opened.
//! - A request has `timeout` from its arrival: one still queued then is not sent; one
//!   whose target does not answer within it (or answers garbled) is answered 0x0B
//!   GatewayTargetDeviceFailedToRespond.
//! - The target's reply PDU (an exception too) goes back to the master as it came.

use crate::client::{Client, ClientError, Reply};
use crate::transport::Transport;
use serde::Deserialize;
use std::collections::VecDeque;
use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, Instant};

/// Why a forwarded request got no reply from its target.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Failed {
    /// The line's queue was full.
    Full,
    /// The line is not running (or there is none).
    Stopped,
    /// The line could not be opened before the request was sent.
    Transport,
    /// No reply within the timeout (or the request waited that long in the queue), or the
    /// connection broke after it was sent.
    Timeout,
    /// A reply that was not one (bad CRC, another unit's, too long).
    Garbled,
}

impl Failed {
    /// The exception answering it: 0x0A when there is no path to the target (full,
    /// stopped, broken), 0x0B when the target did not respond.
    pub fn exception(self) -> u8 {
        use crate::pdu::exception::{GATEWAY_PATH_UNAVAILABLE, GATEWAY_TARGET_FAILED_TO_RESPOND};
        match self {
            Failed::Full | Failed::Stopped | Failed::Transport => GATEWAY_PATH_UNAVAILABLE,
            Failed::Timeout | Failed::Garbled => GATEWAY_TARGET_FAILED_TO_RESPOND,
        }
    }
}

/// The reply PDU of a forwarded request, or why there is none.
pub type Outcome = Result<Vec<u8>, Failed>;

/// A request on its way to a line.
pub(crate) struct Forwarded {
    pub(crate) unit: u8,
    pub(crate) pdu: Vec<u8>,
    /// Not sent after this; answered 0x0B.
    pub(crate) deadline: Instant,
    pub(crate) reply: tokio::sync::oneshot::Sender<Outcome>,
}

/// A line's queue of forwarded requests.
#[derive(Default)]
pub struct Forwarding(Mutex<Queue>);

/// The queue, and the line's waker while it runs (one lock: a request is never queued
/// after the line closed).
#[derive(Default)]
struct Queue {
    waiting: VecDeque<Forwarded>,
    waker: Option<Arc<dyn rtt::activity::Waker>>,
}

impl Forwarded {
    /// Nobody waits for it any more: its master was answered (the server's own timeout)
    /// or is gone, or its time is up.
    fn abandoned(&self, now: Instant) -> bool {
        self.reply.is_closed() || now >= self.deadline
    }

    /// Answers it 0x0B if its time is up (a closed master hears nothing).
    fn expire(self) {
        let _ = self.reply.send(Err(Failed::Timeout));
    }
}

impl Forwarding {
    /// Queues `pdu` for `unit`, to be answered within `timeout` of now, if fewer than
    /// `capacity` requests wait (those whose time is up are answered first): the receiver
    /// of its outcome.
    pub fn submit(
        &self,
        unit: u8,
        pdu: &[u8],
        timeout: Duration,
        capacity: usize,
    ) -> Result<tokio::sync::oneshot::Receiver<Outcome>, Failed> {
        let (tx, rx) = tokio::sync::oneshot::channel();
        let now = Instant::now();
        let waker = {
            let mut q = rtt::lock(&self.0);
            let waker = q.waker.clone().ok_or(Failed::Stopped)?;
            if q.waiting.len() >= capacity {
                let (gone, kept): (VecDeque<_>, VecDeque<_>) =
                    q.waiting.drain(..).partition(|f| f.abandoned(now));
                q.waiting = kept;
                gone.into_iter().for_each(Forwarded::expire);
                if q.waiting.len() >= capacity {
                    return Err(Failed::Full);
                }
            }
            q.waiting.push_back(Forwarded {
                unit,
                pdu: pdu.to_vec(),
                deadline: now + timeout,
                reply: tx,
            });
            waker
        };
        waker.wake();
        Ok(rx)
    }

    /// The oldest request still awaited (those before it whose time is up are answered
    /// 0x0B, those nobody waits for dropped).
    pub(crate) fn take(&self) -> Option<Forwarded> {
        let now = Instant::now();
        let mut q = rtt::lock(&self.0);
        while let Some(f) = q.waiting.pop_front() {
            if !f.abandoned(now) {
                return Some(f);
            }
            f.expire();
        }
        None
    }

    /// True while a request waits.
    pub(crate) fn waiting(&self) -> bool {
        !rtt::lock(&self.0).waiting.is_empty()
    }

    /// The line runs: requests are taken, and `waker` wakes it for each.
    pub(crate) fn open(&self, waker: Arc<dyn rtt::activity::Waker>) {
        rtt::lock(&self.0).waker = Some(waker);
    }

    /// The line stopped: no request is taken, those waiting are answered 0x0A.
    pub(crate) fn close(&self) {
        let waiting: Vec<Forwarded> = {
            let mut q = rtt::lock(&self.0);
            q.waker = None;
            q.waiting.drain(..).collect()
        };
        for f in waiting {
            let _ = f.reply.send(Err(Failed::Stopped));
        }
    }
}

/// The lines of one runtime by where they go ([`rtt::Runtime::shared`]).
#[derive(Default)]
pub struct Lines(Mutex<Vec<(Transport, Weak<Forwarding>)>>);

impl Lines {
    /// Registers the line over `transport` (replacing one that went to the same place).
    pub fn register(&self, transport: &Transport, forwarding: &Arc<Forwarding>) {
        let mut v = rtt::lock(&self.0);
        v.retain(|(t, f)| f.strong_count() > 0 && !t.same_place(transport));
        v.push((transport.clone(), Arc::downgrade(forwarding)));
    }

    /// The line over `transport`, if one runs there with these settings; `Err` with the
    /// settings of one at the same place with others.
    pub fn find(&self, transport: &Transport) -> Result<Option<Arc<Forwarding>>, String> {
        let v = rtt::lock(&self.0);
        for (t, f) in v.iter() {
            if let Some(f) = f.upgrade()
                && t.same_place(transport)
            {
                if t != transport {
                    return Err(t.settings());
                }
                return Ok(Some(f));
            }
        }
        Ok(None)
    }
}

/// Where a server forwards requests for units that are not its own.
#[derive(Clone)]
pub struct Route {
    /// The unit ids forwarded (None: every one not the server's own, but 0).
    pub units: Option<Vec<u8>>,
    /// The line they go to (a Modbus card's).
    pub transport: Transport,
    /// From a request's arrival to its answer: then 0x0B.
    pub timeout: Duration,
    /// Requests waiting for the line at most: beyond, 0x0A.
    pub queue: usize,
    /// The lines of the runtime the server serves in.
    pub lines: Arc<Lines>,
}

impl std::fmt::Debug for Route {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Route")
            .field("units", &self.units)
            .field("transport", &self.transport)
            .field("timeout", &self.timeout)
            .field("queue", &self.queue)
            .finish_non_exhaustive()
    }
}

impl PartialEq for Route {
    fn eq(&self, o: &Route) -> bool {
        (&self.units, &self.transport, self.timeout, self.queue)
            == (&o.units, &o.transport, o.timeout, o.queue)
            && Arc::ptr_eq(&self.lines, &o.lines)
    }
}

impl Eq for Route {}

impl Route {
    /// Whether requests for `unit` take this route (never unit 0, the broadcast).
    pub fn takes(&self, unit: u8) -> bool {
        unit != 0 && self.units.as_ref().is_none_or(|u| u.contains(&unit))
    }

    /// Forwards `pdu` for `unit` on the route's line and waits for its outcome, at most the
    /// route's timeout (and a little, for the line to say so itself).
    pub async fn forward(&self, unit: u8, pdu: &[u8]) -> Outcome {
        let line = match self.lines.find(&self.transport) {
            Ok(Some(line)) => line,
            Ok(None) | Err(_) => return Err(Failed::Stopped),
        };
        let rx = line.submit(unit, pdu, self.timeout, self.queue)?;
        let grace = Duration::from_millis(100);
        match tokio::time::timeout(self.timeout + grace, rx).await {
            Ok(Ok(outcome)) => outcome,
            // The line dropped it: stopped.
            Ok(Err(_)) => Err(Failed::Stopped),
            Err(_) => Err(Failed::Timeout),
        }
    }
}

/// One gateway route: units forwarded to a line.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GatewayConfig {
    /// The unit ids forwarded (1-247); unset: every one not the server's own.
    #[serde(default)]
    pub units: Option<Vec<u8>>,
    /// The line, as a Modbus card's `transport` gives it: a card's line it must be.
    pub transport: crate::config::TransportConfig,
    /// From a request's arrival to its answer, ms: no reply by then is answered 0x0B
    /// (10-60000; default 1000).
    #[serde(default = "default_gateway_timeout_ms")]
    pub timeout_ms: u64,
    /// Requests waiting for the line at most; one more is answered 0x0A (1-4096; default
    /// 256).
    #[serde(default = "default_gateway_queue")]
    pub queue: usize,
}

fn default_gateway_timeout_ms() -> u64 {
    1000
}
fn default_gateway_queue() -> usize {
    256
}

impl GatewayConfig {
    /// The route over the lines of `lines`: (key under the route, message) when wrong.
    pub(crate) fn route(&self, lines: &Arc<Lines>) -> Result<Route, (String, String)> {
        let transport = self
            .transport
            .resolve()
            .map_err(|e| (e.key.unwrap_or_else(|| "transport".into()), e.message))?;
        if let Some(bad) = self
            .units
            .iter()
            .flatten()
            .find(|u| !(1..=247).contains(*u))
        {
            return Err(("units".into(), format!("{bad}: expected 1 to 247")));
        }
        if !(10..=60_000).contains(&self.timeout_ms) {
            return Err((
                "timeout_ms".into(),
                format!("{}: 10-60000 ms", self.timeout_ms),
            ));
        }
        if !(1..=4096).contains(&self.queue) {
            return Err(("queue".into(), format!("{}: 1-4096", self.queue)));
        }
        match lines.find(&transport) {
            Ok(Some(_)) => {}
            Ok(None) => {
                return Err((
                    "transport".into(),
                    format!(
                        "no Modbus card's line goes to {}: the gateway forwards on a card's line, one request at a time with its polls (a card with no points is the line alone)",
                        transport.describe()
                    ),
                ));
            }
            Err(settings) => {
                return Err((
                    "transport".into(),
                    format!(
                        "{} is a card's line with other settings ({settings}): give the card's transport",
                        transport.describe()
                    ),
                ));
            }
        }
        Ok(Route {
            units: self.units.clone(),
            transport,
            timeout: std::time::Duration::from_millis(self.timeout_ms),
            queue: self.queue,
            lines: lines.clone(),
        })
    }
}

/// Sends forwarded request `f` on the line (opening it if need be) and reads its reply,
/// within its deadline. A connection a timeout or a garbled reply left out of step is
/// dropped, as the line's own polls do.
pub(crate) async fn forward(
    ctx: &mut Option<Client>,
    transport: &Transport,
    f: &Forwarded,
) -> Outcome {
    let deadline = tokio::time::Instant::from_std(f.deadline);
    if tokio::time::Instant::now() >= deadline {
        return Err(Failed::Timeout);
    }
    if ctx.is_none() {
        // A line that cannot be opened in time is no path: 0x0A.
        match tokio::time::timeout_at(deadline, transport.open()).await {
            Ok(Ok(c)) => *ctx = Some(c),
            Ok(Err(_)) | Err(_) => return Err(Failed::Transport),
        }
    }
    let Some(c) = ctx.as_mut() else {
        return Err(Failed::Transport);
    };
    // Opening may have taken the time: a request is never sent once its master was
    // answered.
    if f.abandoned(Instant::now()) {
        return Err(Failed::Timeout);
    }
    let (mut out, mut stale) = (Vec::with_capacity(256), 0);
    let sent = tokio::time::timeout_at(deadline, c.request(f.unit, &f.pdu, &mut out, &mut stale));
    let rtu = transport.rtu_framed();
    // Sent, whatever went wrong after is the target's not answering: 0x0B.
    match sent.await {
        // A reply longer than a PDU may be (an RTU byte count of up to 255) is none.
        Ok(Ok(Reply::Pdu)) if out.len() > MAX_PDU => Err(Failed::Garbled),
        Ok(Ok(Reply::Pdu)) => Ok(out),
        Ok(Ok(Reply::Exception(code))) => Ok(vec![f.pdu[0] | 0x80, code]),
        // Unit 0 is never forwarded; a broadcast has no reply to give.
        Ok(Ok(Reply::Broadcast)) => Err(Failed::Garbled),
        Ok(Err(ClientError::Io(_))) => {
            *ctx = None;
            Err(Failed::Timeout)
        }
        Ok(Err(ClientError::Bad(_))) => {
            if rtu {
                *ctx = None;
            }
            Err(Failed::Garbled)
        }
        Err(_) => {
            if rtu || c.out_of_step() {
                *ctx = None;
            }
            Err(Failed::Timeout)
        }
    }
}

/// The longest PDU (a Modbus TCP frame's 253 bytes).
const MAX_PDU: usize = 253;
