//! IO components: every registered device as a component, like OCL's IOComponent.
//!
//! Inputs (AnalogIn, DigitalIn, Encoder) are sampled into output ports at a period; outputs
//! (AnalogOut, DigitalOut) are written from event input ports as soon as new data arrives,
//! and those ports read back the device's output (`hwgw get sim0.ao ch0`). Each device's
//! methods are operations. Names: `<device>.ai`, `.ao`, `.di`, `.do` for the channel
//! interfaces and `<encoder name>` for an encoder; ports `ch0…`, `bit0…` (or the card's
//! channel names), `position`/`turn`.
//!
//! Operation results are `{"Ok": value}` or `{"Err": "message"}`: a device error is an
//! answer, not a failed call.

use crate::config::ChannelNames;
use device_interface::{
    AnalogIn, AnalogOut, Delivery, Device, DeviceError, DigitalIn, DigitalOut, Encoder, Health,
    Interface,
};
use driver_api::{ChannelDetail, ChannelDetails};
use rtt::component::{IntrospectError, PortData};
use rtt::port::{FlowStatus, InputPort, OutputPort};
use rtt::{
    ActivitySpec, Component, Context, HookResult, InitialState, InterfaceBuilder, Runtime,
    RuntimeError, TaskContext,
};
use std::sync::Arc;
use std::time::Duration;

/// A channel interface seen from its IO component: how many channels, how a channel is
/// read (inputs) or written and read back (outputs), and which methods become operations.
trait Channels: Device + Send + Sync + 'static {
    /// What a channel carries.
    type Value: PortData + Default + Copy;
    /// Component name suffix: `ai`, `ao`, `di`, `do`.
    const SUFFIX: &'static str;
    /// Port name prefix for unnamed channels.
    const PREFIX: &'static str;
    /// Port documentation, before the channel number.
    const DOC: &'static str;
    /// Number of channels.
    fn count(&self) -> u32;
    /// Reads channel `c` (an input), or reads back what it was set to (an output).
    fn get(&self, c: u32) -> Result<Self::Value, DeviceError>;
    /// Adds the device's methods as operations.
    fn operations<C: Send + 'static>(
        d: &Arc<Self>,
        iface: &mut InterfaceBuilder<C>,
    ) -> Result<(), IntrospectError>;
}

/// An output channel interface: its channels are written.
trait Writable: Channels {
    /// Writes channel `c`.
    fn put(&self, c: u32, v: Self::Value) -> Result<(), DeviceError>;
    /// `Ok` when channel `c` would take `v` (in range; the channel exists).
    fn accepts(&self, c: u32, v: Self::Value) -> Result<(), DeviceError>;
    /// Where the writes to channel `c` stand (see [`device_interface::Delivery`]).
    fn delivery(&self, c: u32) -> Option<Delivery>;
}

/// The longest a `set` waits to hear whether its write reached a device whose bus
/// carries writes later (a Modbus line, another gateway): less than the CLI's default
/// reply timeout, so the answer says what happened rather than the client giving up.
const DELIVERY_WAIT: Duration = Duration::from_secs(8);

/// Writes `v` to channel `c` of `device` for a `set` from outside, and waits until the
/// device's bus has delivered it or failed it (at most [`DELIVERY_WAIT`]).
fn apply<D: ?Sized + Writable>(device: &D, c: u32, v: D::Value) -> Result<(), DeviceError> {
    device.put(c, v)?;
    delivered(device, c)
}

/// Waits until the newest write to channel `c` of `device` is delivered or failed, for a
/// device whose bus carries writes later (at once for the others; at most
/// [`DELIVERY_WAIT`]). Blocks: for the control socket's threads and the operations it
/// calls, never a real-time path (components write devices directly).
fn delivered<D: ?Sized + Writable>(device: &D, c: u32) -> Result<(), DeviceError> {
    let Some(d) = device.delivery(c) else {
        return Ok(());
    };
    let n = d.taken;
    let start = std::time::Instant::now();
    let mut pause = Duration::from_micros(100);
    loop {
        match device.delivery(c).and_then(|d| d.outcome(n)) {
            Some(r) => return r,
            None if start.elapsed() >= DELIVERY_WAIT => {
                return Err(DeviceError::Undelivered {
                    reason: "still on its way after 8 s (the device's bus has not answered)",
                });
            }
            None => {
                std::thread::sleep(pause);
                pause = (pause * 2).min(Duration::from_millis(5));
            }
        }
    }
}

