//! Component types built into the binary, chosen by `type` in the deployment file.
//!
//! - `blinker`: toggles one bit of a DigitalOut device at each step (properties `device`,
//!   `bit`).
//! - `follow`: `out = in * gain + offset`, from an input port to an output port (connect
//!   an analog input's port to `in` and `out` to an analog output's port).
//!
//! A user's own types are registered the same way: a name and a constructor that adds
//! ports, operations and properties to the interface (see `examples/`).

use device_interface::DigitalOut;
use rtt::component::IntrospectError;
use rtt::port::{FlowStatus, InputPort, OutputPort};
use rtt::property::Property;
use rtt::{
    ActivitySpec, Component, Context, HookError, HookResult, Interface, Runtime, RuntimeError,
    TaskContext,
};
use std::sync::Arc;

/// The names of the built-in types.
pub const TYPES: [&str; 2] = ["blinker", "follow"];

/// Builds component `name` of type `kind`, or says the type is unknown (`Ok(None)`).
pub fn build(
    runtime: &Runtime,
    name: &str,
    kind: &str,
    spec: ActivitySpec,
) -> Result<Option<TaskContext>, RuntimeError> {
    Ok(Some(match kind {
        "blinker" => runtime.add(name, spec, true, Blinker::new)?,
        "follow" => runtime.add(name, spec, true, Follow::new)?,
        _ => return Ok(None),
    }))
}

/// Toggles a digital output bit each step.
pub struct Blinker {
    device_name: Property<String>,
    bit: Property<u32>,
    device: Option<Arc<dyn DigitalOut>>,
    state: bool,
    toggles: OutputPort<bool>,
}

impl Blinker {
    fn new(iface: &mut Interface<Blinker>) -> Result<Blinker, IntrospectError> {
        Ok(Blinker {
            device_name: iface.properties().add(
                "device",
                String::new(),
                "DigitalOut device to blink",
            )?,
            bit: iface.properties().add("bit", 0u32, "the bit to toggle")?,
            device: None,
            state: false,
            toggles: iface.output("state", "the state just written")?,
        })
    }
}

impl Component for Blinker {
    fn configure_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        let name = self.device_name.get();
        let device = ctx.registry().digital_out().lookup(&name)?;
        let bit = self.bit.get();
        if bit >= device.output_count() {
            return Err(HookError::new(format!(
                "bit {bit} does not exist on {name:?} ({} outputs)",
                device.output_count()
            )));
        }
        self.device = Some(device);
        Ok(())
    }

    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        if let Some(d) = &self.device {
            self.state = !self.state;
            d.set_bit(self.bit.get(), self.state)?;
            self.toggles.write(&self.state);
        }
        Ok(())
    }

    fn stop_hook(&mut self, _: &mut Context<'_>) {
        if let Some(d) = &self.device {
            let _ = d.set_bit(self.bit.get(), false);
        }
    }
}

/// `out = in * gain + offset`.
pub struct Follow {
    input: InputPort<f64>,
    output: OutputPort<f64>,
    gain: Property<f64>,
    offset: Property<f64>,
}

impl Follow {
    fn new(iface: &mut Interface<Follow>) -> Result<Follow, IntrospectError> {
        Ok(Follow {
            input: iface.event_input("in", "the value followed")?,
            output: iface.output("out", "in * gain + offset")?,
            gain: iface.properties().add("gain", 1.0, "multiplier")?,
            offset: iface
                .properties()
                .add("offset", 0.0, "added after the gain")?,
        })
    }
}

impl Component for Follow {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        let mut x = 0.0;
        while self.input.read(&mut x) == FlowStatus::NewData {
            self.output
                .write(&(x * self.gain.get() + self.offset.get()));
        }
        Ok(())
    }
}
