//! The output policy: every card output the gateway can write is registered through a
//! guard that knows whether hwgw ever wrote it, when it last did, and refuses writes once
//! the gateway stops; each output has a policy, in the spirit of EPICS's IVOA and the
//! hostmot2 watchdog:
//!
//! - a safe value (`[card.outputs] safe = { setpoint = 1.5, pump = false }`, or the
//!   shorthand `safe_analog_out` / `safe_digital_out_on`): driven at stop, and — with
//!   `watchdog_ms` — when nothing wrote the output for that long, or when a component
//!   connected to it goes to Exception or FatalError;
//! - `"keep"`: left as it is at stop;
//! - by default (`default = "initial"`): an output hwgw wrote goes back to the value it had
//!   just before hwgw first wrote it — when the card's read-back is the device's state
//!   ([`ReadBack`]); otherwise it is left as it is, and the log says why. One hwgw never
//!   wrote is not touched (`default = "keep"` leaves them all).

mod guard;

pub use guard::{GuardedAnalogOut, GuardedDigitalOut, Hold};

use device_interface::{AnalogOut, DeviceError, DigitalOut};
use driver_api::ReadBack;
use guard::Track;
use rtt::TaskState;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

/// The `[card.outputs]` section.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputsConfig {
    /// Each output's policy by port name (`ch0`, `bit3`, or the card's channel names): a
    /// safe value (a number for an analog output, true/false for a digital one) or
    /// `"keep"`.
    #[serde(default)]
    pub safe: BTreeMap<String, toml::Value>,
    /// What an output without a policy of its own gets (default `"initial"`).
    #[serde(default)]
    pub default: DefaultPolicy,
    /// Outputs with a safe value go to it when nothing wrote them for this long (ms), or
    /// when a component connected to them fails. Absent: no watchdog.
    #[serde(default)]
    pub watchdog_ms: Option<f64>,
}

/// The policy of outputs given none of their own.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum DefaultPolicy {
    /// Back to their value before hwgw first wrote them (where the card can tell it);
    /// untouched if hwgw never wrote them.
    #[default]
    Initial,
    /// Left as they are.
    Keep,
}

/// What happens to one output at stop (and on a watchdog trip).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Policy {
    /// Driven to this value (analog, physical units; digital, 0 or 1).
    Safe(f64),
    /// Back to its value before hwgw first wrote it (if hwgw wrote it, and the card could
    /// tell that value).
    Initial,
    /// Left as it is.
    Keep,
}

/// One output's policy and what it needs to apply it.
struct Output {
    /// Its port name.
    port: String,
    policy: Policy,
    /// Components writing it (through a connection to its port); more may come with a
    /// reload while the watchdog reads them.
    writers: arc_swap::ArcSwap<Vec<String>>,
    /// True while a watchdog trip holds it at its safe value (until the next write).
    tripped: AtomicBool,
}

/// A card's outputs under the gateway's policy.
pub struct CardOutputs {
    card: String,
    analog: Option<(Arc<GuardedAnalogOut>, Vec<Output>)>,
    digital: Option<(Arc<GuardedDigitalOut>, Vec<Output>)>,
    watchdog: Option<Duration>,
    trips: AtomicU64,
}

/// Counters of a card's outputs, for `hwgw status` (defined with the control protocol).
pub use protocol::OutputReport;

/// How a card's outputs are to be treated, as the deployment says (checked against the
/// card by [`CardOutputs::new`]).
pub struct OutputSpec<'a> {
    /// `[card.outputs]`.
    pub config: &'a OutputsConfig,
    /// `safe_analog_out`.
    pub safe_analog_out: Option<&'a [f64]>,
    /// `safe_digital_out_on`.
    pub safe_digital_out_on: Option<&'a [u32]>,
    /// Port names of the analog and digital outputs, in channel order.
    pub analog_ports: Vec<String>,
    /// See `analog_ports`.
    pub digital_ports: Vec<String>,
}

/// A card's output devices, as the card hands them out.
pub struct OutputDevices {
    /// Its analog outputs.
    pub analog: Option<Arc<dyn AnalogOut>>,
    /// Its digital outputs.
    pub digital: Option<Arc<dyn DigitalOut>>,
    /// What their read-back shows ([`driver_api::Card::read_back`]).
    pub read_back: ReadBack,
}

/// A policy problem: the key under the card and what is wrong.
pub type PolicyError = (String, String);

fn digital_value(v: &toml::Value) -> Option<f64> {
    match v {
        toml::Value::Boolean(b) => Some(f64::from(u8::from(*b))),
        _ => None,
    }
}

