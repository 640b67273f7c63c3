//! Writes from the broker: a Sparkplug DCMD's metrics or a JSON `set` message, checked
//! whole before anything is written (every metric known, an output, of its type, in its
//! range: a command with one bad metric writes none), then carried out one by one by a
//! thread of its own through the gateway's `set` — the checks and output policy `hwgw
//! set` passes, waiting as it does for a bus that delivers later — so the connection
//! never waits for a device. What became of each command is reported back: a refusal to
//! the Sparkplug host as the node's `hwgw/Last Refusal` metric, to a JSON writer on the
//! set topic's `/result`.

use crate::model::{Group, Metric, Value};
use crate::sparkplug::Write;
use driver_api::ControlLink;
use serde_json::json;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};

/// Who asked, to tell them what became of it.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Origin {
    /// A Sparkplug DCMD to this device.
    Sparkplug(String),
    /// A JSON set topic.
    Json(String),
}

/// A checked command: the writes (`component`, `port`, value) to carry out in order.
#[derive(Debug, Clone)]
pub(crate) struct Job {
    pub origin: Origin,
    pub writes: Vec<(String, String, serde_json::Value)>,
}

/// What became of a command.
#[derive(Debug, Clone)]
pub(crate) struct Outcome {
    pub origin: Origin,
    /// `Err(why)` when refused or failed.
    pub result: Result<(), String>,
}

/// Commands waiting for the worker.
pub(crate) const QUEUE: usize = 64;
/// Outcomes waiting to be published (older ones are dropped, counted).
const OUTCOMES: usize = 256;

/// The command counters and outcomes, shared by the session and the worker.
#[derive(Default)]
pub(crate) struct Book {
    pub accepted: AtomicU64,
    pub refused: AtomicU64,
    pub outcomes: Mutex<VecDeque<Outcome>>,
    pub outcomes_lost: AtomicU64,
    pub last_refusal: Mutex<String>,
}

impl Book {
    /// Records `o` and keeps it for publishing.
    pub(crate) fn record(&self, o: Outcome) {
        match &o.result {
            Ok(()) => self.accepted.fetch_add(1, Ordering::Relaxed),
            Err(why) => {
                let what = match &o.origin {
                    Origin::Sparkplug(d) => format!("DCMD {d}: {why}"),
                    Origin::Json(t) => format!("{t}: {why}"),
                };
                tracing::warn!("MQTT command refused: {what}");
                *rtt::lock(&self.last_refusal) = what;
                self.refused.fetch_add(1, Ordering::Relaxed)
            }
        };
        let mut q = rtt::lock(&self.outcomes);
        if q.len() >= OUTCOMES {
            q.pop_front();
            self.outcomes_lost.fetch_add(1, Ordering::Relaxed);
        }
        q.push_back(o);
    }

    /// Hands `job` to the worker, or refuses it when the worker is `QUEUE` behind.
    pub(crate) fn submit(&self, tx: &SyncSender<Job>, job: Job) {
        let origin = job.origin.clone();
        let why = match tx.try_send(job) {
            Ok(()) => return,
            Err(TrySendError::Full(_)) => format!("{QUEUE} commands are waiting: refused"),
            Err(TrySendError::Disconnected(_)) => "hwgw is stopping".into(),
        };
        self.record(Outcome {
            origin,
            result: Err(why),
        });
    }
}

/// Carries out jobs until the channel closes.
pub(crate) fn worker(rx: Receiver<Job>, control: ControlLink, book: Arc<Book>) {
    for job in rx {
        let mut result = Ok(());
        for (i, (component, port, value)) in job.writes.iter().enumerate() {
            let request =
                json!({"cmd": "set", "component": component, "port": port, "value": value});
            if let Err(e) = control.request(request) {
                let applied = if i == 0 {
                    "nothing written".to_string()
                } else {
                    let done: Vec<_> = job.writes[..i]
                        .iter()
                        .map(|(c, p, _)| format!("{c}.{p}"))
                        .collect();
                    format!("written before it: {}", done.join(", "))
                };
                result = Err(format!("{component}.{port}: {}; {applied}", e.message));
                break;
            }
        }
        book.record(Outcome {
            origin: job.origin,
            result,
        });
    }
}

