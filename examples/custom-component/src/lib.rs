//! An example of a user's own component type, registered beside hwgw's built-in ones.
//!
//! `threshold` turns an analog value into a digital one with hysteresis: `out` goes on
//! when `in` rises above `above` and off when it falls below `above - hysteresis`. Connect
//! an analog input's port to `threshold.in` and `threshold.out` to a digital output's port
//! (see `threshold.toml`). The binary in `src/main.rs` is the whole `hwgw` command line
//! with this type added:
//!
//! ```text
//! cargo run -p hwgw-example-custom -- run examples/custom-component/threshold.toml
//! ```

use hwgw::types::Types;
use rtt::component::IntrospectError;
use rtt::port::{FlowStatus, InputPort, OutputPort};
use rtt::property::Property;
use rtt::{Component, Context, HookError, HookResult, InterfaceBuilder};

/// A comparator with hysteresis.
pub struct Threshold {
    input: InputPort<f64>,
    output: OutputPort<bool>,
    above: Property<f64>,
    hysteresis: Property<f64>,
    on: bool,
}

impl Threshold {
    fn new(iface: &mut InterfaceBuilder<Threshold>) -> Result<Threshold, IntrospectError> {
        // An operation other components and the CLI can call: the current state.
        iface.own_operation(
            "is_on",
            "whether the output is on",
            &[],
            |t: &mut Threshold, (): ()| t.on,
        )?;
        Ok(Threshold {
            input: iface.event_input("in", "the analog value watched")?,
            output: iface.output("out", "on above the threshold")?,
            above: iface
                .properties()
                .add("above", 0.0, "switch on above this value")?,
            hysteresis: iface.properties().add(
                "hysteresis",
                0.1,
                "switch off this far below `above`",
            )?,
            on: false,
        })
    }
}

impl Component for Threshold {
    fn configure_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        let band = self.hysteresis.get();
        if band.is_nan() || band < 0.0 {
            return Err(HookError::new(format!("hysteresis {band} must be >= 0")));
        }
        Ok(())
    }

    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        let mut x = 0.0;
        while self.input.read(&mut x) == FlowStatus::NewData {
            let (above, band) = (self.above.get(), self.hysteresis.get());
            let on = if self.on { x > above - band } else { x > above };
            if on != self.on {
                self.on = on;
                self.output.write(&on);
            }
        }
        Ok(())
    }
}

/// hwgw's built-in types plus `threshold`.
pub fn types() -> Types {
    let mut t = Types::builtin();
    t.components.register("threshold", |rt, name, spec| {
        rt.add(
            name,
            spec,
            rtt::InitialState::PreOperational,
            Threshold::new,
        )
    });
    t
}
