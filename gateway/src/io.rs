//! IO components: every registered device as a component, like OCL's IOComponent.
//!
//! Inputs (AnalogIn, DigitalIn, Encoder) are sampled into output ports at a period; outputs
//! (AnalogOut, DigitalOut) are written from event input ports as soon as new data arrives.
//! Each device's methods are operations. Names: `<device>.ai`, `.ao`, `.di`, `.do` for the
//! channel interfaces and `<encoder name>` for an encoder; ports `ch0…`, `bit0…`,
//! `position`/`turn`.
//!
//! Operation results are `{"Ok": value}` or `{"Err": "message"}`: a device error is an
//! answer, not a failed call.

use crate::config::ChannelNames;
use device_interface::{AnalogIn, AnalogOut, DigitalIn, DigitalOut, Encoder};
use rtt::port::{FlowStatus, InputPort, OutputPort};
use rtt::{ActivitySpec, Component, Context, HookResult, Runtime, RuntimeError, TaskContext};
use std::sync::Arc;
use std::time::Duration;

type Answer<T> = Result<T, String>;

fn answer<T>(r: Result<T, device_interface::DeviceError>) -> Answer<T> {
    r.map_err(|e| e.to_string())
}

struct AnalogInIo {
    device: Arc<dyn AnalogIn>,
    ports: Vec<OutputPort<f64>>,
    errors: u64,
}

impl Component for AnalogInIo {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        for (c, port) in self.ports.iter_mut().enumerate() {
            // A stale or offline input is not written: readers see old data, and the
            // device's health says why.
            match self.device.read(c as u32) {
                Ok(v) => port.write(&v),
                Err(_) => self.errors += 1,
            }
        }
        Ok(())
    }
}

struct AnalogOutIo {
    device: Arc<dyn AnalogOut>,
    ports: Vec<InputPort<f64>>,
}

impl Component for AnalogOutIo {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        let mut v = 0.0;
        for (c, port) in self.ports.iter_mut().enumerate() {
            if port.read(&mut v) == FlowStatus::NewData
                && let Err(e) = self.device.write(c as u32, v)
            {
                tracing::warn!("analog output {c}: {v} not written: {e}");
            }
        }
        Ok(())
    }
}

struct DigitalInIo {
    device: Arc<dyn DigitalIn>,
    ports: Vec<OutputPort<bool>>,
}

impl Component for DigitalInIo {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        for (b, port) in self.ports.iter_mut().enumerate() {
            if let Ok(v) = self.device.read_bit(b as u32) {
                port.write(&v);
            }
        }
        Ok(())
    }
}

struct DigitalOutIo {
    device: Arc<dyn DigitalOut>,
    ports: Vec<InputPort<bool>>,
}

impl Component for DigitalOutIo {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        let mut v = false;
        for (b, port) in self.ports.iter_mut().enumerate() {
            if port.read(&mut v) == FlowStatus::NewData
                && let Err(e) = self.device.set_bit(b as u32, v)
            {
                tracing::warn!("digital output {b}: not set: {e}");
            }
        }
        Ok(())
    }
}

struct EncoderIo {
    device: Arc<dyn Encoder>,
    position: OutputPort<i64>,
    turn: OutputPort<i64>,
}

impl Component for EncoderIo {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        if let (Ok(p), Ok(t)) = (self.device.position(), self.device.turn()) {
            self.position.write(&p);
            self.turn.write(&t);
        }
        Ok(())
    }
}