/// The policy `spec` gives the output behind `port`, from `[card.outputs] safe` (parsed by
/// `value`), else the shorthand (`legacy`), else the default.
fn policy_of(
    port: &str,
    legacy: Option<f64>,
    spec: &OutputSpec<'_>,
    value: fn(&toml::Value) -> Option<f64>,
    expected: &str,
    problems: &mut Vec<PolicyError>,
) -> Policy {
    match spec.config.safe.get(port) {
        Some(toml::Value::String(s)) if s == "keep" => Policy::Keep,
        Some(v) => value(v).map_or_else(
            || {
                problems.push((
                    format!("outputs.safe.{port}"),
                    format!("{v}: expected {expected} or \"keep\""),
                ));
                Policy::Keep
            },
            Policy::Safe,
        ),
        None => legacy.map_or(default_policy(spec.config.default), Policy::Safe),
    }
}

fn analog_value(v: &toml::Value) -> Option<f64> {
    v.as_float().or_else(|| v.as_integer().map(|i| i as f64))
}

/// The analog outputs' policies, each safe value checked against its channel's range.
fn analog_outputs(
    ao: &dyn AnalogOut,
    spec: &OutputSpec<'_>,
    problems: &mut Vec<PolicyError>,
) -> Vec<Output> {
    let n = ao.channel_count();
    if let Some(v) = spec.safe_analog_out
        && v.len() > n as usize
    {
        problems.push((
            "safe_analog_out".into(),
            format!("{} values for {n} analog outputs", v.len()),
        ));
    }
    (0..n)
        .map(|ch| {
            let port = spec
                .analog_ports
                .get(ch as usize)
                .cloned()
                .unwrap_or_else(|| format!("ch{ch}"));
            let legacy = spec
                .safe_analog_out
                .and_then(|v| v.get(ch as usize).copied());
            let policy = policy_of(&port, legacy, spec, analog_value, "a number", problems);
            if let Policy::Safe(x) = policy
                && let Err(e) = ao.scale(ch).and_then(|s| s.to_raw_checked(ch, x))
            {
                let key = if spec.config.safe.contains_key(&port) {
                    format!("outputs.safe.{port}")
                } else {
                    format!("safe_analog_out[{ch}]")
                };
                problems.push((
                    key,
                    format!(
                        "{}: not a safe value for analog output {port:?}: {e}",
                        device_interface::text::Number(x)
                    ),
                ));
            }
            Output::new(port, policy)
        })
        .collect()
}

/// The digital outputs' policies.
fn digital_outputs(
    d: &dyn DigitalOut,
    spec: &OutputSpec<'_>,
    problems: &mut Vec<PolicyError>,
) -> Vec<Output> {
    let n = d.output_count();
    for (i, b) in spec.safe_digital_out_on.into_iter().flatten().enumerate() {
        if *b >= n {
            problems.push((
                format!("safe_digital_out_on[{i}]"),
                format!("bit {b} does not exist (the card has {n} digital outputs)"),
            ));
        }
    }
    (0..n)
        .map(|b| {
            let port = spec
                .digital_ports
                .get(b as usize)
                .cloned()
                .unwrap_or_else(|| format!("bit{b}"));
            let legacy = spec
                .safe_digital_out_on
                .map(|on| f64::from(u8::from(on.contains(&b))));
            let policy = policy_of(
                &port,
                legacy,
                spec,
                digital_value,
                "true or false",
                problems,
            );
            Output::new(port, policy)
        })
        .collect()
}

