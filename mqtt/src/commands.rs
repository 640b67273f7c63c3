//! Writes from the broker: a Sparkplug DCMD's metrics or a JSON `set` message, checked
//! whole before anything is written — every metric known, an output, of its type, in its
//! range, its IO component running and its device not offline: a command with one bad
//! metric writes none — then carried out one by one by a thread of its own through the
//! gateway's `set` — the checks and output policy `hwgw set` passes, waiting as it does
//! for a bus that delivers later — so the connection never waits for a device. What
//! became of each command is reported back: a refusal to the Sparkplug host as the node's
//! `hwgw/Last Refusal` metric, to a JSON writer on the set topic's `/result`. A retained
//! command is refused: a broker hands it to every new session, and hwgw would write an
//! old value again on each reconnection.

use crate::model::{Group, Kind, Metric, Value};
use crate::sparkplug::Write;
use device_interface::Status;
use device_interface::text::Number;
use driver_api::ControlLink;
use serde_json::json;
use std::collections::{HashSet, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Why a command was refused or failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub(crate) enum Refusal {
    #[error("writes are not allowed (allow_writes = false)")]
    NotAllowed,
    #[error("a retained command is not carried out (it would be again at every connection)")]
    Retained,
    #[error("not a Sparkplug B payload: {0}")]
    NotSparkplug(String),
    #[error("not JSON: {0}")]
    NotJson(String),
    #[error("an object must be {{\"value\": V}}")]
    NotValueObject,
    #[error("{0} is neither a number nor a boolean")]
    NotAValue(String),
    #[error("not a set topic (PREFIX/COMPONENT/PORT/set)")]
    NotSetTopic,
    #[error("no device {device:?}; the devices: {devices}")]
    NoDevice { device: String, devices: String },
    #[error("no metrics in it")]
    Empty,
    #[error("{count} metrics: {device} has {has}")]
    TooMany {
        device: String,
        count: usize,
        has: usize,
    },
    #[error("{device} has no metric {metric:?}")]
    NoMetric { device: String, metric: String },
    #[error("no channel {0}")]
    NoChannel(String),
    #[error("{0}: no value, or a kind hwgw does not write")]
    NoValue(String),
    #[error("{0} is an input: it cannot be written")]
    Input(String),
    #[error("{0} is analog: write a number")]
    Analog(String),
    #[error("{0} is digital: write a boolean")]
    Digital(String),
    #[error("{channel}: {value} is not exact as a double")]
    NotExact { channel: String, value: i64 },
    #[error("{channel}: {value} is out of its range {range}")]
    OutOfRange {
        channel: String,
        value: Number,
        range: String,
    },
    #[error("{0} is written twice")]
    Twice(String),
    #[error("{0} is not running")]
    NotRunning(String),
    #[error("{0}: its device is offline")]
    Offline(String),
    #[error("{QUEUE} commands are waiting: refused")]
    Busy,
    #[error("hwgw is stopping: nothing written")]
    Stopping,
    #[error("{channel}: {why}; {applied}")]
    Failed {
        channel: String,
        why: String,
        applied: String,
    },
}

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
    pub result: Result<(), Refusal>,
}

/// Commands waiting for the worker.
pub(crate) const QUEUE: usize = 64;
/// Outcomes waiting to be published (older ones are dropped, counted).
const OUTCOMES: usize = 256;
/// The longest refusal kept (what a peer sent is in it).
const REFUSAL_CHARS: usize = 200;
/// Refusals logged at most this often.
const LOG_EVERY: Duration = Duration::from_secs(1);

/// The command counters and outcomes, shared by the session and the worker.
#[derive(Default)]
pub(crate) struct Book {
    pub accepted: AtomicU64,
    pub refused: AtomicU64,
    pub outcomes: Mutex<VecDeque<Outcome>>,
    pub outcomes_lost: AtomicU64,
    pub last_refusal: Mutex<String>,
    /// Set at stop: commands not begun are refused.
    pub stopping: AtomicBool,
    logged: Mutex<Option<Instant>>,
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
                let what: String = what.chars().take(REFUSAL_CHARS).collect();
                let mut logged = rtt::lock(&self.logged);
                if logged.is_none_or(|t| t.elapsed() >= LOG_EVERY) {
                    *logged = Some(Instant::now());
                    tracing::warn!("MQTT command refused: {what} (at most one logged a second)");
                }
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
            Err(TrySendError::Full(_)) => Refusal::Busy,
            Err(TrySendError::Disconnected(_)) => Refusal::Stopping,
        };
        self.record(Outcome {
            origin,
            result: Err(why),
        });
    }
}

/// Carries out jobs until the channel closes; once stopping, refuses those not begun.
pub(crate) fn worker(rx: Receiver<Job>, control: ControlLink, book: Arc<Book>) {
    for job in rx {
        let result = carry_out(&job, &control, &book);
        book.record(Outcome {
            origin: job.origin,
            result,
        });
    }
}

fn carry_out(job: &Job, control: &ControlLink, book: &Book) -> Result<(), Refusal> {
    // A command begun is carried out whole (stop waits for it); one not begun is not.
    if book.stopping.load(Ordering::Acquire) {
        return Err(Refusal::Stopping);
    }
    for (i, (component, port, value)) in job.writes.iter().enumerate() {
        let request = json!({"cmd": "set", "component": component, "port": port, "value": value});
        if let Err(e) = control.request(request) {
            return Err(failed(job, i, e.message));
        }
    }
    Ok(())
}