/// Offers device method `f` as a ClientThread operation: arguments `A`, answer
/// `{"Ok": r}` or `{"Err": message}`.
pub(crate) fn device_op<C, D, A, R>(
    iface: &mut InterfaceBuilder<C>,
    device: &Arc<D>,
    name: &str,
    doc: &str,
    args: &[(&str, &str)],
    f: fn(&D, A) -> Result<R, DeviceError>,
) -> Result<(), IntrospectError>
where
    C: Send + 'static,
    D: ?Sized + Send + Sync + 'static,
    A: rtt::operation::Args,
    R: serde::Serialize + Send + 'static,
{
    let d = device.clone();
    iface.client_operation(name, doc, args, move |a: A| {
        f(&d, a).map_err(|e| e.to_string())
    })
}

fn health(h: Health) -> (String, Option<f64>, Option<String>) {
    (
        h.status.to_string(),
        h.age().map(|a| a.as_secs_f64()),
        h.last_error.map(|e| e.to_string()),
    )
}

/// Offers the device's health as an operation (every IO component has it).
pub(crate) fn health_op<C, D>(
    iface: &mut InterfaceBuilder<C>,
    device: &Arc<D>,
) -> Result<(), IntrospectError>
where
    C: Send + 'static,
    D: ?Sized + Device + 'static,
{
    device_op(
        iface,
        device,
        "health",
        "online/stale/offline, sample age and last error",
        &[],
        |d, ()| Ok(health(d.health())),
    )
}

const CH: &[(&str, &str)] = &[("channel", "")];

impl Channels for dyn AnalogIn {
    type Value = f64;
    const SUFFIX: &'static str = "ai";
    const PREFIX: &'static str = "ch";
    const DOC: &'static str = "analog input in physical units, channel";
    fn count(&self) -> u32 {
        self.channel_count()
    }
    fn get(&self, c: u32) -> Result<f64, DeviceError> {
        self.read(c)
    }
    fn operations<C: Send + 'static>(
        d: &Arc<Self>,
        i: &mut InterfaceBuilder<C>,
    ) -> Result<(), IntrospectError> {
        device_op(
            i,
            d,
            "read",
            "reads a channel in physical units",
            CH,
            |d, (c,)| d.read(c),
        )?;
        device_op(
            i,
            d,
            "read_raw",
            "reads a channel's raw value",
            CH,
            |d, (c,)| d.read_raw(c),
        )?;
        device_op(
            i,
            d,
            "range",
            "lowest, highest and unit of a channel",
            CH,
            |d, (c,)| {
                d.range(c)
                    .map(|r| (r.lowest, r.highest, r.unit.to_string()))
            },
        )
    }
}

impl Channels for dyn AnalogOut {
    type Value = f64;
    const SUFFIX: &'static str = "ao";
    const PREFIX: &'static str = "ch";
    const DOC: &'static str = "analog output in physical units, channel";
    fn count(&self) -> u32 {
        self.channel_count()
    }
    fn get(&self, c: u32) -> Result<f64, DeviceError> {
        self.read_back(c)
    }
    fn operations<C: Send + 'static>(
        d: &Arc<Self>,
        i: &mut InterfaceBuilder<C>,
    ) -> Result<(), IntrospectError> {
        let write_args = &[("channel", ""), ("value", "")];
        device_op(
            i,
            d,
            "write",
            "writes a channel in physical units; answers once the device has it (a bus that \
             carries writes later: delivered or failed, 8 s at most)",
            write_args,
            |d, (c, v)| {
                d.write(c, v)?;
                delivered(d, c)
            },
        )?;
        device_op(
            i,
            d,
            "read_back",
            "the value last written",
            CH,
            |d, (c,)| d.read_back(c),
        )
    }
}

impl Channels for dyn DigitalIn {
    type Value = bool;
    const SUFFIX: &'static str = "di";
    const PREFIX: &'static str = "bit";
    const DOC: &'static str = "digital input";
    fn count(&self) -> u32 {
        self.input_count()
    }
    fn get(&self, b: u32) -> Result<bool, DeviceError> {
        self.read_bit(b)
    }
    fn operations<C: Send + 'static>(
        d: &Arc<Self>,
        i: &mut InterfaceBuilder<C>,
    ) -> Result<(), IntrospectError> {
        device_op(
            i,
            d,
            "read_bit",
            "reads one input",
            &[("bit", "")],
            |d, (b,)| d.read_bit(b),
        )?;
        let span = &[("start", ""), ("stop", "")];
        device_op(
            i,
            d,
            "read_sequence",
            "inputs start..=stop, start at bit 0",
            span,
            |d, (a, b)| d.read_sequence(a, b),
        )
    }
}

