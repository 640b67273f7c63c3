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
//!   when the gateway started; one it never wrote is not touched (`default = "keep"`
//!   leaves them all).

use device_interface::{AnalogOut, Device, DeviceError, DigitalOut, Health, Scale};
use rtt::TaskState;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

/// Why guarded outputs refuse writes during a stop.
const STOPPING: &str = "the gateway is stopping: outputs go to their safe values";

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
    /// Back to their value at start, if hwgw wrote them; untouched otherwise.
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
    /// Back to its value at start, if hwgw wrote it.
    Initial,
    /// Left as it is.
    Keep,
}

/// Per output: written at all, and when last (ns on the monotonic clock).
struct Track {
    written: Vec<AtomicBool>,
    last_ns: Vec<AtomicU64>,
}

impl Track {
    fn new(n: u32) -> Track {
        Track {
            written: (0..n).map(|_| AtomicBool::new(false)).collect(),
            last_ns: (0..n).map(|_| AtomicU64::new(0)).collect(),
        }
    }

    fn mark(&self, i: u32) {
        use rtt::time::{Clock, MonotonicClock};
        if let (Some(w), Some(t)) = (self.written.get(i as usize), self.last_ns.get(i as usize)) {
            t.store(MonotonicClock.now().as_nanos(), Ordering::Release);
            w.store(true, Ordering::Release);
        }
    }

    fn written(&self, i: u32) -> bool {
        self.written
            .get(i as usize)
            .is_some_and(|w| w.load(Ordering::Acquire))
    }

    fn last(&self, i: u32) -> u64 {
        self.last_ns
            .get(i as usize)
            .map_or(0, |t| t.load(Ordering::Acquire))
    }
}

/// A card's analog outputs as the registry hands them out: writes go through to the card,
/// are noted, and are refused once the gateway holds its outputs.
pub struct GuardedAnalogOut {
    inner: Arc<dyn AnalogOut>,
    held: Arc<AtomicBool>,
    track: Track,
}

impl GuardedAnalogOut {
    fn check(&self) -> Result<(), DeviceError> {
        if self.held.load(Ordering::Acquire) {
            return Err(DeviceError::Held { reason: STOPPING });
        }
        Ok(())
    }
}

impl Device for GuardedAnalogOut {
    fn health(&self) -> Health {
        self.inner.health()
    }
}

impl AnalogOut for GuardedAnalogOut {
    fn channel_count(&self) -> u32 {
        self.inner.channel_count()
    }
    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        self.inner.scale(channel)
    }
    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        self.check()?;
        self.inner.write_raw(channel, raw)?;
        self.track.mark(channel);
        Ok(())
    }
    fn write(&self, channel: u32, value: f64) -> Result<(), DeviceError> {
        self.check()?;
        self.inner.write(channel, value)?;
        self.track.mark(channel);
        Ok(())
    }
    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        self.inner.read_back_raw(channel)
    }
    fn read_back(&self, channel: u32) -> Result<f64, DeviceError> {
        self.inner.read_back(channel)
    }
}

/// A card's digital outputs as the registry hands them out (see [`GuardedAnalogOut`]).
pub struct GuardedDigitalOut {
    inner: Arc<dyn DigitalOut>,
    held: Arc<AtomicBool>,
    track: Track,
}

impl GuardedDigitalOut {
    fn check(&self) -> Result<(), DeviceError> {
        if self.held.load(Ordering::Acquire) {
            return Err(DeviceError::Held { reason: STOPPING });
        }
        Ok(())
    }
}

impl Device for GuardedDigitalOut {
    fn health(&self) -> Health {
        self.inner.health()
    }
}

impl DigitalOut for GuardedDigitalOut {
    fn output_count(&self) -> u32 {
        self.inner.output_count()
    }
    fn set_bit(&self, bit: u32, value: bool) -> Result<(), DeviceError> {
        self.check()?;
        self.inner.set_bit(bit, value)?;
        self.track.mark(bit);
        Ok(())
    }
    fn check_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        self.inner.check_bit(bit)
    }
    fn set_sequence(&self, start: u32, stop: u32, value: u64) -> Result<(), DeviceError> {
        self.check()?;
        self.inner.set_sequence(start, stop, value)?;
        for b in start..=stop {
            self.track.mark(b);
        }
        Ok(())
    }
    fn check_sequence(&self, start: u32, stop: u32) -> Result<u64, DeviceError> {
        self.inner.check_sequence(start, stop)
    }
}

