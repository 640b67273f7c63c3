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
use rtt::component::IntrospectError;
use rtt::port::{FlowStatus, InputPort, OutputPort};
use rtt::{
    ActivitySpec, Component, Context, HookResult, InterfaceBuilder, Runtime, RuntimeError,
    TaskContext,
};
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

/// One port per channel, named from `names` (else `prefix{i}`).
fn ports<T>(
    n: u32,
    names: &[String],
    prefix: &str,
    doc: &str,
    mut make: impl FnMut(&str, &str) -> Result<T, IntrospectError>,
) -> Result<Vec<T>, IntrospectError> {
    (0..n)
        .map(|i| make(&ChannelNames::port(names, prefix, i), &format!("{doc} {i}")))
        .collect()
}

/// Offers device method `f` as a ClientThread operation: arguments `A`, answer
/// `{"Ok": r}` or `{"Err": message}`.
fn device_op<C, D, A, R>(
    iface: &mut InterfaceBuilder<C>,
    device: &Arc<D>,
    name: &str,
    doc: &str,
    args: &[(&str, &str)],
    f: fn(&D, A) -> Result<R, device_interface::DeviceError>,
) -> Result<(), IntrospectError>
where
    C: Component,
    D: ?Sized + Send + Sync + 'static,
    A: rtt::operation::Args,
    R: serde::Serialize + 'static,
{
    let d = device.clone();
    iface.client_operation(name, doc, args, move |a: A| answer(f(&d, a)))
}

/// Builds the IO components of every device `card` registered, sampling inputs every
/// `sample`, naming channel ports from `names`. Returns them in a start order.
pub fn build(
    runtime: &Runtime,
    card: &str,
    sample: Duration,
    names: &ChannelNames,
) -> Result<Vec<TaskContext>, RuntimeError> {
    use device_interface::Interface as I;
    let registry = runtime.registry().clone();
    let mut out = Vec::new();
    for e in registry.entries() {
        if e.info.owner != card || e.info.alias_of.is_some() {
            continue;
        }
        let name = e.info.name.clone();
        let ch: &[(&str, &str)] = &[("channel", "")];
        let task = match e.interface {
            I::AnalogIn => {
                let Some(device) = registry.analog_in().get(&name) else {
                    continue;
                };
                let port_names = names.analog_in.clone();
                runtime.add(
                    &format!("{name}.ai"),
                    ActivitySpec::periodic(sample),
                    rtt::InitialState::Stopped,
                    move |iface| {
                        let ports = ports(
                            device.channel_count(),
                            &port_names,
                            "ch",
                            "analog input in physical units, channel",
                            |n, d| iface.output(n, d),
                        )?;
                        device_op(
                            iface,
                            &device,
                            "read",
                            "reads a channel in physical units",
                            ch,
                            |d, (c,): (u32,)| d.read(c),
                        )?;
                        device_op(
                            iface,
                            &device,
                            "read_raw",
                            "reads a channel's raw value",
                            ch,
                            |d, (c,): (u32,)| d.read_raw(c),
                        )?;
                        device_op(
                            iface,
                            &device,
                            "range",
                            "lowest, highest and unit of a channel",
                            ch,
                            |d, (c,): (u32,)| {
                                d.range(c)
                                    .map(|r| (r.lowest, r.highest, r.unit.to_string()))
                            },
                        )?;
                        device_op(
                            iface,
                            &device,
                            "health",
                            "online/stale/offline and sample age",
                            &[],
                            |d, (): ()| Ok(health(d.health())),
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
                    rtt::InitialState::Stopped,
                    move |iface| {
                        let ports = ports(
                            device.channel_count(),
                            &port_names,
                            "ch",
                            "analog output in physical units, channel",
                            |n, d| iface.event_input(n, d),
                        )?;
                        device_op(
                            iface,
                            &device,
                            "write",
                            "writes a channel in physical units",
                            &[("channel", ""), ("value", "")],
                            |d, (c, v): (u32, f64)| d.write(c, v),
                        )?;
                        device_op(
                            iface,
                            &device,
                            "read_back",
                            "the value last written",
                            ch,
                            |d, (c,): (u32,)| d.read_back(c),
                        )?;
                        device_op(
                            iface,
                            &device,
                            "health",
                            "online/stale/offline and sample age",
                            &[],
                            |d, (): ()| Ok(health(d.health())),
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
                    rtt::InitialState::Stopped,
                    move |iface| {
                        let ports = ports(
                            device.input_count(),
                            &port_names,
                            "bit",
                            "digital input",
                            |n, d| iface.output(n, d),
                        )?;
                        device_op(
                            iface,
                            &device,
                            "read_bit",
                            "reads one input",
                            &[("bit", "")],
                            |d, (b,): (u32,)| d.read_bit(b),
                        )?;
                        device_op(
                            iface,
                            &device,
                            "read_sequence",
                            "inputs start..=stop, start at bit 0",
                            &[("start", ""), ("stop", "")],
                            |d, (a, b): (u32, u32)| d.read_sequence(a, b),
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
                    rtt::InitialState::Stopped,
                    move |iface| {
                        let ports = ports(
                            device.output_count(),
                            &port_names,
                            "bit",
                            "digital output",
                            |n, d| iface.event_input(n, d),
                        )?;
                        device_op(
                            iface,
                            &device,
                            "set_bit",
                            "sets one output",
                            &[("bit", ""), ("value", "")],
                            |d, (b, v): (u32, bool)| d.set_bit(b, v),
                        )?;
                        device_op(
                            iface,
                            &device,
                            "check_bit",
                            "the state an output was set to",
                            &[("bit", "")],
                            |d, (b,): (u32,)| d.check_bit(b),
                        )?;
                        device_op(
                            iface,
                            &device,
                            "set_sequence",
                            "sets outputs start..=stop from a value, bit 0 at start",
                            &[("start", ""), ("stop", ""), ("value", "")],
                            |d, (a, b, v): (u32, u32, u64)| d.set_sequence(a, b, v),
                        )?;
                        device_op(
                            iface,
                            &device,
                            "check_sequence",
                            "outputs start..=stop, start at bit 0",
                            &[("start", ""), ("stop", "")],
                            |d, (a, b): (u32, u32)| d.check_sequence(a, b),
                        )?;
                        Ok(DigitalOutIo { device, ports })
                    },
                )?
            }
            I::Encoder => {
                let Some(device) = registry.encoder().get(&name) else {
                    continue;
                };
                runtime.add(
                    &name,
                    ActivitySpec::periodic(sample),
                    rtt::InitialState::Stopped,
                    move |iface| {
                        device_op(
                            iface,
                            &device,
                            "set_position",
                            "sets the position within the turn",
                            &[("position", "")],
                            |d, (p,): (i64,)| d.set_position(p),
                        )?;
                        device_op(
                            iface,
                            &device,
                            "set_turn",
                            "sets the turn count",
                            &[("turn", "")],
                            |d, (t,): (i64,)| d.set_turn(t),
                        )?;
                        Ok(EncoderIo {
                            position: iface.output("position", "position within the turn")?,
                            turn: iface.output("turn", "turns")?,
                            device,
                        })
                    },
                )?
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