/// `v` as `hwgw set` takes it for metric `m`, or why it is refused.
fn checked(m: &Metric, v: Value) -> Result<serde_json::Value, String> {
    let name = m.address();
    if !m.output {
        return Err(format!("{name} is an input: it cannot be written"));
    }
    match (m.range, v) {
        (Some(r), Value::F64(_) | Value::I64(_)) => {
            let x = match v {
                Value::F64(x) => x,
                Value::I64(i) if (i as f64) as i64 == i && i.unsigned_abs() <= 1 << 53 => i as f64,
                _ => return Err(format!("{name}: {v:?} is not exact as a double")),
            };
            if !(x.is_finite() && r.lowest <= x && x <= r.highest) {
                return Err(format!("{name}: {x} is out of its range {r}"));
            }
            serde_json::Number::from_f64(x)
                .map(Into::into)
                .ok_or_else(|| format!("{name}: {x} is not a number"))
        }
        (None, Value::Bool(b)) => Ok(b.into()),
        (Some(_), Value::Bool(_)) => Err(format!(
            "{name} is analog: a boolean cannot be written to it"
        )),
        (None, _) => Err(format!("{name} is digital: write a boolean")),
    }
}

/// A DCMD to `device` checked whole, or why it is refused (nothing written).
pub(crate) fn dcmd(
    groups: &[Group],
    device: &str,
    writes: &[Write],
    allowed: bool,
) -> Result<Job, String> {
    if !allowed {
        return Err("writes are not allowed (allow_writes = false)".into());
    }
    let Some(g) = groups.iter().find(|g| g.id == device) else {
        let ids: Vec<_> = groups.iter().map(|g| g.id.as_str()).collect();
        return Err(format!(
            "no device {device:?}; the devices: {}",
            ids.join(", ")
        ));
    };
    if writes.is_empty() {
        return Err("no metrics in it".into());
    }
    let mut out: Vec<(String, String, serde_json::Value)> = Vec::new();
    for w in writes {
        let m = g.metrics.iter().find(|m| match (&w.name, w.alias) {
            (Some(n), _) => &m.name == n,
            (None, Some(a)) => m.alias == a,
            (None, None) => false,
        });
        let Some(m) = m else {
            let what = w
                .name
                .clone()
                .unwrap_or_else(|| format!("alias {:?}", w.alias));
            return Err(format!("{device} has no metric {what:?}"));
        };
        let v = w
            .value
            .ok_or_else(|| format!("{}: no value, or a kind hwgw does not write", m.name))?;
        let value = checked(m, v)?;
        if out
            .iter()
            .any(|(c, p, _)| c == &m.component && p == &m.port)
        {
            return Err(format!("{} is written twice", m.name));
        }
        out.push((m.component.clone(), m.port.clone(), value));
    }
    Ok(Job {
        origin: Origin::Sparkplug(device.into()),
        writes: out,
    })
}

/// A JSON `set` message on `topic` (`PREFIX/COMPONENT/PORT/set`) checked, or why it is
/// refused: its payload is `{"value": V}` or `V`.
pub(crate) fn json_set(
    groups: &[Group],
    prefix: &str,
    topic: &str,
    payload: &[u8],
    allowed: bool,
) -> Result<Job, String> {
    let address = topic
        .strip_prefix(prefix)
        .and_then(|t| t.strip_prefix('/'))
        .and_then(|t| t.strip_suffix("/set"))
        .and_then(|t| t.split_once('/'))
        .ok_or_else(|| "not a set topic (PREFIX/COMPONENT/PORT/set)".to_string())?;
    if !allowed {
        return Err("writes are not allowed (allow_writes = false)".into());
    }
    let m = groups
        .iter()
        .flat_map(|g| &g.metrics)
        .find(|m| m.component == address.0 && m.port == address.1)
        .ok_or_else(|| format!("no channel {}.{}", address.0, address.1))?;
    let v: serde_json::Value =
        serde_json::from_slice(payload).map_err(|e| format!("not JSON: {e}"))?;
    let v = match v {
        serde_json::Value::Object(mut o) if o.len() == 1 && o.contains_key("value") => {
            o.remove("value").unwrap_or_default()
        }
        serde_json::Value::Object(_) => return Err("an object must be {\"value\": V}".into()),
        v => v,
    };
    let v = match v {
        serde_json::Value::Bool(b) => Value::Bool(b),
        serde_json::Value::Number(n) => match (n.as_i64(), n.as_f64()) {
            (Some(i), _) => Value::I64(i),
            (None, Some(f)) => Value::F64(f),
            _ => return Err(format!("{n} is out of range")),
        },
        other => return Err(format!("{other} is neither a number nor a boolean")),
    };
    let value = checked(m, v)?;
    Ok(Job {
        origin: Origin::Json(topic.into()),
        writes: vec![(m.component.clone(), m.port.clone(), value)],
    })
}