/// One output's policy and what it needs to apply it.
struct Output {
    /// Its port name.
    port: String,
    policy: Policy,
    /// Its value when the gateway started.
    initial: f64,
    /// Components writing it (through a connection to its port).
    writers: Vec<String>,
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

/// Counters of a card's outputs, for `hwgw status`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct OutputReport {
    /// Outputs hwgw wrote since it started.
    pub written: u64,
    /// Watchdog trips (an output driven to its safe value while running).
    pub watchdog_trips: u64,
}

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
                    format!("{x}: not a safe value for analog output {port:?}: {e}"),
                ));
            }
            Output::new(port, policy, ao.read_back(ch).unwrap_or(0.0))
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
            Output::new(
                port,
                policy,
                f64::from(u8::from(d.check_bit(b).unwrap_or(false))),
            )
        })
        .collect()
}

impl CardOutputs {
    /// Guards `analog` and `digital` (the card's output devices) and settles each output's
    /// policy; `held` is the gateway's stop flag. Every problem names its key.
    pub fn new(
        card: &str,
        analog: Option<Arc<dyn AnalogOut>>,
        digital: Option<Arc<dyn DigitalOut>>,
        spec: &OutputSpec<'_>,
        held: &Arc<AtomicBool>,
    ) -> Result<CardOutputs, Vec<PolicyError>> {
        let mut problems = Vec::new();
        let analog = analog.map(|ao| {
            let outputs = analog_outputs(&*ao, spec, &mut problems);
            let track = Track::new(ao.channel_count());
            (
                Arc::new(GuardedAnalogOut {
                    inner: ao,
                    held: held.clone(),
                    track,
                }),
                outputs,
            )
        });
        let digital = digital.map(|d| {
            let outputs = digital_outputs(&*d, spec, &mut problems);
            let track = Track::new(d.output_count());
            (
                Arc::new(GuardedDigitalOut {
                    inner: d,
                    held: held.clone(),
                    track,
                }),
                outputs,
            )
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
                    format!("{ms}: expected 1 to 86400000 ms"),
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

    /// Notes that component `writer` writes the output behind port `port` (a connection
    /// to it); its failing trips the output's watchdog.
    pub fn add_writer(&mut self, port: &str, writer: &str) {
        for outputs in [
            self.analog.as_mut().map(|a| &mut a.1),
            self.digital.as_mut().map(|d| &mut d.1),
        ]
        .into_iter()
        .flatten()
        {
            for o in outputs.iter_mut().filter(|o| o.port == port) {
                if !o.writers.iter().any(|w| w == writer) {
                    o.writers.push(writer.to_string());
                }
            }
        }
    }

    /// True when some output has a watchdog to keep.
    pub fn watched(&self) -> bool {
        let safe = |v: &Vec<Output>| v.iter().any(|o| matches!(o.policy, Policy::Safe(_)));
        (self.watchdog.is_some() || self.outputs().any(|o| !o.writers.is_empty()))
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
                if let Some(v) = o.at_stop(g.track.written(ch as u32))
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
                if let Some(v) = o.at_stop(g.track.written(b as u32))
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
        fn failed<'o>(
            o: &'o Output,
            state: &dyn Fn(&str) -> Option<TaskState>,
        ) -> Option<&'o String> {
            o.writers
                .iter()
                .find(|w| matches!(state(w), Some(TaskState::Exception | TaskState::FatalError)))
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
                        state(w).map_or(String::new(), |s| s.to_string())
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

    /// Counters for `hwgw status`.
    pub fn report(&self) -> OutputReport {
        let count = |t: &Track| {
            t.written
                .iter()
                .filter(|w| w.load(Ordering::Relaxed))
                .count() as u64
        };
        OutputReport {
            written: self.analog.as_ref().map_or(0, |a| count(&a.0.track))
                + self.digital.as_ref().map_or(0, |d| count(&d.0.track)),
            watchdog_trips: self.trips.load(Ordering::Relaxed),
        }
    }
}

impl Output {
    fn new(port: String, policy: Policy, initial: f64) -> Output {
        Output {
            port,
            policy,
            initial,
            writers: Vec::new(),
            tripped: AtomicBool::new(false),
        }
    }

    /// The value to drive at stop, if any.
    fn at_stop(&self, written: bool) -> Option<f64> {
        match self.policy {
            Policy::Safe(v) => Some(v),
            Policy::Initial if written => Some(self.initial),
            Policy::Initial | Policy::Keep => None,
        }
    }
}

fn default_policy(d: DefaultPolicy) -> Policy {
    match d {
        DefaultPolicy::Initial => Policy::Initial,
        DefaultPolicy::Keep => Policy::Keep,
    }
}
