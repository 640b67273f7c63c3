//! An example of a user's own component types, registered beside hwgw's built-in ones.
//!
//! `threshold` turns an analog value into a digital one with hysteresis: `out` goes on
//! when `in` rises above `above` and off when it falls below `above - hysteresis`. Connect
//! an analog input's port to `threshold.in` and `threshold.out` to a digital output's port
//! (see `threshold.toml`). It *provides* the service `limit` (`limit.set(above)`,
//! `limit.is_on()`); `supervisor` *requires* it, imposes its own limit through it and
//! republishes the state as `alarm`: when the threshold leaves Running the supervisor is
//! told (`service_lost`) and applies its limit again when it is back (see
//! `supervised.toml`). The binary in `src/main.rs` is the whole `hwgw` command line with
//! these types added:
//!
//! ```text
//! cargo run -p hwgw-example-custom -- run examples/custom-component/threshold.toml
//! ```

use hwgw::types::Types;
use rtt::component::IntrospectError;
use rtt::port::{FlowStatus, InputPort, OutputPort};
use rtt::property::Property;
use rtt::service::RequiredOperation;
use rtt::{Component, Context, HookError, HookResult, InterfaceBuilder};

/// A comparator with hysteresis.
pub struct Threshold {
    input: InputPort<f64>,
    output: OutputPort<bool>,
    above: Property<f64>,
    hysteresis: Property<f64>,
    on: bool,
    /// Times the output switched (an attribute: a run-time value, not saved).
    switches: Property<u64>,
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
        // A service: operations other components require by name and type, bound by the
        // deployment (`supervisor` below).
        iface
            .provides("limit")
            .own_operation(
                "set",
                "switch on above this value from now on",
                &[("above", "the new limit")],
                |t: &mut Threshold, (above,): (f64,)| t.above.set(above),
            )?
            .own_operation(
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
            switches: {
                iface.attributes().constant(
                    "kind",
                    "comparator with hysteresis".to_string(),
                    "what this component is",
                )?;
                iface
                    .attributes()
                    .add("switches", 0u64, "times the output switched")?
            },
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
                // An example's counter, not a real-time path: a property's store allocates.
                self.switches.set(self.switches.get() + 1);
            }
        }
        Ok(())
    }
}

/// Imposes its limit on a `limit` service and republishes its state as `alarm`.
pub struct Supervisor {
    set: RequiredOperation<(f64,), ()>,
    is_on: RequiredOperation<(), bool>,
    above: Property<f64>,
    alarm: OutputPort<bool>,
    /// The limit is still to be applied (at start, and after the service came back).
    apply: bool,
}

impl Supervisor {
    fn new(iface: &mut InterfaceBuilder<Supervisor>) -> Result<Supervisor, IntrospectError> {
        let mut limit = iface.requires("limit");
        Ok(Supervisor {
            set: limit.operation("set")?,
            is_on: limit.operation("is_on")?,
            above: iface
                .properties()
                .add("above", 1.0, "the limit imposed on the service")?,
            alarm: iface.output("alarm", "the service's output state")?,
            apply: true,
        })
    }
}

impl Component for Supervisor {
    fn start_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        self.apply = true;
        Ok(())
    }

    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        if !self.set.ready() {
            return Ok(());
        }
        // A call refused is the service going (NotReady): `service_lost` tells, and the
        // limit is applied again when it is back — no reason to fail this component.
        if self.apply && self.set.call((self.above.get(),)).is_ok() {
            self.apply = false;
        }
        if let Ok(on) = self.is_on.call(()) {
            self.alarm.write(&on);
        }
        Ok(())
    }

    fn service_lost(&mut self, ctx: &mut Context<'_>, service: &str) {
        tracing::warn!("{}: service {service:?} lost; waiting for it", ctx.name());
    }

    fn service_back(&mut self, _: &mut Context<'_>, _: &str) {
        // A provider that restarted may have forgotten the limit.
        self.apply = true;
    }
}

/// hwgw's built-in types plus `threshold` and `supervisor`.
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
    t.components.register("supervisor", |rt, name, spec| {
        rt.add(
            name,
            spec,
            rtt::InitialState::PreOperational,
            Supervisor::new,
        )
    });
    t
}
