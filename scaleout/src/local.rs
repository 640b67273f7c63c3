//! This gateway's own devices as the others see them: their samples and shapes, and the
//! writes other gateways make to its outputs.
//!
//! Only devices a card of this gateway registered are published or written here: an
//! imported device (owner `zenoh:<gateway>`) is never passed on, so two gateways that
//! import from each other cannot loop.

use crate::wire::{self, Catalogue, DeviceShape, EncoderShape, Sample, Write, WriteReply};
use device_interface::time::{Clock, MonotonicClock};
use device_interface::{DeviceError, Health, Interface, Registry};
use std::collections::HashMap;

/// The registry owner of the devices imported from gateway `gw`.
pub fn owner_of(gw: &str) -> String {
    format!("zenoh:{gw}")
}

/// True when the device registered by `owner` is this gateway's own.
pub fn is_local(owner: &str) -> bool {
    !owner.starts_with("zenoh:")
}

/// Every local physical device (no alias, no import, no logical device) whose name can be
/// a key: `(interface, name)`.
pub fn local_devices(registry: &Registry) -> Vec<(Interface, String)> {
    registry
        .entries()
        .into_iter()
        .filter(|e| e.info.alias_of.is_none() && is_local(&e.info.owner))
        .filter(|e| !e.interface.is_logical())
        .filter(|e| crate::config::is_key_name(&e.info.name))
        .map(|e| (e.interface, e.info.name))
        .collect()
}

fn shape_of(registry: &Registry, i: Interface, name: &str) -> Option<DeviceShape> {
    let scales = |n: u32, f: &dyn Fn(u32) -> Result<device_interface::Scale, DeviceError>| {
        (0..n).map(f).collect::<Result<Vec<_>, _>>().ok()
    };
    let (channels, scales, encoder) = match i {
        Interface::AnalogIn => {
            let d = registry.analog_in().get(name)?;
            let n = d.channel_count();
            (n, scales(n, &|c| d.scale(c))?, None)
        }
        Interface::AnalogOut => {
            let d = registry.analog_out().get(name)?;
            let n = d.channel_count();
            (n, scales(n, &|c| d.scale(c))?, None)
        }
        Interface::DigitalIn => (registry.digital_in().get(name)?.input_count(), vec![], None),
        Interface::DigitalOut => (
            registry.digital_out().get(name)?.output_count(),
            vec![],
            None,
        ),
        Interface::Encoder => {
            let d = registry.encoder().get(name)?;
            let e = EncoderShape {
                resolution: d.resolution(),
                upcounting: d.upcounting(),
            };
            (2, vec![], Some(e))
        }
        // Logical devices are not forwarded: their IO components' operations are.
        Interface::Sensor | Interface::Drive | Interface::Axis => return None,
    };
    Some(DeviceShape {
        interface: i,
        name: name.to_string(),
        channels,
        scales,
        encoder,
    })
}

/// The catalogue of gateway `gw` in its run `run`: every local device and its shape.
pub fn catalogue(gw: &str, run: u64, registry: &Registry) -> Catalogue {
    Catalogue {
        protocol: wire::PROTOCOL,
        gateway: gw.to_string(),
        run,
        devices: local_devices(registry)
            .iter()
            .filter_map(|(i, n)| shape_of(registry, *i, n))
            .collect(),
    }
}