impl Channels for dyn DigitalOut {
    type Value = bool;
    const SUFFIX: &'static str = "do";
    const PREFIX: &'static str = "bit";
    const DOC: &'static str = "digital output";
    fn count(&self) -> u32 {
        self.output_count()
    }
    fn get(&self, b: u32) -> Result<bool, DeviceError> {
        self.check_bit(b)
    }
    fn operations<C: Send + 'static>(
        d: &Arc<Self>,
        i: &mut InterfaceBuilder<C>,
    ) -> Result<(), IntrospectError> {
        let bit = &[("bit", "")];
        let span = &[("start", ""), ("stop", "")];
        device_op(
            i,
            d,
            "set_bit",
            "sets one output; answers once the device has it (a bus that carries writes \
             later: delivered or failed, 8 s at most)",
            &[("bit", ""), ("value", "")],
            |d, (b, v)| {
                d.set_bit(b, v)?;
                delivered(d, b)
            },
        )?;
        device_op(
            i,
            d,
            "check_bit",
            "the state an output was set to",
            bit,
            |d, (b,)| d.check_bit(b),
        )?;
        let seq = &[("start", ""), ("stop", ""), ("value", "")];
        device_op(
            i,
            d,
            "set_sequence",
            "sets outputs start..=stop from a value, bit 0 at start; answers once the device \
             has them (a bus that carries writes later: delivered or failed, 8 s at most)",
            seq,
            |d, (a, b, v)| {
                d.set_sequence(a, b, v)?;
                (a..=b).try_for_each(|bit| delivered(d, bit))
            },
        )?;
        device_op(
            i,
            d,
            "check_sequence",
            "outputs start..=stop, start at bit 0",
            span,
            |d, (a, b)| d.check_sequence(a, b),
        )
    }
}

impl Writable for dyn AnalogOut {
    fn put(&self, c: u32, v: f64) -> Result<(), DeviceError> {
        self.write(c, v)
    }
    fn accepts(&self, c: u32, v: f64) -> Result<(), DeviceError> {
        self.scale(c)?.to_raw_checked(c, v).map(|_| ())
    }
    fn delivery(&self, c: u32) -> Option<Delivery> {
        AnalogOut::delivery(self, c)
    }
}

impl Writable for dyn DigitalOut {
    fn put(&self, b: u32, v: bool) -> Result<(), DeviceError> {
        self.set_bit(b, v)
    }
    fn accepts(&self, b: u32, _: bool) -> Result<(), DeviceError> {
        self.check_bit(b).map(|_| ())
    }
    fn delivery(&self, b: u32) -> Option<Delivery> {
        DigitalOut::delivery(self, b)
    }
}

/// Consecutive overruns after which a sampling IO component reports itself unhealthy (and
/// the systemd watchdog stops being fed).
pub const MAX_OVERRUNS: u32 = 10;

/// Samples a device's inputs into one output port per channel, every period; missed
/// readings count against the card's fault policy.
struct Sampled<D: ?Sized + Channels> {
    device: Arc<D>,
    ports: Vec<OutputPort<D::Value>>,
    faults: rtt::faults::FaultCounter,
}

impl<D: ?Sized + Channels> Sampled<D> {
    /// One sample of every channel; a step with a channel stale or offline is a missed
    /// reading.
    fn sample(&mut self, ctx: &mut Context<'_>) {
        let mut missed = false;
        for (c, port) in self.ports.iter_mut().enumerate() {
            // A stale or offline input is not written: readers see old data, and the
            // device's health says why.
            match self.device.get(c as u32) {
                Ok(v) => port.write(&v),
                Err(e) => missed |= e.is_transient(),
            }
        }
        if missed {
            self.faults.missed(ctx);
        } else {
            self.faults.good(ctx);
        }
    }
}

impl<D: ?Sized + Channels> Component for Sampled<D> {
    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        self.sample(ctx);
        Ok(())
    }

    fn error_hook(&mut self, ctx: &mut Context<'_>) {
        self.sample(ctx);
    }
}

/// Writes a device's outputs from one event input port per channel, as data arrives.
struct Driven<D: ?Sized + Writable> {
    device: Arc<D>,
    ports: Vec<InputPort<D::Value>>,
    /// Refused writes: counted, logged at most once a second.
    refused: u64,
    logged: u64,
    last_log: Option<std::time::Instant>,
}