/// Builds the IO components of every device `card` registered, sampling inputs every
/// `sample`. Returns them in a start order.
pub fn build(
    runtime: &Runtime,
    card: &str,
    sample: Duration,
    names: &ChannelNames,
) -> Result<Vec<TaskContext>, RuntimeError> {
    let registry = runtime.registry().clone();
    let mine = |owner: &str, alias: &Option<String>| owner == card && alias.is_none();
    let mut out = Vec::new();
    for e in registry.entries() {
        if !mine(&e.info.owner, &e.info.alias_of) {
            continue;
        }
        let name = e.info.name.clone();
        use device_interface::Interface as I;
        let task = match e.interface {
            I::AnalogIn => {
                let Some(device) = registry.analog_in().get(&name) else {
                    continue;
                };
                let port_names = names.analog_in.clone();
                runtime.add(
                    &format!("{name}.ai"),
                    ActivitySpec::periodic(sample),
                    false,
                    move |iface| {
                        let n = device.channel_count();
                        let ports = (0..n)
                            .map(|c| {
                                iface.output(
                                    &ChannelNames::port(&port_names, "ch", c),
                                    &format!("analog input {c}, physical units"),
                                )
                            })
                            .collect::<Result<_, _>>()?;
                        let d = device.clone();
                        iface.client_operation(
                            "read",
                            "reads a channel in physical units",
                            &[("channel", "")],
                            move |(c,): (u32,)| answer(d.read(c)),
                        )?;
                        let d = device.clone();
                        iface.client_operation(
                            "read_raw",
                            "reads a channel's raw value",
                            &[("channel", "")],
                            move |(c,): (u32,)| answer(d.read_raw(c)),
                        )?;
                        let d = device.clone();
                        iface.client_operation(
                            "range",
                            "lowest, highest and unit of a channel",
                            &[("channel", "")],
                            move |(c,): (u32,)| {
                                answer(d.range(c))
                                    .map(|r| (r.lowest, r.highest, r.unit.to_string()))
                            },
                        )?;
                        let d = device.clone();
                        iface.client_operation(
                            "health",
                            "online/stale/offline and sample age",
                            &[],
                            move |(): ()| health(d.health()),
                        )?;
                        Ok(AnalogInIo {
                            device,
                            ports,
                            errors: 0,
                        })
                    },
                )?
            }
            I::AnalogOut => {
                let Some(device) = registry.analog_out().get(&name) else {
                    continue;
                };
                let port_names = names.analog_out.clone();
                runtime.add(
                    &format!("{name}.ao"),
                    ActivitySpec::non_periodic(),
                    false,
                    move |iface| {
                        let n = device.channel_count();
                        let ports = (0..n)
                            .map(|c| {
                                iface.event_input(
                                    &ChannelNames::port(&port_names, "ch", c),
                                    &format!("analog output {c}, physical units"),
                                )
                            })
                            .collect::<Result<_, _>>()?;
                        let d = device.clone();
                        iface.client_operation(
                            "write",
                            "writes a channel in physical units",
                            &[("channel", ""), ("value", "")],
                            move |(c, v): (u32, f64)| answer(d.write(c, v)),
                        )?;
                        let d = device.clone();
                        iface.client_operation(
                            "read_back",
                            "the value last written",
                            &[("channel", "")],
                            move |(c,): (u32,)| answer(d.read_back(c)),
                        )?;
                        let d = device.clone();
                        iface.client_operation(
                            "health",
                            "online/stale/offline and sample age",
                            &[],
                            move |(): ()| health(d.health()),
                        )?;
                        Ok(AnalogOutIo { device, ports })
                    },
                )?
            }
            I::DigitalIn => {
                let Some(device) = registry.digital_in().get(&name) else {
                    continue;
                };
                let port_names = names.digital_in.clone();
                runtime.add(
                    &format!("{name}.di"),
                    ActivitySpec::periodic(sample),
                    false,
                    move |iface| {
                        let n = device.input_count();
                        let ports = (0..n)
                            .map(|b| {
                                iface.output(
                                    &ChannelNames::port(&port_names, "bit", b),
                                    &format!("digital input {b}"),
                                )
                            })
                            .collect::<Result<_, _>>()?;
                        let d = device.clone();
                        iface.client_operation(
                            "read_bit",
                            "reads one input",
                            &[("bit", "")],
                            move |(b,): (u32,)| answer(d.read_bit(b)),
                        )?;
                        let d = device.clone();
                        iface.client_operation(
                            "read_sequence",
                            "inputs start..=stop, start at bit 0",
                            &[("start", ""), ("stop", "")],
                            move |(a, b): (u32, u32)| answer(d.read_sequence(a, b)),
                        )?;
                        Ok(DigitalInIo { device, ports })
                    },
                )?
            }
            I::DigitalOut => {
                let Some(device) = registry.digital_out().get(&name) else {
                    continue;
                };
                let port_names = names.digital_out.clone();
                runtime.add(
                    &format!("{name}.do"),
                    ActivitySpec::non_periodic(),
                    false,
                    move |iface| {
                        let n = device.output_count();
                        let ports = (0..n)
                            .map(|b| {
                                iface.event_input(
                                    &ChannelNames::port(&port_names, "bit", b),
                                    &format!("digital output {b}"),
                                )
                            })
                            .collect::<Result<_, _>>()?;
                        let d = device.clone();
                        iface.client_operation(
                            "set_bit",
                            "sets one output",
                            &[("bit", ""), ("value", "")],
                            move |(b, v): (u32, bool)| answer(d.set_bit(b, v)),
                        )?;
                        let d = device.clone();
                        iface.client_operation(
                            "check_bit",
                            "the state an output was set to",
                            &[("bit", "")],
                            move |(b,): (u32,)| answer(d.check_bit(b)),
                        )?;
                        let d = device.clone();
                        iface.client_operation(
                            "set_sequence",
                            "sets outputs start..=stop from a value, bit 0 at start",
                            &[("start", ""), ("stop", ""), ("value", "")],
                            move |(a, b, v): (u32, u32, u64)| answer(d.set_sequence(a, b, v)),
                        )?;
                        let d = device.clone();
                        iface.client_operation(
                            "check_sequence",
                            "outputs start..=stop, start at bit 0",
                            &[("start", ""), ("stop", "")],
                            move |(a, b): (u32, u32)| answer(d.check_sequence(a, b)),
                        )?;
                        Ok(DigitalOutIo { device, ports })
                    },
                )?
            }
            I::Encoder => {
                let Some(device) = registry.encoder().get(&name) else {
                    continue;
                };
                runtime.add(&name, ActivitySpec::periodic(sample), false, move |iface| {
                    let d = device.clone();
                    iface.client_operation(
                        "set_position",
                        "sets the position within the turn",
                        &[("position", "")],
                        move |(p,): (i64,)| answer(d.set_position(p)),
                    )?;
                    let d = device.clone();
                    iface.client_operation(
                        "set_turn",
                        "sets the turn count",
                        &[("turn", "")],
                        move |(t,): (i64,)| answer(d.set_turn(t)),
                    )?;
                    Ok(EncoderIo {
                        position: iface.output("position", "position within the turn")?,
                        turn: iface.output("turn", "turns")?,
                        device,
                    })
                })?
            }
        };
        out.push(task);
    }
    Ok(out)
}

fn health(h: device_interface::Health) -> (String, Option<f64>, Option<String>) {
    (
        h.status.to_string(),
        h.age().map(|a| a.as_secs_f64()),
        h.last_error.map(|e| e.to_string()),
    )
}
