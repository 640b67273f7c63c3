//! What is published: every channel of the chosen devices as a metric (a Sparkplug metric
//! with its alias, datatype, unit and range; a JSON topic), grouped into Sparkplug
//! devices (a card, or an IO component), read straight from the device registry — the
//! values the cards keep anyway, so publishing costs the real-time threads nothing — and
//! the rule of when a changed value is published again (deadband, shortest and longest
//! period).

use crate::config::{DevicePer, MqttConfig};
use device_interface::{AnalogRange, Interface, Registry, Status};
use driver_api::CardError;
use std::time::{Duration, Instant};

pub(crate) use driver_api::channels::{Kind, Source, Value};

/// A source's kind of value, as a Sparkplug datatype.
pub(crate) fn datatype(source: &Source) -> DataType {
    match source {
        Source::Ai(..) | Source::Ao(..) => DataType::Double,
        Source::Di(..) | Source::Do(..) => DataType::Boolean,
        Source::Position(_) | Source::Turn(_) => DataType::Int64,
    }
}

/// The Sparkplug datatypes hwgw uses (numbers of the specification).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum DataType {
    Int64 = 4,
    UInt64 = 8,
    Double = 10,
    Boolean = 11,
    String = 12,
}

/// One channel as a metric.
#[derive(Clone)]
pub(crate) struct Metric {
    /// Its Sparkplug name within its device (`ai/ch0`, or `ch0`).
    pub name: String,
    /// Its Sparkplug alias, unique in the edge node.
    pub alias: u64,
    /// Its IO component and port (`sim0.ai`, `ch0`): what `hwgw get` names, where a
    /// write goes, its JSON topic.
    pub component: String,
    /// Its port.
    pub port: String,
    /// Where it is read.
    pub source: Source,
    /// Which device of its group's `devices` it is read from, for its health.
    pub device: usize,
    /// An input, or which kind of output.
    pub kind: Kind,
    /// Its IO component (`None` when the runtime had none by that name).
    pub task: Option<rtt::TaskContext>,
    /// An analog channel's range and unit.
    pub range: Option<AnalogRange>,
    /// Its deadband.
    pub deadband: f64,
    /// The value last published, and when.
    pub sent: Option<(Value, Instant)>,
}

impl Metric {
    /// `component.port`.
    pub(crate) fn address(&self) -> String {
        format!("{}.{}", self.component, self.port)
    }

    /// True when `v`, read at `now`, is to be published (see [`due`]).
    pub(crate) fn due(&self, v: Value, now: Instant, min: Duration, max: Option<Duration>) -> bool {
        due(self.sent, self.deadband, v, now, (min, max))
    }
}

/// True when `v`, read at `now`, is to be published after `sent`: it changed beyond
/// `deadband` and `min` has passed since, or `max` has.
pub(crate) fn due(
    sent: Option<(Value, Instant)>,
    deadband: f64,
    v: Value,
    now: Instant,
    (min, max): (Duration, Option<Duration>),
) -> bool {
    let Some((sent, at)) = sent else {
        return true;
    };
    let since = now.saturating_duration_since(at);
    if since < min {
        return false;
    }
    if max.is_some_and(|m| since >= m) {
        return true;
    }
    changed(sent, v, deadband)
}

/// True when `v` differs from `sent` by more than `deadband` (any difference in bits when
/// the deadband is 0, or either is not finite).
fn changed(sent: Value, v: Value, deadband: f64) -> bool {
    match (sent, v) {
        (Value::F64(a), Value::F64(b)) => {
            if deadband == 0.0 || !a.is_finite() || !b.is_finite() {
                a.to_bits() != b.to_bits()
            } else {
                (a - b).abs() > deadband
            }
        }
        (a, b) => a != b,
    }
}

/// A Sparkplug device: a card's devices, or one IO component's.
#[derive(Clone)]
pub(crate) struct Group {
    /// Its Sparkplug device id.
    pub id: String,
    /// The registry devices it stands for.
    pub devices: Vec<(Interface, String)>,
    /// Its metrics.
    pub metrics: Vec<Metric>,
    /// Born (a DBIRTH published in this session, no DDEATH since).
    pub born: bool,
    /// Its metrics by name and by alias.
    names: std::collections::HashMap<String, usize>,
    aliases: std::collections::HashMap<u64, usize>,
}

impl Group {
    /// Its metric named `name`.
    pub(crate) fn by_name(&self, name: &str) -> Option<usize> {
        self.names.get(name).copied()
    }

    /// Its metric of alias `alias`.
    pub(crate) fn by_alias(&self, alias: u64) -> Option<usize> {
        self.aliases.get(&alias).copied()
    }

    /// Each of its devices' status now (offline when it left the registry).
    pub(crate) fn statuses(&self, registry: &Registry) -> Vec<Status> {
        self.devices
            .iter()
            .map(|(i, n)| registry.health(*i, n).map_or(Status::Offline, |h| h.status))
            .collect()
    }
}

/// Online when any of `statuses` is not offline.
pub(crate) fn online(statuses: &[Status]) -> bool {
    statuses.iter().any(|s| *s != Status::Offline)
}