impl<D: ?Sized + Writable> Driven<D> {
    /// Notes a refused write; says so in the log now and then, not once per sample.
    fn refused(&mut self, c: usize, e: &DeviceError) {
        self.refused += 1;
        if matches!(e, DeviceError::Held { .. }) {
            // The gateway is stopping: its outputs are held at their safe values on
            // purpose; counted, not reported.
            self.logged = self.refused;
            return;
        }
        let now = std::time::Instant::now();
        if self
            .last_log
            .is_none_or(|t| now.duration_since(t) >= Duration::from_secs(1))
        {
            let more = self.refused - self.logged - 1;
            let also = if more > 0 {
                format!(" ({more} more refused since the last report)")
            } else {
                String::new()
            };
            tracing::warn!("{} output {c}: not written: {e}{also}", D::SUFFIX);
            self.logged = self.refused;
            self.last_log = Some(now);
        }
    }
}

impl<D: ?Sized + Writable> Component for Driven<D> {
    fn start_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        // What was written into the ports while the component did not run is dropped, not
        // applied late: an output follows what is written while it runs.
        let mut v = D::Value::default();
        for port in &mut self.ports {
            while port.read(&mut v) == FlowStatus::NewData {}
        }
        Ok(())
    }

    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        let mut v = D::Value::default();
        for c in 0..self.ports.len() {
            if self.ports[c].read(&mut v) == FlowStatus::NewData
                && let Err(e) = self.device.put(c as u32, v)
            {
                self.refused(c, &e);
            }
        }
        Ok(())
    }
}

/// A channel port's documentation: what it is, and what the driver says of it.
fn port_doc(kind: &str, channel: u32, detail: Option<&ChannelDetail>) -> String {
    match detail.and_then(|d| d.doc.as_deref()) {
        Some(doc) => format!("{kind} {channel}: {doc}"),
        None => format!("{kind} {channel}"),
    }
}

/// Gives a channel port the value names the driver has for it, as the port's type carries
/// them (a digital port's 0 and 1 as false and true).
fn name_values<C: Send + 'static, V: serde::Serialize + 'static>(
    iface: &mut rtt::InterfaceBuilder<C>,
    port: &str,
    detail: Option<&ChannelDetail>,
) -> Result<(), IntrospectError> {
    let Some(d) = detail.filter(|d| !d.values.is_empty()) else {
        return Ok(());
    };
    let digital = std::any::TypeId::of::<V>() == std::any::TypeId::of::<bool>();
    let values = d
        .values
        .iter()
        .filter_map(|(v, name)| {
            let value = if digital {
                match *v {
                    0.0 => serde_json::Value::Bool(false),
                    1.0 => serde_json::Value::Bool(true),
                    _ => return None,
                }
            } else {
                serde_json::Number::from_f64(*v).map(serde_json::Value::Number)?
            };
            Some(rtt::component::NamedValue {
                name: name.clone(),
                value,
            })
        })
        .collect();
    iface.name_values(port, values)
}

/// The sampling IO component of input device `name`.
fn sampled<D: ?Sized + Channels>(
    runtime: &Runtime,
    name: &str,
    device: Arc<D>,
    (names, details): (&[String], &[ChannelDetail]),
    (sample, faults): (Duration, rtt::faults::FaultPolicy),
) -> Result<TaskContext, RuntimeError> {
    let names = names.to_vec();
    let details = details.to_vec();
    let component = format!("{name}.{}", D::SUFFIX);
    let spec = ActivitySpec::Periodic {
        period: sample,
        thread: rtt::ThreadOptions::default(),
        timing: rtt::Timing::Absolute,
        max_overruns: Some(MAX_OVERRUNS),
    };
    runtime.add(&component, spec, InitialState::Stopped, move |iface| {
        let ports = (0..device.count())
            .map(|c| {
                let port = ChannelNames::port(&names, D::PREFIX, c);
                let detail = details.get(c as usize);
                let p = iface.output(&port, &port_doc(D::DOC, c, detail))?;
                name_values::<_, D::Value>(iface, &port, detail)?;
                Ok(p)
            })
            .collect::<Result<_, IntrospectError>>()?;
        D::operations(&device, iface)?;
        health_op(iface, &device)?;
        Ok(Sampled {
            device,
            ports,
            faults: rtt::faults::FaultCounter::new(faults),
        })
    })
}