impl CardOutputs {
    /// Guards the card's output `devices` and settles each output's policy; `hold` is the
    /// gateway's stop gate. Every problem names its key.
    pub fn new(
        card: &str,
        devices: OutputDevices,
        spec: &OutputSpec<'_>,
        hold: &Arc<Hold>,
    ) -> Result<CardOutputs, Vec<PolicyError>> {
        let OutputDevices {
            analog,
            digital,
            read_back,
        } = devices;
        let mut problems = Vec::new();
        let analog = analog.map(|ao| {
            let outputs = analog_outputs(&*ao, spec, &mut problems);
            let guard = GuardedAnalogOut::new(ao, hold, read_back.clone());
            (Arc::new(guard), outputs)
        });
        let digital = digital.map(|d| {
            let outputs = digital_outputs(&*d, spec, &mut problems);
            let guard = GuardedDigitalOut::new(d, hold, read_back.clone());
            (Arc::new(guard), outputs)
        });
        let ports: Vec<&str> = analog
            .iter()
            .flat_map(|a| a.1.iter())
            .chain(digital.iter().flat_map(|d| d.1.iter()))
            .map(|o| o.port.as_str())
            .collect();
        for port in spec
            .config
            .safe
            .keys()
            .filter(|p| !ports.contains(&p.as_str()))
        {
            let have = if ports.is_empty() {
                "none".to_string()
            } else {
                ports.join(", ")
            };
            problems.push((
                format!("outputs.safe.{port}"),
                format!("the card has no output port {port:?}; it has: {have}"),
            ));
        }
        let watchdog = match spec.config.watchdog_ms {
            None => None,
            Some(ms) if (1.0..=86_400_000.0).contains(&ms) => {
                Some(Duration::from_secs_f64(ms / 1000.0))
            }
            Some(ms) => {
                problems.push((
                    "outputs.watchdog_ms".into(),
                    format!(
                        "{}: expected 1 to 86400000 ms",
                        device_interface::text::Number(ms)
                    ),
                ));
                None
            }
        };
        if !problems.is_empty() {
            return Err(problems);
        }
        Ok(CardOutputs {
            card: card.to_string(),
            analog,
            digital,
            watchdog,
            trips: AtomicU64::new(0),
        })
    }

    /// The policy and port name of analog output `channel` (`analog`) or digital output
    /// `channel`; `None` past the end.
    pub fn policy(&self, analog: bool, channel: u32) -> Option<(Policy, &str)> {
        let outputs = if analog {
            &self.analog.as_ref()?.1
        } else {
            &self.digital.as_ref()?.1
        };
        outputs
            .get(channel as usize)
            .map(|o| (o.policy, o.port.as_str()))
    }

    /// The guarded analog outputs, to register in place of the card's own.
    pub fn analog_device(&self) -> Option<Arc<dyn AnalogOut>> {
        self.analog
            .as_ref()
            .map(|(g, _)| g.clone() as Arc<dyn AnalogOut>)
    }

    /// The guarded digital outputs, to register in place of the card's own.
    pub fn digital_device(&self) -> Option<Arc<dyn DigitalOut>> {
        self.digital
            .as_ref()
            .map(|(g, _)| g.clone() as Arc<dyn DigitalOut>)
    }

    /// Sets every output's writers at once: `(port, writer component)` pairs, as the
    /// connections to the card's outputs now are (a reload).
    pub fn set_writers(&self, pairs: &[(&str, &str)]) {
        for o in self.outputs() {
            let mut writers: Vec<String> = Vec::new();
            for (_, w) in pairs.iter().filter(|(p, _)| *p == o.port) {
                if !writers.iter().any(|x| x == w) {
                    writers.push(w.to_string());
                }
            }
            if **o.writers.load() != writers {
                o.writers.store(Arc::new(writers));
            }
        }
    }

    /// Notes that component `writer` writes the output behind port `port` (a connection
    /// to it); its failing trips the output's watchdog.
    pub fn add_writer(&self, port: &str, writer: &str) {
        for o in self.outputs().filter(|o| o.port == port) {
            o.writers.rcu(|writers| {
                let mut more = Vec::clone(writers);
                if !more.iter().any(|w| w == writer) {
                    more.push(writer.to_string());
                }
                more
            });
        }
    }

    /// True when some output has a watchdog to keep.
    pub fn watched(&self) -> bool {
        let safe = |v: &Vec<Output>| v.iter().any(|o| matches!(o.policy, Policy::Safe(_)));
        (self.watchdog.is_some() || self.outputs().any(|o| !o.writers.load().is_empty()))
            && (self.analog.as_ref().is_some_and(|a| safe(&a.1))
                || self.digital.as_ref().is_some_and(|d| safe(&d.1)))
    }

    fn outputs(&self) -> impl Iterator<Item = &Output> {
        self.analog
            .iter()
            .flat_map(|a| a.1.iter())
            .chain(self.digital.iter().flat_map(|d| d.1.iter()))
    }

    /// Drives the outputs whose policy asks for it to their safe (or initial) values,
    /// through the card itself (the guard refuses everyone else once the stop began).
    pub fn drive_safe(&self) {
        if let Some((g, outs)) = &self.analog {
            for (ch, o) in outs.iter().enumerate() {
                if let Some(v) = self.at_stop(o, &g.track, ch as u32)
                    && let Err(e) = g.inner.write(ch as u32, v)
                {
                    tracing::error!(
                        "card {:?}: analog output {:?} not at its safe value {v}: {e}",
                        self.card,
                        o.port
                    );
                }
            }
        }
        if let Some((g, outs)) = &self.digital {
            for (b, o) in outs.iter().enumerate() {
                if let Some(v) = self.at_stop(o, &g.track, b as u32)
                    && let Err(e) = g.inner.set_bit(b as u32, v != 0.0)
                {
                    tracing::error!(
                        "card {:?}: digital output {:?} not at its safe value: {e}",
                        self.card,
                        o.port
                    );
                }
            }
        }
    }

