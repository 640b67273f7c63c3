//! The channels a northbound server serves (MQTT metrics, OPC UA variables): every
//! channel of the registry's devices with its IO component and port (what `hwgw get`
//! names, where `hwgw set` writes), read straight from the device registry — the values
//! the cards keep anyway, so serving them costs the real-time threads nothing.

use device_interface::{
    AnalogIn, AnalogOut, AnalogRange, DeviceError, DigitalIn, DigitalOut, Encoder, Interface,
    Registry, RegistryEntry,
};
use rtt::info::Direction;
use std::sync::Arc;

/// A channel's value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Value {
    /// An analog channel.
    F64(f64),
    /// A digital channel.
    Bool(bool),
    /// An encoder's position or turn.
    I64(i64),
}

impl Value {
    /// As JSON (a float round-trips: the workspace's serde_json has `float_roundtrip`;
    /// a value JSON cannot carry, NaN or infinite, is null).
    pub fn json(self) -> serde_json::Value {
        match self {
            Value::F64(v) => {
                serde_json::Number::from_f64(v).map_or(serde_json::Value::Null, Into::into)
            }
            Value::Bool(b) => b.into(),
            Value::I64(i) => i.into(),
        }
    }
}

/// Where a channel's value is read.
#[derive(Clone)]
pub enum Source {
    /// An analog input's channel.
    Ai(Arc<dyn AnalogIn>, u32),
    /// An analog output's channel (its read-back).
    Ao(Arc<dyn AnalogOut>, u32),
    /// A digital input's channel.
    Di(Arc<dyn DigitalIn>, u32),
    /// A digital output's channel (its read-back).
    Do(Arc<dyn DigitalOut>, u32),
    /// An encoder's position.
    Position(Arc<dyn Encoder>),
    /// An encoder's turn count.
    Turn(Arc<dyn Encoder>),
}

impl Source {
    /// The channel's value now: an input's newest sample, an output's read-back.
    pub fn read(&self) -> Result<Value, DeviceError> {
        Ok(match self {
            Source::Ai(d, c) => Value::F64(d.read(*c)?),
            Source::Ao(d, c) => Value::F64(d.read_back(*c)?),
            Source::Di(d, c) => Value::Bool(d.read_bit(*c)?),
            Source::Do(d, c) => Value::Bool(d.check_bit(*c)?),
            Source::Position(e) => Value::I64(e.position()?),
            Source::Turn(e) => Value::I64(e.turn()?),
        })
    }

    /// An input, or which kind of output.
    pub fn kind(&self) -> Kind {
        match self {
            Source::Ao(..) => Kind::AnalogOut,
            Source::Do(..) => Kind::DigitalOut,
            _ => Kind::Input,
        }
    }
}

/// What a channel is, for writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// An input (or an encoder): not written.
    Input,
    /// An analog output.
    AnalogOut,
    /// A digital output.
    DigitalOut,
}

/// Why a device's channels could not be found.
#[derive(Debug, thiserror::Error)]
pub enum ChannelsError {
    /// The device's IO component is not in the runtime.
    #[error("device {device:?} has no IO component: {why}")]
    NoComponent {
        /// The device.
        device: String,
        /// Why.
        why: String,
    },
    /// The device left the registry while it was looked at.
    #[error("device {0:?} left the registry")]
    Gone(String),
    /// A channel has no port on the IO component.
    #[error("{component} has no port for channel {channel}")]
    NoPort {
        /// The IO component.
        component: String,
        /// The channel.
        channel: u32,
    },
}

/// One channel of a device.
#[derive(Clone)]
pub struct Channel {
    /// Its IO component (`sim0.ai`).
    pub component: String,
    /// Its port (`ch0`).
    pub port: String,
    /// Where it is read.
    pub source: Source,
    /// An analog channel's range and unit.
    pub range: Option<AnalogRange>,
}

impl Channel {
    /// `component.port`.
    pub fn address(&self) -> String {
        format!("{}.{}", self.component, self.port)
    }
}