/// The driving IO component of output device `name`; its ports read the outputs back and
/// refuse, when written from outside, what the device would refuse.
fn driven<D: ?Sized + Writable>(
    runtime: &Runtime,
    name: &str,
    device: Arc<D>,
    (names, details): (&[String], &[ChannelDetail]),
) -> Result<TaskContext, RuntimeError> {
    let names = names.to_vec();
    let details = details.to_vec();
    let component = format!("{name}.{}", D::SUFFIX);
    runtime.add(
        &component,
        ActivitySpec::non_periodic(),
        InitialState::Stopped,
        move |iface| {
            let ports = (0..device.count())
                .map(|c| {
                    let port = ChannelNames::port(&names, D::PREFIX, c);
                    let (d, k, w) = (device.clone(), device.clone(), device.clone());
                    let detail = details.get(c as usize);
                    let p = iface.event_input_driving(
                        &port,
                        &port_doc(D::DOC, c, detail),
                        move || d.get(c).ok(),
                        move |v| k.accepts(c, *v).map_err(|e| e.to_string()),
                        move |v| apply(&*w, c, *v).map_err(|e| e.to_string()),
                    )?;
                    name_values::<_, D::Value>(iface, &port, detail)?;
                    Ok(p)
                })
                .collect::<Result<_, IntrospectError>>()?;
            D::operations(&device, iface)?;
            health_op(iface, &device)?;
            Ok(Driven {
                device,
                ports,
                refused: 0,
                logged: 0,
                last_log: None,
            })
        },
    )
}

/// Samples an encoder's position and turn.
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

fn encoder(
    runtime: &Runtime,
    name: &str,
    device: Arc<dyn Encoder>,
    sample: Duration,
) -> Result<TaskContext, RuntimeError> {
    runtime.add(
        name,
        ActivitySpec::periodic(sample),
        InitialState::Stopped,
        move |i| {
            let d = &device;
            device_op(
                i,
                d,
                "set_position",
                "sets the position within the turn",
                &[("position", "")],
                |d, (p,)| d.set_position(p),
            )?;
            device_op(
                i,
                d,
                "set_turn",
                "sets the turn count",
                &[("turn", "")],
                |d, (t,)| d.set_turn(t),
            )?;
            health_op(i, d)?;
            Ok(EncoderIo {
                position: i.output("position", "position within the turn")?,
                turn: i.output("turn", "turns")?,
                device,
            })
        },
    )
}

/// Builds the IO components of every device `card` registered, sampling inputs every
/// `sample` under fault policy `faults`, naming channel ports from `names`. Returns them
/// in a start order.
pub fn build(
    runtime: &Runtime,
    card: &str,
    (sample, faults): (Duration, rtt::faults::FaultPolicy),
    names: &ChannelNames,
    details: &ChannelDetails,
) -> Result<Vec<TaskContext>, RuntimeError> {
    let registry = runtime.registry().clone();
    let mut out = Vec::new();
    for e in registry.entries() {
        if e.info.owner != card || e.info.alias_of.is_some() {
            continue;
        }
        let n = e.info.name.as_str();
        let task = match e.interface {
            Interface::AnalogIn => registry.analog_in().get(n).map(|d| {
                sampled(
                    runtime,
                    n,
                    d,
                    (&names.analog_in, &details.analog_in),
                    (sample, faults),
                )
            }),
            Interface::DigitalIn => registry.digital_in().get(n).map(|d| {
                sampled(
                    runtime,
                    n,
                    d,
                    (&names.digital_in, &details.digital_in),
                    (sample, faults),
                )
            }),
            Interface::AnalogOut => registry
                .analog_out()
                .get(n)
                .map(|d| driven(runtime, n, d, (&names.analog_out, &details.analog_out))),
            Interface::DigitalOut => registry
                .digital_out()
                .get(n)
                .map(|d| driven(runtime, n, d, (&names.digital_out, &details.digital_out))),
            Interface::Encoder => registry
                .encoder()
                .get(n)
                .map(|d| encoder(runtime, n, d, sample)),
            // A card's drive (a CANopen CiA 402 node) gets the drive component of
            // `[[logical]]` drives: enable, disable, set_velocity, readings.
            Interface::Drive => registry
                .drive()
                .get(n)
                .map(|d| crate::logical::drive_io(runtime, n, d, false)),
            // A card registers no sensor or axis; `[[logical]]` ones have their own.
            Interface::Sensor | Interface::Axis => None,
        };
        if let Some(t) = task {
            out.push(t?);
        }
    }
    Ok(out)
}
