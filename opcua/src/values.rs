//! Channel values as OPC UA data values, and the sampler that reads them from the device
//! registry every period and hands what changed (value, status, or the device's error) to
//! the address space, which tells the monitored items.
//!
//! A value's status comes from its device's health: Good when online, Uncertain (last
//! usable value) when stale, Bad when offline or unreadable (no communication, a
//! communication error, a device failure). Its source timestamp is when the device last
//! delivered a good sample (so a stale value's age is the server timestamp less it), its
//! server timestamp when it was read.

use crate::nodes::HwgwNodeManager;
use crate::plan::Plan;
use device_interface::{DeviceError, Health, Interface, Status};
use driver_api::channels::{Source, Value};
use std::time::Duration;
use ua::server::SubscriptionCache;
use ua::types::{DataTypeId, DataValue, DateTime, NodeId, StatusCode, Variant};

/// A channel value as a variant (the exact bits).
pub(crate) fn variant(v: Value) -> Variant {
    match v {
        Value::F64(x) => Variant::Double(x),
        Value::Bool(b) => Variant::Boolean(b),
        Value::I64(i) => Variant::Int64(i),
    }
}

/// A channel's OPC UA data type.
pub(crate) fn data_type(source: &Source) -> DataTypeId {
    match source {
        Source::Ai(..) | Source::Ao(..) => DataTypeId::Double,
        Source::Di(..) | Source::Do(..) => DataTypeId::Boolean,
        Source::Position(_) | Source::Turn(_) => DataTypeId::Int64,
    }
}

/// The status of a value read as `read` from a device of health `health`.
pub(crate) fn status(health: Option<&Health>, read: &Result<Value, DeviceError>) -> StatusCode {
    let Some(h) = health else {
        // The device left the registry.
        return StatusCode::BadNoCommunication;
    };
    match (h.status, read) {
        (Status::Offline, _) => h
            .last_error
            .as_ref()
            .map_or(StatusCode::BadNoCommunication, bad),
        // A stale device's inputs say so when read: the last good value is what is served.
        (_, Err(DeviceError::Stale { .. })) | (Status::Stale, Ok(_)) => {
            StatusCode::UncertainLastUsableValue
        }
        (_, Err(e)) => bad(e),
        (Status::Online, Ok(_)) => StatusCode::Good,
    }
}

/// The Bad status of a device error.
fn bad(e: &DeviceError) -> StatusCode {
    match e {
        DeviceError::Bus { .. } => StatusCode::BadCommunicationError,
        DeviceError::Offline | DeviceError::Stale { .. } => StatusCode::BadNoCommunication,
        _ => StatusCode::BadDeviceFailure,
    }
}

/// Now less `age`.
fn before_now(now: DateTime, age: Duration) -> DateTime {
    let ticks = i64::try_from(age.as_nanos() / 100).unwrap_or(i64::MAX);
    DateTime::from(now.ticks().saturating_sub(ticks).max(0))
}

/// One served channel as the sampler keeps it.
struct Entry {
    id: NodeId,
    source: Source,
    device: usize,
    last: Option<(Option<Value>, StatusCode)>,
    /// The last value read without error: an Uncertain value's.
    last_good: Option<Value>,
}

/// One served device: its health's source and its error variable.
struct DeviceEntry {
    interface: Interface,
    name: String,
    error_id: NodeId,
    last_error: Option<String>,
}

/// Reads the served channels and pushes what changed.
pub(crate) struct Sampler {
    entries: Vec<Entry>,
    devices: Vec<DeviceEntry>,
    registry: std::sync::Arc<device_interface::Registry>,
}

/// The node id of channel `component.port` in namespace `ns`.
pub(crate) fn channel_id(ns: u16, component: &str, port: &str) -> NodeId {
    NodeId::new(ns, format!("{component}.{port}"))
}

/// The node id of the error variable of device `component` in namespace `ns`.
pub(crate) fn error_id(ns: u16, component: &str) -> NodeId {
    NodeId::new(ns, format!("{component}/Error"))
}

impl Sampler {
    pub(crate) fn new(
        plan: &Plan,
        ns: u16,
        registry: std::sync::Arc<device_interface::Registry>,
    ) -> Sampler {
        let mut entries = Vec::new();
        let mut devices = Vec::new();
        for (i, d) in plan.devices.iter().enumerate() {
            devices.push(DeviceEntry {
                interface: d.interface,
                name: d.name.clone(),
                error_id: error_id(ns, &d.component),
                last_error: None,
            });
            for c in &d.channels {
                entries.push(Entry {
                    id: channel_id(ns, &c.component, &c.port),
                    source: c.source.clone(),
                    device: i,
                    last: None,
                    last_good: None,
                });
            }
        }
        Sampler {
            entries,
            devices,
            registry,
        }
    }