/// Reads device `name` of interface `i` into a sample (numbered `seq`), or `None` when it
/// is no longer registered.
pub fn sample(registry: &Registry, i: Interface, name: &str, seq: u64) -> Option<Sample> {
    fn all<T>(
        n: u32,
        f: impl Fn(u32) -> Result<T, DeviceError>,
        to: fn(T) -> i64,
    ) -> Vec<Option<i64>> {
        (0..n).map(|c| f(c).ok().map(to)).collect()
    }
    let (health, values): (Health, Vec<Option<i64>>) = match i {
        Interface::AnalogIn => {
            let d = registry.analog_in().get(name)?;
            (d.health(), all(d.channel_count(), |c| d.read_raw(c), |v| v))
        }
        Interface::AnalogOut => {
            let d = registry.analog_out().get(name)?;
            (
                d.health(),
                all(d.channel_count(), |c| d.read_back_raw(c), |v| v),
            )
        }
        Interface::DigitalIn => {
            let d = registry.digital_in().get(name)?;
            (
                d.health(),
                all(d.input_count(), |c| d.read_bit(c), i64::from),
            )
        }
        Interface::DigitalOut => {
            let d = registry.digital_out().get(name)?;
            (
                d.health(),
                all(d.output_count(), |c| d.check_bit(c), i64::from),
            )
        }
        Interface::Encoder => {
            let d = registry.encoder().get(name)?;
            (d.health(), vec![d.position().ok(), d.turn().ok()])
        }
        Interface::Sensor | Interface::Drive | Interface::Axis => return None,
    };
    let unix_ns = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX));
    Some(Sample {
        seq,
        read_ns: MonotonicClock.now().as_nanos(),
        unix_ns,
        age_ns: health
            .age()
            .map(|a| u64::try_from(a.as_nanos()).unwrap_or(u64::MAX)),
        status: health.status,
        error: health.last_error.map(|e| e.to_string()),
        values,
    })
}

/// Why a write from another gateway was refused whole.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WriteError {
    /// The writer speaks another protocol version.
    #[error("protocol {got} from {writer}; {gateway} speaks {}", wire::PROTOCOL)]
    Protocol {
        /// The version it speaks.
        got: u32,
        /// The writing gateway.
        writer: String,
        /// This gateway.
        gateway: String,
    },
    /// No device of this gateway has that name on that interface: which there are.
    #[error("{gateway} has no {interface} device {device:?}; it has: {has}")]
    NoDevice {
        /// This gateway.
        gateway: String,
        /// The interface's key (`analog_out`).
        interface: &'static str,
        /// The device named.
        device: String,
        /// The devices it has on that interface, or "none".
        has: String,
    },
    /// The values name a channel twice, or more channels than the device has.
    #[error(
        "a write of {values} values to {device} (of {count} channels) names a channel twice or too many"
    )]
    Channels {
        /// Values in the write.
        values: usize,
        /// The device.
        device: String,
        /// Its channels.
        count: u32,
    },
}

/// Carries out a write from another gateway; the answer says which values were refused.
pub fn write(gw: &str, registry: &Registry, w: &Write) -> Result<WriteReply, WriteError> {
    if w.protocol != wire::PROTOCOL {
        return Err(WriteError::Protocol {
            got: w.protocol,
            writer: w.writer.clone(),
            gateway: gw.to_string(),
        });
    }
    let own = |owner: Option<String>| owner.is_some_and(|o| is_local(&o));
    let owner = registry
        .entries()
        .into_iter()
        .find(|e| {
            e.interface == w.interface && e.info.name == w.device && e.info.alias_of.is_none()
        })
        .map(|e| e.info.owner);
    if !own(owner) {
        let names: Vec<String> = local_devices(registry)
            .into_iter()
            .filter(|(i, _)| *i == w.interface)
            .map(|(_, n)| n)
            .collect();
        return Err(WriteError::NoDevice {
            gateway: gw.to_string(),
            interface: wire::interface_key(w.interface),
            device: w.device.clone(),
            has: if names.is_empty() {
                "none".to_string()
            } else {
                names.join(", ")
            },
        });
    }
    let count = match w.interface {
        Interface::AnalogOut => registry
            .analog_out()
            .get(&w.device)
            .map(|d| d.channel_count()),
        Interface::DigitalOut => registry
            .digital_out()
            .get(&w.device)
            .map(|d| d.output_count()),
        Interface::Encoder => Some(2),
        _ => None,
    }
    .unwrap_or(0);
    let mut seen = std::collections::HashSet::new();
    if w.values.len() > count as usize || !w.values.iter().all(|(c, _)| seen.insert(*c)) {
        return Err(WriteError::Channels {
            values: w.values.len(),
            device: w.device.clone(),
            count,
        });
    }
    let mut refused = Vec::new();
    for &(c, raw) in &w.values {
        let r = match w.interface {
            Interface::AnalogOut => registry
                .analog_out()
                .lookup(&w.device)
                .map_err(|e| e.to_string())
                .and_then(|d| d.write_raw(c, raw).map_err(|e| e.to_string())),
            Interface::DigitalOut => registry
                .digital_out()
                .lookup(&w.device)
                .map_err(|e| e.to_string())
                .and_then(|d| d.set_bit(c, raw != 0).map_err(|e| e.to_string())),
            Interface::Encoder => registry
                .encoder()
                .lookup(&w.device)
                .map_err(|e| e.to_string())
                .and_then(|d| match c {
                    0 => d.set_position(raw).map_err(|e| e.to_string()),
                    1 => d.set_turn(raw).map_err(|e| e.to_string()),
                    _ => Err(format!(
                        "an encoder has channels 0 (position) and 1 (turn), not {c}"
                    )),
                }),
            i => Err(format!("{i} is an input: it cannot be written")),
        };
        if let Err(e) = r {
            refused.push((c, e));
        }
    }
    Ok(WriteReply { refused })
}