    /// One watchdog check: an output with a safe value goes to it when nothing wrote it for
    /// the watchdog's time, or when one of its writers (`state` of a component by name)
    /// failed. Once per episode: a new write rearms it.
    pub fn watch(&self, now_ns: u64, state: &dyn Fn(&str) -> Option<TaskState>) {
        fn failed(o: &Output, state: &dyn Fn(&str) -> Option<TaskState>) -> Option<String> {
            o.writers
                .load()
                .iter()
                .find(|w| matches!(state(w), Some(TaskState::Exception | TaskState::FatalError)))
                .cloned()
        }
        let check = |o: &Output, written: bool, last: u64| -> Option<(f64, String)> {
            let Policy::Safe(v) = o.policy else {
                return None;
            };
            if let Some(w) = failed(o, state) {
                return Some((
                    v,
                    format!(
                        "component {w:?} writing it is in {}",
                        state(&w).map_or(String::new(), |s| s.to_string())
                    ),
                ));
            }
            let limit = self.watchdog?;
            let age = Duration::from_nanos(now_ns.saturating_sub(last));
            (written && age > limit)
                .then(|| (v, format!("not written for {age:.0?} (watchdog {limit:?})")))
        };
        if let Some((g, outs)) = &self.analog {
            for (ch, o) in outs.iter().enumerate() {
                let ch = ch as u32;
                self.trip(o, check(o, g.track.written(ch), g.track.last(ch)), |v| {
                    g.inner.write(ch, v)
                });
            }
        }
        if let Some((g, outs)) = &self.digital {
            for (b, o) in outs.iter().enumerate() {
                let b = b as u32;
                self.trip(o, check(o, g.track.written(b), g.track.last(b)), |v| {
                    g.inner.set_bit(b, v != 0.0)
                });
            }
        }
    }

    /// Drives `o` to its safe value when `why` says so, once per episode (the episode ends
    /// when the reason goes: a new write, a recovered writer).
    fn trip(
        &self,
        o: &Output,
        why: Option<(f64, String)>,
        write: impl FnOnce(f64) -> Result<(), DeviceError>,
    ) {
        let Some((v, why)) = why else {
            o.tripped.store(false, Ordering::Release);
            return;
        };
        if o.tripped.swap(true, Ordering::AcqRel) {
            return;
        }
        self.trips.fetch_add(1, Ordering::Relaxed);
        match write(v) {
            Ok(()) => tracing::error!(
                "card {:?}: output {:?} to its safe value {v}: {why}",
                self.card,
                o.port
            ),
            Err(e) => tracing::error!(
                "card {:?}: output {:?} should go to its safe value {v} ({why}) but: {e}",
                self.card,
                o.port
            ),
        }
    }

    /// The value to drive output `i` (policy `o`, noted in `track`) to at stop, if any.
    fn at_stop(&self, o: &Output, track: &Track, i: u32) -> Option<f64> {
        match o.policy {
            Policy::Safe(v) => Some(v),
            Policy::Initial if track.written(i) => {
                let initial = track.initial(i);
                if initial.is_none() {
                    tracing::warn!(
                        "card {:?}: output {:?} left as hwgw last wrote it: its value before \
                         that is unknown (the card's read-back did not show the device's \
                         state); give it a safe value or \"keep\"",
                        self.card,
                        o.port
                    );
                }
                initial
            }
            Policy::Initial | Policy::Keep => None,
        }
    }

    /// Counters for `hwgw status`.
    pub fn report(&self) -> OutputReport {
        OutputReport {
            written: self
                .analog
                .as_ref()
                .map_or(0, |a| a.0.track.count_written())
                + self
                    .digital
                    .as_ref()
                    .map_or(0, |d| d.0.track.count_written()),
            watchdog_trips: self.trips.load(Ordering::Relaxed),
        }
    }
}

impl Output {
    fn new(port: String, policy: Policy) -> Output {
        Output {
            port,
            policy,
            writers: arc_swap::ArcSwap::from_pointee(Vec::new()),
            tripped: AtomicBool::new(false),
        }
    }
}

fn default_policy(d: DefaultPolicy) -> Policy {
    match d {
        DefaultPolicy::Initial => Policy::Initial,
        DefaultPolicy::Keep => Policy::Keep,
    }
}
