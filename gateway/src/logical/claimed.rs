//! A drive an axis commands, as the registry hands it to everyone else: it reads and it
//! disables (anyone may make a drive safe), but it takes no enable and no velocity — those
//! are the axis', which watches the limit switches while it moves.

use device_interface::logical::Drive;
use device_interface::{Device, DeviceError, Health};
use std::sync::Arc;

/// The registry's view of a drive its axis commands.
pub(super) struct ClaimedDrive(pub(super) Arc<dyn Drive>);

const BY_AXIS: DeviceError = DeviceError::Refused {
    reason: "an axis commands this drive: enable and move the axis",
};

impl Device for ClaimedDrive {
    fn health(&self) -> Health {
        self.0.health()
    }
}

impl Drive for ClaimedDrive {
    fn enable(&self) -> Result<(), DeviceError> {
        Err(BY_AXIS)
    }

    fn disable(&self) -> Result<(), DeviceError> {
        self.0.disable()
    }

    fn is_enabled(&self) -> bool {
        self.0.is_enabled()
    }

    fn set_velocity(&self, _: f64) -> Result<(), DeviceError> {
        Err(BY_AXIS)
    }

    fn velocity(&self) -> f64 {
        self.0.velocity()
    }

    fn velocity_range(&self) -> Result<(f64, f64), DeviceError> {
        self.0.velocity_range()
    }

    fn faulted(&self) -> Result<bool, DeviceError> {
        self.0.faulted()
    }

    fn unit(&self) -> &str {
        self.0.unit()
    }
}
