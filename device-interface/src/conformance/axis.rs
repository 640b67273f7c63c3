//! The axis check of the conformance kit: the [`Axis`] contract run against an axis on a
//! rig that moves (a simulated card, or a real axis on a test bench).

use super::{Report, Rule};
use crate::DeviceError;
use crate::logical::{Axis, AxisFault, AxisState};
use crate::registry::Interface;

/// What the axis check needs besides the axis.
pub struct AxisRig<'a> {
    /// Advances the rig one cycle: time passes and the card's bus runs (the check calls
    /// [`Axis::step`] after it).
    pub cycle: &'a mut dyn FnMut(),
    /// Turns a limit switch on (`true`) or off: the high one when the first argument is
    /// `true`, the low one otherwise. Without it, [`Rule::AxLimit`] is not run.
    pub limit: Option<&'a mut dyn FnMut(bool, bool)>,
    /// Whether the drive's enable output is on, as the card sees it. Without it, the rules
    /// check the axis' own account only.
    pub enabled: Option<&'a dyn Fn() -> bool>,
    /// A velocity that moves the axis measurably in 10 cycles (its sign does not matter).
    pub jog: f64,
    /// How far from the expected position a homed axis may end, in the axis' unit.
    pub tolerance: f64,
    /// The most cycles homing may take.
    pub max_cycles: usize,
}

impl AxisRig<'_> {
    /// True unless the rig says the drive's enable output is not `on`.
    fn drive_is(&self, on: bool) -> bool {
        self.enabled.is_none_or(|f| f() == on)
    }

    fn run(&mut self, axis: &dyn Axis, cycles: usize) {
        for _ in 0..cycles {
            (self.cycle)();
            // A failed step shows in the state the rules check.
            let _ = axis.step();
        }
    }
}

fn refused<T>(r: &Result<T, DeviceError>) -> bool {
    matches!(r, Err(DeviceError::Refused { .. }))
}

/// Checks `axis` on `rig`. The axis moves: run it on a rig, never on a machine that can
/// hurt. It ends disabled, and not stepping.
pub fn check_axis(axis: &dyn Axis, mut rig: AxisRig<'_>) -> Report {
    use Rule::*;
    let mut report = Report::new(Interface::Axis);
    let v = rig.jog.abs();
    // Not stepped by its thread yet: nothing may move it.
    let early = axis.enable();
    report.expect(
        AxRefusedDisabled,
        refused(&early) && rig.drive_is(false),
        || format!("enable() before the axis is stepped = {early:?}, expected Refused"),
    );
    axis.set_stepping(true);
    let state = axis.state();
    report.expect(
        AxStartsDisabled,
        state == AxisState::Disabled && axis.velocity() == 0.0 && axis.fault().is_none(),
        || format!("a new axis is {state}, velocity {}", axis.velocity()),
    );

    let jog = axis.jog(v);
    report.expect(AxRefusedDisabled, refused(&jog), || {
        format!("jog({v}) while disabled = {jog:?}, expected Refused")
    });
    if axis.homing().is_some() {
        let home = axis.home();
        report.expect(AxRefusedDisabled, refused(&home), || {
            format!("home() while disabled = {home:?}, expected Refused")
        });
    }

    let e = axis.enable();
    let ready = axis.state();
    report.expect(
        AxEnableDisable,
        e.is_ok() && ready == AxisState::Ready && axis.velocity() == 0.0 && rig.drive_is(true),
        || {
            format!(
                "enable() = {e:?}, then {ready}; its enable output on: {}",
                rig.drive_is(true)
            )
        },
    );
    let d = axis.disable();
    let off = axis.state();
    report.expect(
        AxEnableDisable,
        d.is_ok() && off == AxisState::Disabled && rig.drive_is(false),
        || {
            format!(
                "disable() = {d:?}, then {off}; its enable output off: {}",
                rig.drive_is(false)
            )
        },
    );
    let _ = axis.enable();

    for dir in [1.0, -1.0] {
        let p0 = axis.position();
        let j = axis.jog(dir * v);
        let moving = axis.state();
        rig.run(axis, 10);
        let p1 = axis.position();
        let s = axis.stop();
        let after = axis.state();
        let moved = match (&p0, &p1) {
            (Ok(a), Ok(b)) => (b - a) * dir > 0.0,
            _ => false,
        };
        report.expect(
            AxJog,
            j.is_ok() && moving == AxisState::Moving && moved,
            || {
                format!(
                    "jog({}) = {j:?} ({moving}): position {p0:?} → {p1:?} in 10 cycles",
                    dir * v
                )
            },
        );
        report.expect(
            AxJog,
            s.is_ok() && after == AxisState::Ready && axis.velocity() == 0.0,
            || {
                format!(
                    "stop() = {s:?}, then {after} at velocity {}",
                    axis.velocity()
                )
            },
        );
    }

    if let Some(h) = axis.homing() {
        let start = axis.home();
        let homing = axis.state();
        let mut cycles = 0;
        while axis.state() == AxisState::Homing && cycles < rig.max_cycles {
            rig.run(axis, 1);
            cycles += 1;
        }
        let end = axis.state();
        let expected = h.position - h.velocity.signum() * h.back_off;
        let p = axis.position();
        let near = p
            .as_ref()
            .is_ok_and(|p| (p - expected).abs() <= rig.tolerance);
        report.expect(
            AxHoming,
            start.is_ok() && homing == AxisState::Homing,
            || format!("home() = {start:?}, then {homing}"),
        );
        report.expect(
            AxHoming,
            end == AxisState::Ready && axis.homed() && near,
            || {
                format!(
                    "after {cycles} cycles of homing the axis is {end} (homed: {}, fault: {:?}) \
                     at {p:?}, expected ready and homed at {expected} ± {}",
                    axis.homed(),
                    axis.fault(),
                    rig.tolerance
                )
            },
        );
    }

    if let Some(limit) = rig.limit.take() {
        for high in [true, false] {
            let toward = if high { v } else { -v };
            let fault = if high {
                AxisFault::LimitMax
            } else {
                AxisFault::LimitMin
            };
            let j = axis.jog(toward);
            rig.run(axis, 2);
            limit(high, true);
            rig.run(axis, 2);
            let s = axis.state();
            report.expect(
                AxLimit,
                j.is_ok()
                    && s == AxisState::Error
                    && axis.fault() == Some(fault)
                    && axis.velocity() == 0.0
                    && rig.drive_is(false),
                || {
                    format!(
                        "jog({toward}) = {j:?}, limit on: {s}, fault {:?}",
                        axis.fault()
                    )
                },
            );
            let (again, en) = (axis.jog(toward), axis.enable());
            report.expect(AxLimit, refused(&again) && refused(&en), || {
                format!("in error: jog = {again:?}, enable = {en:?}, expected both Refused")
            });
            let r = axis.reset();
            let e = axis.enable();
            let into = axis.jog(toward);
            let away = axis.jog(-toward);
            let s = axis.state();
            report.expect(
                AxLimit,
                r.is_ok() && e.is_ok() && refused(&into) && away.is_ok() && s == AxisState::Moving,
                || {
                    format!(
                        "reset = {r:?}, enable = {e:?}, jog into the limit = {into:?} \
                         (expected Refused), away = {away:?} ({s})"
                    )
                },
            );
            rig.run(axis, 2);
            let _ = axis.stop();
            limit(high, false);
            rig.run(axis, 1);
        }
    }
    let _ = axis.disable();
    axis.set_stepping(false);
    report
}
