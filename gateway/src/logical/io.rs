//! The IO components of logical devices: a sensor's sampled `value` port, a drive's
//! operations, and an axis' own thread — it steps the axis, publishes its position and
//! state, runs its commands (homing among them) as OwnThread operations, and disables the
//! drive when it stops.
//!
//! Operation results are `{"Ok": value}` or `{"Err": "message"}`, as for the cards' IO
//! components.

use crate::io::{device_op, health_op};
use device_interface::DeviceError;
use device_interface::logical::{Axis, AxisState, Drive, Sensor};
use rtt::port::OutputPort;
use rtt::{
    ActivitySpec, Component, Context, HookResult, InitialState, Runtime, RuntimeError, TaskContext,
};
use std::sync::Arc;
use std::time::Duration;

/// Samples a sensor into its `value` port.
struct SensorIo {
    device: Arc<dyn Sensor<f64>>,
    value: OutputPort<f64>,
}

impl Component for SensorIo {
    fn update_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        if let Ok(v) = self.device.read() {
            self.value.write(&v);
        }
        Ok(())
    }
}

/// Logs a drive that could not be disabled at stop — unless its outputs are held because
/// the gateway is stopping: their card's output policy drives them then.
fn disabled_at_stop(name: &str, r: Result<(), DeviceError>) {
    match r {
        Ok(()) | Err(DeviceError::Held { .. }) => {}
        Err(e) => tracing::warn!("{name}: disabling the drive at stop failed: {e}"),
    }
}

/// The sensor's component: `value` sampled every `sample`; `read`, `range`, `health`.
pub(super) fn sensor(
    runtime: &Runtime,
    name: &str,
    device: Arc<dyn Sensor<f64>>,
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
                "read",
                "the reading now, in its unit",
                &[],
                |d, ()| d.read(),
            )?;
            device_op(
                i,
                d,
                "range",
                "lowest and highest reading, and the unit",
                &[],
                |d, ()| {
                    let (lo, hi) = d.measurement_range();
                    Ok::<_, DeviceError>((lo, hi, d.unit().to_string()))
                },
            )?;
            health_op(i, d)?;
            let doc = format!("the reading, in {:?}", device.unit());
            Ok(SensorIo {
                value: i.output("value", &doc)?,
                device,
            })
        },
    )
}

/// A drive's component: no thread work; it disables the drive when it stops (unless an
/// axis owns the drive: the axis does).
struct DriveIo {
    device: Arc<dyn Drive>,
    owned: bool,
}

impl Component for DriveIo {
    fn stop_hook(&mut self, ctx: &mut Context<'_>) {
        if !self.owned {
            disabled_at_stop(ctx.name(), self.device.disable());
        }
    }
}

/// The drive's component. A drive an axis uses (`owned`) offers only what reads it: its
/// commands are the axis'.
pub(crate) fn drive(
    runtime: &Runtime,
    name: &str,
    device: Arc<dyn Drive>,
    owned: bool,
) -> Result<TaskContext, RuntimeError> {
    runtime.add(
        name,
        ActivitySpec::non_periodic(),
        InitialState::Stopped,
        move |i| {
            let d = &device;
            if !owned {
                device_op(
                    i,
                    d,
                    "enable",
                    "enables the drive at zero velocity",
                    &[],
                    |d, ()| d.enable(),
                )?;
                device_op(
                    i,
                    d,
                    "disable",
                    "zero velocity, then the enable off",
                    &[],
                    |d, ()| d.disable(),
                )?;
                device_op(
                    i,
                    d,
                    "quick_stop",
                    "stops as fast as the drive can (CiA 402: its quick stop), then disabled",
                    &[],
                    |d, ()| d.quick_stop(),
                )?;
                device_op(
                    i,
                    d,
                    "set_velocity",
                    "sets the velocity (refused while disabled)",
                    &[("velocity", "in the drive's unit")],
                    |d, (v,)| d.set_velocity(v),
                )?;
            }
            device_op(i, d, "velocity", "the velocity last set", &[], |d, ()| {
                Ok::<_, DeviceError>(d.velocity())
            })?;
            device_op(i, d, "enabled", "true while enabled", &[], |d, ()| {
                Ok::<_, DeviceError>(d.is_enabled())
            })?;
            device_op(
                i,
                d,
                "faulted",
                "true when the fault input is on",
                &[],
                |d, ()| d.faulted(),
            )?;
            health_op(i, d)?;
            Ok(DriveIo { device, owned })
        },
    )
}