/// Write `i` of `job` failed: why, and which writes were made before it.
fn failed(job: &Job, i: usize, why: String) -> Refusal {
    let (component, port, _) = &job.writes[i];
    let applied = if i == 0 {
        "nothing written".to_string()
    } else {
        let done: Vec<_> = job.writes[..i]
            .iter()
            .map(|(c, p, _)| format!("{c}.{p}"))
            .collect();
        format!("written before it: {}", done.join(", "))
    };
    Refusal::Failed {
        channel: format!("{component}.{port}"),
        why,
        applied,
    }
}

/// `v` as `hwgw set` takes it for metric `m` of a device whose status is `status`, or
/// why it is refused.
fn checked(m: &Metric, v: Value, status: Status) -> Result<serde_json::Value, Refusal> {
    let name = m.address();
    let value = match (m.kind, v) {
        (Kind::AnalogOut, Value::F64(x)) => analog(m, x)?,
        (Kind::AnalogOut, Value::I64(i)) => {
            if i.unsigned_abs() > 1 << 53 {
                return Err(Refusal::NotExact {
                    channel: name,
                    value: i,
                });
            }
            analog(m, i as f64)?
        }
        (Kind::AnalogOut, Value::Bool(_)) => return Err(Refusal::Analog(name)),
        (Kind::DigitalOut, Value::Bool(b)) => b.into(),
        (Kind::DigitalOut, _) => return Err(Refusal::Digital(name)),
        (Kind::Input, _) => return Err(Refusal::Input(name)),
    };
    if !m
        .task
        .as_ref()
        .is_some_and(|t| t.state() == rtt::TaskState::Running)
    {
        return Err(Refusal::NotRunning(m.component.clone()));
    }
    if status == Status::Offline {
        return Err(Refusal::Offline(name));
    }
    Ok(value)
}

/// An analog output's value, in its range.
fn analog(m: &Metric, x: f64) -> Result<serde_json::Value, Refusal> {
    let range = m.range.map_or_else(|| "unknown".into(), |r| r.to_string());
    let inside = m.range.is_some_and(|r| r.lowest <= x && x <= r.highest);
    match serde_json::Number::from_f64(x) {
        Some(n) if inside => Ok(n.into()),
        _ => Err(Refusal::OutOfRange {
            channel: m.address(),
            value: Number(x),
            range,
        }),
    }
}

/// A DCMD to `device` checked whole, or why it is refused (nothing written). `statuses`
/// are the group's devices' now.
pub(crate) fn dcmd(
    groups: &[Group],
    device: &str,
    writes: &[Write],
    statuses: impl Fn(&Group) -> Vec<Status>,
) -> Result<Job, Refusal> {
    let Some(g) = groups.iter().find(|g| g.id == device) else {
        let ids: Vec<_> = groups.iter().map(|g| g.id.as_str()).collect();
        return Err(Refusal::NoDevice {
            device: device.into(),
            devices: ids.join(", "),
        });
    };
    if writes.is_empty() {
        return Err(Refusal::Empty);
    }
    if writes.len() > g.metrics.len() {
        return Err(Refusal::TooMany {
            device: device.into(),
            count: writes.len(),
            has: g.metrics.len(),
        });
    }
    let statuses = statuses(g);
    let mut out = Vec::with_capacity(writes.len());
    let mut seen = HashSet::new();
    for w in writes {
        let found = match (&w.name, w.alias) {
            (Some(n), _) => g.by_name(n),
            (None, Some(a)) => g.by_alias(a),
            (None, None) => None,
        };
        let Some(i) = found else {
            let what = w
                .name
                .clone()
                .unwrap_or_else(|| format!("alias {:?}", w.alias));
            return Err(Refusal::NoMetric {
                device: device.into(),
                metric: what,
            });
        };
        let m = &g.metrics[i];
        let v = w.value.ok_or_else(|| Refusal::NoValue(m.name.clone()))?;
        let value = checked(m, v, statuses[m.device])?;
        if !seen.insert(i) {
            return Err(Refusal::Twice(m.name.clone()));
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
    statuses: impl Fn(&Group) -> Vec<Status>,
) -> Result<Job, Refusal> {
    let (component, port) = topic
        .strip_prefix(prefix)
        .and_then(|t| t.strip_prefix('/'))
        .and_then(|t| t.strip_suffix("/set"))
        .and_then(|t| t.split_once('/'))
        .ok_or(Refusal::NotSetTopic)?;
    let (g, m) = groups
        .iter()
        .find_map(|g| {
            let m = g
                .metrics
                .iter()
                .find(|m| m.component == component && m.port == port)?;
            Some((g, m))
        })
        .ok_or_else(|| Refusal::NoChannel(format!("{component}.{port}")))?;
    let v: serde_json::Value =
        serde_json::from_slice(payload).map_err(|e| Refusal::NotJson(e.to_string()))?;
    let v = match v {
        serde_json::Value::Object(mut o) if o.len() == 1 && o.contains_key("value") => {
            o.remove("value").unwrap_or_default()
        }
        serde_json::Value::Object(_) => return Err(Refusal::NotValueObject),
        v => v,
    };
    let v = match v {
        serde_json::Value::Bool(b) => Value::Bool(b),
        serde_json::Value::Number(n) => match (n.as_i64(), n.as_f64()) {
            (Some(i), _) => Value::I64(i),
            (None, Some(f)) => Value::F64(f),
            _ => return Err(Refusal::NotAValue(n.to_string())),
        },
        other => {
            let text: String = other.to_string().chars().take(40).collect();
            return Err(Refusal::NotAValue(text));
        }
    };
    let value = checked(m, v, statuses(g)[m.device])?;
    Ok(Job {
        origin: Origin::Json(topic.into()),
        writes: vec![(m.component.clone(), m.port.clone(), value)],
    })
}
