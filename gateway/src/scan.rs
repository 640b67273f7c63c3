//! The `scan` component: a control loop's shape, as a PLC scans — at every step, read
//! analog input channels of any cards, and write analog output channels from them.
//!
//! Each step reads every channel of `inputs` straight from its device (no port between),
//! and writes `gain × (mean of the inputs) + offset` to every channel of `outputs`. A
//! channel is `"device:channel"` with the channel's number (`"sim0:0"`). Devices are
//! looked up and channels checked when it is configured; the step allocates nothing and takes no lock
//! of its own, so on a SCHED_FIFO periodic activity it is a real-time loop doing I/O on
//! real cards (`docs/benchmarks.md` measures one over the simulator and Modbus TCP).
//!
//! A missed reading or write (a device stale or offline) is counted by the error model's
//! `FaultCounter` (`warn_after`, `error_after`); the step then writes nothing, so an
//! output keeps its last value, never one computed from a missing input.

use device_interface::{AnalogIn, AnalogOut, DeviceError};
use rtt::component::IntrospectError;
use rtt::log::{Area, Arg};
use rtt::port::OutputPort;
use rtt::property::Property;
use rtt::{Component, Context, HookError, HookResult, InterfaceBuilder};
use std::sync::Arc;

/// See the module's documentation.
pub struct Scan {
    inputs: Property<Vec<String>>,
    outputs: Property<Vec<String>>,
    gain: Property<f64>,
    offset: Property<f64>,
    warn_after: Property<u32>,
    error_after: Property<u32>,
    read_from: Vec<(Arc<dyn AnalogIn>, u32)>,
    write_to: Vec<(Arc<dyn AnalogOut>, u32)>,
    faults: rtt::faults::FaultCounter,
    written: OutputPort<f64>,
    log: Area,
}

/// `"device:channel"` as its two parts; the channel a number.
fn channel(s: &str, what: &str) -> Result<(String, u32), HookError> {
    let bad = || {
        HookError::new(format!(
            "{what} {s:?}: expected \"device:channel\" with a channel number (\"sim0:0\")"
        ))
    };
    let (device, ch) = s.rsplit_once(':').ok_or_else(bad)?;
    let ch: u32 = ch.trim().parse().map_err(|_| bad())?;
    if device.is_empty() {
        return Err(bad());
    }
    Ok((device.to_string(), ch))
}

/// Each `"device:channel"` of `list` as its device (by `lookup`) and channel, checked
/// against the device's `count` of channels.
fn resolve<D: ?Sized, E: std::fmt::Display>(
    list: &[String],
    what: &str,
    lookup: impl Fn(&str) -> Result<Arc<D>, E>,
    count: impl Fn(&D) -> u32,
) -> Result<Vec<(Arc<D>, u32)>, HookError> {
    let mut found = Vec::with_capacity(list.len());
    for s in list {
        let (name, ch) = channel(s, what)?;
        let device = lookup(&name).map_err(|e| HookError::new(e.to_string()))?;
        let n = count(&device);
        if ch >= n {
            return Err(HookError::new(format!(
                "{what} {s:?}: {name:?} has {n} channels"
            )));
        }
        found.push((device, ch));
    }
    Ok(found)
}

impl Scan {
    /// The interface: properties and the `out` port.
    pub fn new(iface: &mut InterfaceBuilder<Scan>) -> Result<Scan, IntrospectError> {
        let policy = rtt::faults::FaultPolicy::default();
        Ok(Scan {
            inputs: iface.properties().add(
                "inputs",
                Vec::new(),
                "AnalogIn channels read at every step, each \"device:channel\"",
            )?,
            outputs: iface.properties().add(
                "outputs",
                Vec::new(),
                "AnalogOut channels written at every step, each \"device:channel\"",
            )?,
            gain: iface
                .properties()
                .add("gain", 1.0, "multiplies the inputs' mean")?,
            offset: iface
                .properties()
                .add("offset", 0.0, "added after the gain")?,
            warn_after: iface.properties().add(
                "warn_after",
                policy.warn_after,
                "missed steps in a row that raise the warning (0: never)",
            )?,
            error_after: iface.properties().add(
                "error_after",
                policy.error_after,
                "missed steps in a row that go to RunTimeError (0: never)",
            )?,
            read_from: Vec::new(),
            write_to: Vec::new(),
            faults: rtt::faults::FaultCounter::default(),
            written: iface.output("out", "the value written at the last step")?,
            log: Area::named(iface.name()),
        })
    }

    /// One scan: every input read, every output written. `Err` on the first that missed.
    fn scan(&mut self) -> Result<f64, DeviceError> {
        let mut sum = 0.0;
        for (device, ch) in &self.read_from {
            sum += device.read(*ch)?;
        }
        let n = self.read_from.len().max(1) as f64;
        let value = self.gain.get() * (sum / n) + self.offset.get();
        for (device, ch) in &self.write_to {
            device.write(*ch, value)?;
        }
        Ok(value)
    }
}

impl Component for Scan {
    fn configure_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let inputs = self.inputs.get();
        let outputs = self.outputs.get();
        if inputs.is_empty() && outputs.is_empty() {
            return Err(HookError::new(
                "properties inputs and outputs are both empty: name the channels to scan",
            ));
        }
        let registry = ctx.registry();
        let read_from = resolve(
            &inputs,
            "input",
            |n| registry.analog_in().lookup(n),
            |d| d.channel_count(),
        )?;
        let write_to = resolve(
            &outputs,
            "output",
            |n| registry.analog_out().lookup(n),
            |d| d.channel_count(),
        )?;
        let policy = rtt::faults::FaultPolicy {
            warn_after: self.warn_after.get(),
            error_after: self.error_after.get(),
        };
        policy.check()?;
        self.faults = rtt::faults::FaultCounter::new(policy);
        self.read_from = read_from;
        self.write_to = write_to;
        Ok(())
    }

    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        match self.scan() {
            Ok(v) => {
                self.written.write(&v);
                self.faults.good(ctx);
            }
            Err(e) if e.is_transient() => {
                if self.faults.run() == 0 {
                    rtt::rt_log!(self.log, Warn, "missed a scan: {}", Arg::display(&e));
                }
                self.faults.missed(ctx);
            }
            // The gateway is stopping and holds its outputs at their safe values.
            Err(DeviceError::Held { .. }) => {}
            Err(e) => return Err(e.into()),
        }
        Ok(())
    }

    fn error_hook(&mut self, ctx: &mut Context<'_>) {
        if let Ok(v) = self.scan() {
            self.written.write(&v);
            rtt::rt_log!(self.log, Info, "scanning again");
            self.faults.good(ctx);
        }
    }

    fn cleanup_hook(&mut self, _: &mut Context<'_>) {
        self.read_from.clear();
        self.write_to.clear();
    }
}