/// The last message a remote writer's run applied to one device here.
type WriterKey = (String, u64, Interface, String);

/// The longest writer or device name remembered, bytes.
const MAX_NAME: usize = 256;

/// The writers remembered at most (beyond it they are forgotten together, and a repeat of
/// a forgotten writer's last message would be written once more).
const MAX_WRITERS: usize = 4096;

/// Other gateways' writes, each message applied once: a message sent again (same writer,
/// run and sequence number) is answered as the first time, not written again, so a
/// writer's retries never feed this gateway's output watchdog; an older one is
/// superseded (a newer value of those outputs went through).
#[derive(Debug, Default)]
pub struct Writes {
    last: HashMap<WriterKey, (u64, WriteReply)>,
}

impl Writes {
    /// Carries out `w` unless it is a repeat; the answer, and whether it was a repeat. A
    /// write refused whole is answered with every value it carried refused, and why.
    pub fn apply(&mut self, gw: &str, registry: &Registry, w: &Write) -> (WriteReply, bool) {
        let key = (w.writer.clone(), w.session, w.interface, w.device.clone());
        if w.seq != 0
            && let Some((seq, reply)) = self.last.get(&key)
            && w.seq <= *seq
        {
            let reply = if w.seq == *seq {
                reply.clone()
            } else {
                WriteReply {
                    refused: Vec::new(),
                }
            };
            return (reply, true);
        }
        let r = match write(gw, registry, w) {
            Ok(r) => r,
            Err(e) => {
                // Refused whole: every value refused with why, bounded (a legitimate writer
                // names each of a device's channels once, at most MAX_CHANNELS), the why cut
                // short; nothing was written, so nothing is remembered either.
                let e = device_interface::text::Cut(&e.to_string()).to_string();
                let refused = w
                    .values
                    .iter()
                    .take(crate::config::MAX_CHANNELS as usize)
                    .map(|(ch, _)| (*ch, e.clone()))
                    .collect();
                return (WriteReply { refused }, false);
            }
        };
        // Remembered only under names a gateway and a device can have (a hostile peer's
        // megabyte-long writer name is not kept).
        if w.seq != 0 && key.0.len() <= MAX_NAME && key.3.len() <= MAX_NAME {
            if self.last.len() >= MAX_WRITERS && !self.last.contains_key(&key) {
                self.last.clear();
            }
            self.last.insert(key, (w.seq, r.clone()));
        }
        (r, false)
    }
}
