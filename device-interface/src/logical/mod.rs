//! Logical devices: what people work with — a sensor in its unit, a drive, an axis — built
//! over the physical interfaces a card offers.
//!
//! The Orocos manual's device-interface chapter (RTT 1.x manual, lines 5824–5876) splits
//! devices into a physical layer (AnalogIn/Out, DigitalIn/Out, Encoder: card dependent) and
//! a logical layer that "puts semantics on top": "a drive, a sensor, an encoder", the
//! generic `SensorInterface<T>`, and the Component Library's `Axis` and `AnalogDrive`. The
//! RTT 2.0 road map (line 322) keeps them in `rtt/dev` as `SensorInterface`,
//! `DriveInterface`, `AxisInterface` and `HomingInterface`. Here they are:
//!
//! - [`Sensor<T>`] (SensorInterface): a reading of type `T` with its range and unit;
//!   [`AnalogSensor`] (an analog input with gain and offset) and [`EncoderSensor`] (an
//!   encoder's count as a position in a unit) build one over physical devices.
//! - [`Drive`] (DriveInterface): enable, disable, a velocity setpoint, an optional fault
//!   input; [`AnalogDrive`] is OCL's AnalogDrive — an enable output and an analog setpoint
//!   with its scale.
//! - [`Axis`] (AxisInterface + HomingInterface): a drive and an encoder, optional limit and
//!   home switches, position in a configured unit, and homing stepped by the axis' own
//!   thread ([`Axis::step`]); [`ServoAxis`] builds one.
//!
//! Each is a device like the physical ones: it reports [`Health`] (the worst
//! of the devices under it), is served by the [`Registry`](crate::Registry) by name
//! ([`Interface::Sensor`](crate::Interface::Sensor), `Drive`, `Axis`), and keeps the real-time
//! contract below.
//!
//! # The real-time contract
//!
//! Every method may be called from a real-time thread: it does not block on I/O, runs in
//! bounded time and does not allocate. A [`Drive`] and an [`Axis`] keep their state behind
//! a short internal lock, held only for the few device calls of one command (which are
//! themselves non-blocking), so a caller waits at most for one other command; callers of
//! different priorities should not share one axis without priority inheritance.
//!
//! # Safety
//!
//! A drive is enabled only when asked; [`Drive::disable`] writes the zero-velocity setpoint
//! before it switches the enable output off, and tries both even when the first fails. An
//! axis disables its drive when a limit switch it moves towards turns on, when the drive
//! reports a fault, and when a device it needs while the drive is enabled fails (an output
//! changed under the drive included); it then stays in error until [`Axis::reset`], and a
//! disable that failed is tried again every step. It takes no command that moves it while
//! its own thread does not step it ([`Axis::set_stepping`]).

mod axis;
mod drive;
mod sensor;

pub use axis::{Axis, AxisFault, AxisState, HomingConfig, ServoAxis, ServoAxisParts};
pub use drive::{AnalogDrive, AnalogDriveParts, Drive};
pub use sensor::{AnalogSensor, EncoderSensor, Sensor};

use crate::{Health, Status};

/// The worst of several devices' health: offline before stale before online; the first of
/// equals. `None` for none.
pub fn worst_health(healths: impl IntoIterator<Item = Health>) -> Option<Health> {
    let rank = |s: Status| match s {
        Status::Online => 0,
        Status::Stale => 1,
        Status::Offline => 2,
    };
    healths
        .into_iter()
        .fold(None, |acc: Option<Health>, h| match acc {
            Some(a) if rank(a.status) >= rank(h.status) => Some(a),
            _ => Some(h),
        })
}