    /// Reads every channel and device once; pushes what changed since the last time.
    /// Returns how many values were pushed.
    pub(crate) fn tick(&mut self, nm: &HwgwNodeManager, subs: &SubscriptionCache) -> usize {
        let now = DateTime::now();
        let healths: Vec<Option<Health>> = self
            .devices
            .iter()
            .map(|d| self.registry.health(d.interface, &d.name))
            .collect();
        let mut changed: Vec<(NodeId, DataValue)> = Vec::new();
        for (d, h) in self.devices.iter_mut().zip(&healths) {
            let text = match h {
                None => "the device left the registry".to_string(),
                Some(h) => h
                    .last_error
                    .as_ref()
                    .map(|e| e.to_string())
                    .unwrap_or_default(),
            };
            if d.last_error.as_ref() != Some(&text) {
                changed.push((
                    d.error_id.clone(),
                    DataValue {
                        value: Some(Variant::from(text.as_str())),
                        status: Some(StatusCode::Good),
                        source_timestamp: Some(now),
                        server_timestamp: Some(now),
                        ..Default::default()
                    },
                ));
                d.last_error = Some(text);
            }
        }
        for e in &mut self.entries {
            let h = healths[e.device].as_ref();
            let read = e.source.read();
            let code = status(h, &read);
            if let Ok(v) = read {
                e.last_good = Some(v);
            }
            let value = match read {
                Ok(v) => Some(v),
                Err(_) if code.is_uncertain() => e.last_good,
                Err(_) => None,
            };
            let same = e.last.as_ref().is_some_and(|(v, c)| {
                *c == code
                    && match (v, &value) {
                        (Some(Value::F64(a)), Some(Value::F64(b))) => a.to_bits() == b.to_bits(),
                        (a, b) => a == b,
                    }
            });
            if same {
                continue;
            }
            let source_ts = h
                .and_then(|h| h.age())
                .map_or(now, |age| before_now(now, age));
            changed.push((
                e.id.clone(),
                DataValue {
                    value: Some(value.map_or(Variant::Empty, variant)),
                    status: Some(code),
                    source_timestamp: Some(source_ts),
                    server_timestamp: Some(now),
                    ..Default::default()
                },
            ));
            e.last = Some((value, code));
        }
        let n = changed.len();
        if n > 0
            && let Err(e) = nm.set_values(subs, changed.iter().map(|(id, v)| (id, None, v.clone())))
        {
            tracing::error!("OPC UA: values not set: {e}");
        }
        n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn age_is_subtracted() {
        let now = DateTime::now();
        let t = before_now(now, Duration::from_millis(1500));
        assert_eq!(now.ticks() - t.ticks(), 15_000_000);
        assert_eq!(before_now(now, Duration::MAX).ticks(), 0);
    }

    #[test]
    fn statuses() {
        use device_interface::time::Timestamp;
        let h = |status, last_error| Health {
            status,
            last_good: None,
            checked_at: Timestamp::from_nanos(0),
            last_error,
        };
        let ok = Ok(Value::F64(1.0));
        assert_eq!(
            status(Some(&h(Status::Online, None)), &ok),
            StatusCode::Good
        );
        assert_eq!(
            status(Some(&h(Status::Stale, None)), &ok),
            StatusCode::UncertainLastUsableValue
        );
        assert_eq!(
            status(Some(&h(Status::Offline, Some(DeviceError::Offline))), &ok),
            StatusCode::BadNoCommunication
        );
        assert_eq!(status(None, &ok), StatusCode::BadNoCommunication);
        assert_eq!(
            status(Some(&h(Status::Online, None)), &Err(DeviceError::Offline)),
            StatusCode::BadNoCommunication
        );
        let stale = DeviceError::Stale {
            age: Some(Duration::from_millis(500)),
        };
        assert_eq!(
            status(Some(&h(Status::Stale, None)), &Err(stale.clone())),
            StatusCode::UncertainLastUsableValue
        );
        assert_eq!(
            status(Some(&h(Status::Offline, Some(stale))), &ok),
            StatusCode::BadNoCommunication
        );
    }
}
