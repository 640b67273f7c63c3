//! `Drive`: enable, disable and a velocity setpoint (RTT's DriveInterface), and
//! [`AnalogDrive`], a drive behind an enable output and an analog setpoint (OCL's
//! AnalogDrive).

use crate::channel::{AnalogOutput, DigitalInput, DigitalOutput};
use crate::logical::worst_health;
use crate::{Device, DeviceError, Health};
use std::sync::Mutex;

/// A velocity-controlled drive.
///
/// Real-time contract: see [the module](crate::logical). A drive starts disabled.
pub trait Drive: Device {
    /// Enables the drive at zero velocity: the setpoint first, then the enable output.
    /// Errors: the devices' errors (the drive stays disabled); refused while the drive
    /// reports a fault.
    fn enable(&self) -> Result<(), DeviceError>;

    /// Disables the drive: the zero-velocity setpoint, then the enable output off. Tries
    /// both; reports the first error.
    fn disable(&self) -> Result<(), DeviceError>;

    /// Stops as fast as the drive can and leaves it disabled: a drive with a quick stop of
    /// its own (CiA 402) brakes on its quick-stop ramp; the default disables.
    fn quick_stop(&self) -> Result<(), DeviceError> {
        self.disable()
    }

    /// True when the drive was enabled and not disabled since.
    fn is_enabled(&self) -> bool;

    /// Sets the velocity setpoint in [`unit`](Self::unit). Errors:
    /// [`Refused`](DeviceError::Refused) while disabled;
    /// [`ValueOutOfRange`](DeviceError::ValueOutOfRange) beyond what the setpoint output
    /// can carry; the devices' errors (the setpoint is then unchanged).
    fn set_velocity(&self, velocity: f64) -> Result<(), DeviceError>;

    /// The velocity last set (0 when disabled).
    fn velocity(&self) -> f64;

    /// The slowest and fastest velocity the setpoint output can carry.
    fn velocity_range(&self) -> Result<(f64, f64), DeviceError>;

    /// True when the drive's fault input says it failed (false without one).
    fn faulted(&self) -> Result<bool, DeviceError>;

    /// The velocity unit ("mm/s").
    fn unit(&self) -> &str;

    /// Writes the outputs again as last set, while enabled: the keep-alive an output
    /// watchdog expects of a live controller (an axis calls it every cycle). Nothing while
    /// disabled. Default: nothing.
    fn refresh(&self) -> Result<(), DeviceError> {
        Ok(())
    }
}

/// A drive behind an analog setpoint (`output = volts_per_unit × velocity + offset`), an
/// optional enable output and an optional fault input.
pub struct AnalogDrive {
    setpoint: AnalogOutput,
    volts_per_unit: f64,
    offset: f64,
    enable: Option<DigitalOutput>,
    fault: Option<DigitalInput>,
    unit: String,
    state: Mutex<DriveState>,
}

#[derive(Clone, Copy)]
struct DriveState {
    enabled: bool,
    velocity: f64,
}

/// The parts of an [`AnalogDrive`].
pub struct AnalogDriveParts {
    /// The setpoint output.
    pub setpoint: AnalogOutput,
    /// Output units per velocity unit (volts per mm/s); not 0.
    pub volts_per_unit: f64,
    /// The output at zero velocity.
    pub offset: f64,
    /// The enable output, on to enable.
    pub enable: Option<DigitalOutput>,
    /// The fault input, on when the drive failed.
    pub fault: Option<DigitalInput>,
    /// The velocity unit.
    pub unit: String,
}