/// What `hwgw call AXIS status` answers.
#[derive(serde::Serialize)]
struct AxisStatus {
    state: AxisState,
    fault: Option<String>,
    homed: bool,
    position: Option<f64>,
    velocity: f64,
    unit: String,
}

/// An axis' own thread.
struct AxisIo {
    device: Arc<dyn Axis>,
    position: OutputPort<f64>,
    state: OutputPort<AxisState>,
    homed: OutputPort<bool>,
    /// Steps that failed (a device error), counted as warnings.
    failed: bool,
}

impl Component for AxisIo {
    fn update_hook(&mut self, ctx: &mut Context<'_>) -> HookResult {
        match self.device.step() {
            Ok(()) if self.failed => {
                self.failed = false;
                ctx.recovered();
            }
            Ok(()) => {}
            Err(_) if self.failed => {}
            Err(_) => {
                self.failed = true;
                ctx.warning();
            }
        }
        if let Ok(p) = self.device.position() {
            self.position.write(&p);
        }
        self.state.write(&self.device.state());
        self.homed.write(&self.device.homed());
        Ok(())
    }

    fn start_hook(&mut self, _: &mut Context<'_>) -> HookResult {
        self.device.set_stepping(true);
        Ok(())
    }

    fn stop_hook(&mut self, ctx: &mut Context<'_>) {
        disabled_at_stop(ctx.name(), self.device.disable());
        self.device.set_stepping(false);
    }
}

/// Adds an axis command run in the axis' own thread.
fn command(
    i: &mut rtt::InterfaceBuilder<AxisIo>,
    name: &str,
    doc: &str,
    f: fn(&dyn Axis) -> Result<(), DeviceError>,
) -> Result<(), rtt::component::IntrospectError> {
    i.own_operation(name, doc, &[], move |c: &mut AxisIo, ()| {
        f(&*c.device).map_err(|e| e.to_string())
    })
}

/// The axis' component: stepped every `period` on its own thread (`thread`).
pub(super) fn axis(
    runtime: &Runtime,
    name: &str,
    device: Arc<dyn Axis>,
    period: Duration,
    thread: rtt::ThreadOptions,
) -> Result<TaskContext, RuntimeError> {
    let spec = ActivitySpec::Periodic {
        period,
        thread,
        timing: rtt::Timing::Absolute,
        max_overruns: None,
    };
    runtime.add(name, spec, InitialState::Stopped, move |i| {
        command(i, "enable", "enables the drive, standing still", |a| {
            a.enable()
        })?;
        command(
            i,
            "disable",
            "disables the drive (zero velocity first)",
            |a| a.disable(),
        )?;
        command(
            i,
            "stop",
            "stands still, enabled; ends homing unfinished",
            |a| a.stop(),
        )?;
        command(
            i,
            "home",
            "starts homing: search the home switch, latch, back off",
            |a| a.home(),
        )?;
        command(i, "reset", "leaves the error state, to disabled", |a| {
            a.reset()
        })?;
        i.own_operation(
            "jog",
            "moves at a velocity (unit/s; 0 stands still)",
            &[("velocity", "unit/s")],
            |c: &mut AxisIo, (v,): (f64,)| c.device.jog(v).map_err(|e| e.to_string()),
        )?;
        let d = device.clone();
        i.client_operation(
            "status",
            "state, fault, homed, position, velocity, unit",
            &[],
            move |()| AxisStatus {
                state: d.state(),
                fault: d.fault().map(|f| f.to_string()),
                homed: d.homed(),
                position: d.position().ok(),
                velocity: d.velocity(),
                unit: d.unit().to_string(),
            },
        )?;
        device_op(
            i,
            &device,
            "position",
            "the position in the axis' unit",
            &[],
            |d, ()| d.position(),
        )?;
        health_op(i, &device)?;
        Ok(AxisIo {
            position: i.output("position", "the position in the axis' unit")?,
            state: i.output("state", "disabled, ready, moving, homing or error")?,
            homed: i.output("homed", "true once homing finished")?,
            device,
            failed: false,
        })
    })
}
