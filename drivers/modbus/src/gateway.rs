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
    /// The line could not be opened, or broke.
    Transport,
    /// No reply within the timeout (or the request waited that long in the queue).
    Timeout,
    /// A reply that was not one (bad CRC, another unit's).
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
pub struct Forwarding {
    queue: Mutex<VecDeque<Forwarded>>,
    /// Wakes the line's activity (set while it runs).
    waker: Mutex<Option<Arc<dyn rtt::activity::Waker>>>,
}

impl Forwarding {
    /// Queues `pdu` for `unit`, to be answered within `timeout` of now, if fewer than
    /// `capacity` requests wait: the receiver of its outcome.
    pub fn submit(
        &self,
        unit: u8,
        pdu: &[u8],
        timeout: Duration,
        capacity: usize,
    ) -> Result<tokio::sync::oneshot::Receiver<Outcome>, Failed> {
        let waker = rtt::lock(&self.waker).clone().ok_or(Failed::Stopped)?;
        let (tx, rx) = tokio::sync::oneshot::channel();
        {
            let mut q = rtt::lock(&self.queue);
            if q.len() >= capacity {
                return Err(Failed::Full);
            }
            q.push_back(Forwarded {
                unit,
                pdu: pdu.to_vec(),
                deadline: Instant::now() + timeout,
                reply: tx,
            });
        }
        waker.wake();
        Ok(rx)
    }

    /// The oldest request waiting.
    pub(crate) fn take(&self) -> Option<Forwarded> {
        rtt::lock(&self.queue).pop_front()
    }

    /// True while a request waits.
    pub(crate) fn waiting(&self) -> bool {
        !rtt::lock(&self.queue).is_empty()
    }

    /// The line runs: requests are taken, and `waker` wakes it for each.
    pub(crate) fn open(&self, waker: Arc<dyn rtt::activity::Waker>) {
        *rtt::lock(&self.waker) = Some(waker);
    }

    /// The line stopped: no request is taken, those waiting are answered 0x0A.
    pub(crate) fn close(&self) {
        *rtt::lock(&self.waker) = None;
        let waiting: Vec<Forwarded> = rtt::lock(&self.queue).drain(..).collect();
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
        match tokio::time::timeout_at(deadline, transport.open()).await {
            Ok(Ok(c)) => *ctx = Some(c),
            Ok(Err(_)) => return Err(Failed::Transport),
            Err(_) => return Err(Failed::Timeout),
        }
    }
    let Some(c) = ctx.as_mut() else {
        return Err(Failed::Transport);
    };
    let (mut out, mut stale) = (Vec::with_capacity(256), 0);
    let sent = tokio::time::timeout_at(deadline, c.request(f.unit, &f.pdu, &mut out, &mut stale));
    let rtu = transport.rtu_framed();
    match sent.await {
        Ok(Ok(Reply::Pdu)) => Ok(out),
        Ok(Ok(Reply::Exception(code))) => Ok(vec![f.pdu[0] | 0x80, code]),
        // Unit 0 is never forwarded; a broadcast has no reply to give.
        Ok(Ok(Reply::Broadcast)) => Err(Failed::Garbled),
        Ok(Err(ClientError::Io(_))) => {
            *ctx = None;
            Err(Failed::Transport)
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