/// The groups of a section over `registry` and the runtime's IO components; every problem.
pub(crate) fn groups(
    c: &MqttConfig,
    registry: &Registry,
    rt: &rtt::Runtime,
) -> Result<Vec<Group>, Vec<CardError>> {
    let per = c
        .sparkplug
        .as_ref()
        .map_or(DevicePer::Card, |s| s.device_per);
    let (entries, missing) = driver_api::channels::devices(registry, &c.devices);
    let mut problems: Vec<CardError> = missing
        .into_iter()
        .map(|(i, why)| CardError::at(format!("devices[{i}]"), why))
        .collect();
    let mut groups: Vec<Group> = Vec::new();
    let mut alias = 0;
    for e in &entries {
        let name = &e.info.name;
        let metrics = match driver_api::channels::of_device(registry, rt, e.interface, name) {
            Ok(m) => m,
            Err(why) => {
                problems.push(CardError::new(why));
                continue;
            }
        };
        let component = metrics
            .first()
            .map(|m| m.component.clone())
            .unwrap_or_default();
        // A card's device: its metrics named after the IO component without the card's
        // name (`ai/ch0`; an encoder registered under a name of its own, `enc0/position`).
        let (id, prefix) = match per {
            DevicePer::Card => {
                let owner = &e.info.owner;
                let rest = component
                    .strip_prefix(owner.as_str())
                    .and_then(|r| r.strip_prefix('.'));
                (owner.clone(), Some(rest.unwrap_or(&component).to_string()))
            }
            DevicePer::Device => (component.clone(), None),
        };
        if let Some(why) = unfit(c, &id, &metrics) {
            problems.push(CardError::new(format!(
                "{why}; leave device {name:?} out with devices = [...]"
            )));
            continue;
        }
        let task = rt.component(&component).ok();
        let group = match groups.iter_mut().position(|g| g.id == id) {
            Some(i) => &mut groups[i],
            None => {
                groups.push(Group {
                    id: id.clone(),
                    devices: Vec::new(),
                    metrics: Vec::new(),
                    born: false,
                    names: Default::default(),
                    aliases: Default::default(),
                });
                groups.last_mut().expect("just pushed")
            }
        };
        group.devices.push((e.interface, name.clone()));
        let device = group.devices.len() - 1;
        for ch in metrics {
            alias += 1;
            let address = ch.address();
            let driver_api::channels::Channel {
                component,
                port,
                source,
                range,
            } = ch;
            let metric_name = match &prefix {
                Some(p) if !p.is_empty() => format!("{p}/{port}"),
                _ => port.clone(),
            };
            let kind = source.kind();
            let i = group.metrics.len();
            group.names.insert(metric_name.clone(), i);
            group.aliases.insert(alias, i);
            group.metrics.push(Metric {
                name: metric_name,
                alias,
                deadband: c.deadbands.get(&address).copied().unwrap_or(c.deadband),
                component,
                port,
                source,
                device,
                kind,
                task: task.clone(),
                range,
                sent: None,
            });
        }
    }
    for port in c.deadbands.keys() {
        if !groups
            .iter()
            .flat_map(|g| &g.metrics)
            .any(|m| &m.address() == port)
        {
            problems.push(CardError::at(
                format!("deadbands.{port}"),
                format!("{port:?} is no published channel (component.port, e.g. sim0.ai.ch0)"),
            ));
        }
    }
    if problems.is_empty() {
        Ok(groups)
    } else {
        Err(problems)
    }
}

/// Why names of a device cannot be published as the section asks: a Sparkplug device id,
/// or a JSON topic level, that is not one.
fn unfit(c: &MqttConfig, id: &str, metrics: &[driver_api::channels::Channel]) -> Option<String> {
    use crate::config::topic_level;
    if c.sparkplug.is_some()
        && let Err(why) = topic_level(id, false)
    {
        return Some(format!("{id:?} cannot be a Sparkplug device id: {why}"));
    }
    if c.json.is_some() {
        for driver_api::channels::Channel {
            component, port, ..
        } in metrics
        {
            for level in [component, port] {
                if let Err(why) = topic_level(level, false) {
                    return Some(format!("{component}.{port} cannot be a JSON topic: {why}"));
                }
            }
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn periods() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let sent = Some((Value::F64(1.0), t0));
        let deadband = 0.5;
        // Never sent: due. Changed beyond the deadband: due once min has passed.
        assert!(due(None, deadband, Value::F64(1.0), t0, (ms(0), None)));
        assert!(!due(
            sent,
            deadband,
            Value::F64(2.0),
            t0 + ms(50),
            (ms(100), None)
        ));
        assert!(due(
            sent,
            deadband,
            Value::F64(2.0),
            t0 + ms(100),
            (ms(100), None)
        ));
        // Within the deadband: not due, until max has passed.
        let max = Some(ms(1000));
        assert!(!due(
            sent,
            deadband,
            Value::F64(1.2),
            t0 + ms(500),
            (ms(0), max)
        ));
        assert!(due(
            sent,
            deadband,
            Value::F64(1.2),
            t0 + ms(1000),
            (ms(0), max)
        ));
    }

    #[test]
    fn deadband_and_periods() {
        assert!(!changed(Value::F64(1.0), Value::F64(1.0), 0.0));
        assert!(changed(
            Value::F64(1.0),
            Value::F64(1.0 + f64::EPSILON),
            0.0
        ));
        assert!(!changed(Value::F64(1.0), Value::F64(1.05), 0.1));
        assert!(changed(Value::F64(1.0), Value::F64(1.2), 0.1));
        assert!(changed(Value::F64(1.0), Value::F64(f64::NAN), 0.1));
        assert!(!changed(Value::F64(f64::NAN), Value::F64(f64::NAN), 0.1));
        assert!(changed(Value::Bool(false), Value::Bool(true), 0.0));
        assert!(!changed(Value::I64(3), Value::I64(3), 5.0));
    }
}