impl AnalogDrive {
    /// A drive from its parts. Fails for a scale that is 0 or not finite, or a zero-velocity
    /// output outside the setpoint's range.
    pub fn new(parts: AnalogDriveParts) -> Result<AnalogDrive, DeviceError> {
        if !parts.volts_per_unit.is_finite() || parts.volts_per_unit == 0.0 {
            return Err(DeviceError::Refused {
                reason: "volts_per_unit must be finite and not 0",
            });
        }
        let r = parts.setpoint.range()?;
        if !(r.lowest..=r.highest).contains(&parts.offset) {
            return Err(DeviceError::ValueOutOfRange {
                channel: parts.setpoint.channel(),
                value: parts.offset,
                lowest: r.lowest,
                highest: r.highest,
            });
        }
        Ok(AnalogDrive {
            setpoint: parts.setpoint,
            volts_per_unit: parts.volts_per_unit,
            offset: parts.offset,
            enable: parts.enable,
            fault: parts.fault,
            unit: parts.unit,
            state: Mutex::new(DriveState {
                enabled: false,
                velocity: 0.0,
            }),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, DriveState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The setpoint output the drive writes.
    pub fn setpoint(&self) -> &AnalogOutput {
        &self.setpoint
    }

    /// The enable output, if the drive has one.
    pub fn enable_output(&self) -> Option<&DigitalOutput> {
        self.enable.as_ref()
    }

    /// The output value (volts) at zero velocity.
    pub fn zero_output(&self) -> f64 {
        self.offset
    }
}

impl Device for AnalogDrive {
    fn health(&self) -> Health {
        let all = [
            Some(self.setpoint.device().health()),
            self.enable.as_ref().map(|e| e.device().health()),
            self.fault.as_ref().map(|f| f.device().health()),
        ];
        worst_health(all.into_iter().flatten()).unwrap_or_else(|| self.setpoint.device().health())
    }
}

impl Drive for AnalogDrive {
    fn enable(&self) -> Result<(), DeviceError> {
        let mut s = self.lock();
        if self.faulted()? {
            return Err(DeviceError::Refused {
                reason: "the drive reports a fault",
            });
        }
        s.velocity = 0.0;
        let on = self.setpoint.write(self.offset).and_then(|()| {
            self.enable
                .as_ref()
                .map_or(Ok(()), DigitalOutput::switch_on)
        });
        if on.is_err() {
            // The enable may have taken (a write that timed out): off again, both tried.
            let _ = self.setpoint.write(self.offset);
            if let Some(e) = &self.enable {
                let _ = e.switch_off();
            }
        }
        s.enabled = on.is_ok();
        on
    }

    fn disable(&self) -> Result<(), DeviceError> {
        let mut s = self.lock();
        s.enabled = false;
        s.velocity = 0.0;
        let zero = self.setpoint.write(self.offset);
        let off = self.enable.as_ref().map_or(Ok(()), |e| e.switch_off());
        zero.and(off)
    }

    fn is_enabled(&self) -> bool {
        self.lock().enabled
    }

    fn set_velocity(&self, velocity: f64) -> Result<(), DeviceError> {
        let mut s = self.lock();
        if !s.enabled {
            return Err(DeviceError::Refused {
                reason: "the drive is disabled; enable it first",
            });
        }
        self.setpoint
            .write(self.volts_per_unit * velocity + self.offset)?;
        s.velocity = velocity;
        Ok(())
    }

    fn velocity(&self) -> f64 {
        self.lock().velocity
    }

    fn velocity_range(&self) -> Result<(f64, f64), DeviceError> {
        let r = self.setpoint.range()?;
        let a = (r.lowest - self.offset) / self.volts_per_unit;
        let b = (r.highest - self.offset) / self.volts_per_unit;
        Ok((a.min(b), a.max(b)))
    }

    fn faulted(&self) -> Result<bool, DeviceError> {
        self.fault.as_ref().map_or(Ok(false), |f| f.is_on())
    }

    fn unit(&self) -> &str {
        &self.unit
    }

    /// Also checks that the outputs still read back as the drive set them: an output
    /// changed under the drive (an output watchdog drove it to its safe value) is
    /// [`Refused`](DeviceError::Refused), not written over.
    fn refresh(&self) -> Result<(), DeviceError> {
        let s = self.lock();
        if !s.enabled {
            return Ok(());
        }
        let want = self.volts_per_unit * s.velocity + self.offset;
        let step = self.setpoint.device().resolution(self.setpoint.channel())?;
        let off = self
            .enable
            .as_ref()
            .map_or(Ok(false), |e| e.is_on().map(|on| !on))?;
        if off || (self.setpoint.read_back()? - want).abs() > step {
            return Err(DeviceError::Refused {
                reason: "an output of the drive was changed under it (an output watchdog?)",
            });
        }
        self.setpoint.write(want)?;
        self.enable
            .as_ref()
            .map_or(Ok(()), DigitalOutput::switch_on)
    }
}