/// The registry's devices a server serves: every device that is no alias and no logical
/// device, or those named in `chosen` (when not empty); each name of `chosen` that is no
/// such device as `(its index, why)`.
pub fn devices(
    registry: &Registry,
    chosen: &[String],
) -> (Vec<RegistryEntry>, Vec<(usize, String)>) {
    let mut entries: Vec<_> = registry
        .entries()
        .into_iter()
        .filter(|e| e.info.alias_of.is_none() && !e.interface.is_logical())
        .collect();
    let mut problems = Vec::new();
    for (i, d) in chosen.iter().enumerate() {
        if !entries.iter().any(|e| &e.info.name == d) {
            let mut names: Vec<_> = entries.iter().map(|e| e.info.name.clone()).collect();
            names.dedup();
            problems.push((
                i,
                format!("no device {d:?}; the devices: {}", names.join(", ")),
            ));
        }
    }
    if !chosen.is_empty() {
        entries.retain(|e| chosen.contains(&e.info.name));
    }
    (entries, problems)
}

/// The IO component of registry device `name` under `interface` (`sim0.ai`; an encoder's
/// is its own name), and the direction of its channel ports; `None` for an interface
/// without channels.
pub fn io_component(interface: Interface, name: &str) -> Option<(String, Direction)> {
    let (suffix, direction) = match interface {
        Interface::AnalogIn => ("ai", Direction::Output),
        Interface::AnalogOut => ("ao", Direction::Input),
        Interface::DigitalIn => ("di", Direction::Output),
        Interface::DigitalOut => ("do", Direction::Input),
        Interface::Encoder => return Some((name.to_string(), Direction::Output)),
        Interface::Sensor | Interface::Drive | Interface::Axis => return None,
    };
    Some((format!("{name}.{suffix}"), direction))
}

/// The channels of registry device `name` under `interface`: its IO component's ports in
/// channel order, each with its source; an error when its IO component is missing.
pub fn of_device(
    registry: &Registry,
    rt: &rtt::Runtime,
    interface: Interface,
    name: &str,
) -> Result<Vec<Channel>, ChannelsError> {
    let Some((component, direction)) = io_component(interface, name) else {
        return Ok(Vec::new());
    };
    let task = rt
        .component(&component)
        .map_err(|e| ChannelsError::NoComponent {
            device: name.into(),
            why: e.to_string(),
        })?;
    let ports: Vec<String> = task
        .ports()
        .into_iter()
        .filter(|p| p.direction == direction)
        .map(|p| p.name)
        .collect();
    let gone = || ChannelsError::Gone(name.into());
    let sources: Vec<(Source, Option<AnalogRange>)> = match interface {
        Interface::AnalogIn => {
            let d = registry.analog_in().get(name).ok_or_else(gone)?;
            let range = |c| d.range(c).ok();
            (0..d.channel_count())
                .map(|c| (Source::Ai(d.clone(), c), range(c)))
                .collect()
        }
        Interface::AnalogOut => {
            let d = registry.analog_out().get(name).ok_or_else(gone)?;
            let range = |c| d.range(c).ok();
            (0..d.channel_count())
                .map(|c| (Source::Ao(d.clone(), c), range(c)))
                .collect()
        }
        Interface::DigitalIn => {
            let d = registry.digital_in().get(name).ok_or_else(gone)?;
            (0..d.input_count())
                .map(|c| (Source::Di(d.clone(), c), None))
                .collect()
        }
        Interface::DigitalOut => {
            let d = registry.digital_out().get(name).ok_or_else(gone)?;
            (0..d.output_count())
                .map(|c| (Source::Do(d.clone(), c), None))
                .collect()
        }
        Interface::Encoder => {
            let d = registry.encoder().get(name).ok_or_else(gone)?;
            let channel = |port: &str, source| Channel {
                component: component.clone(),
                port: port.into(),
                source,
                range: None,
            };
            return Ok(vec![
                channel("position", Source::Position(d.clone())),
                channel("turn", Source::Turn(d)),
            ]);
        }
        Interface::Sensor | Interface::Drive | Interface::Axis => Vec::new(),
    };
    (0u32..)
        .zip(sources)
        .map(|(c, (source, range))| {
            let port = ports
                .get(c as usize)
                .cloned()
                .ok_or_else(|| ChannelsError::NoPort {
                    component: component.clone(),
                    channel: c,
                })?;
            Ok(Channel {
                component: component.clone(),
                port,
                source,
                range,
            })
        })
        .collect()
}
