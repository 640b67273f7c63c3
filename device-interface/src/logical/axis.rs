//! `Axis`: a drive, an encoder, optional limit and home switches, position in a unit, and
//! homing (RTT's AxisInterface and HomingInterface; OCL's Axis), and [`ServoAxis`], which
//! builds one from those parts.
//!
//! Homing is a state machine advanced by [`Axis::step`], which the axis' own thread calls
//! every cycle: [`Axis::home`] only starts it. It searches the home switch at the
//! configured velocity (first moving off it if it is on already), latches the encoder's
//! count at the switch's edge as the configured home position, and backs off by the
//! configured distance. A limit switch the axis moves towards, a drive fault or a device
//! failing while the drive is enabled disables the drive and puts the axis in error; a
//! disable that fails is retried every step until it works.

use crate::channel::DigitalInput;
use crate::logical::{Drive, EncoderSensor, Sensor, worst_health};
use crate::{Device, DeviceError, Health};
use std::fmt;
use std::sync::{Arc, Mutex, MutexGuard};

/// What an axis is doing.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AxisState {
    /// The drive is disabled.
    #[default]
    Disabled,
    /// Enabled, standing still.
    Ready,
    /// Enabled, moving at a velocity it was given.
    Moving,
    /// Enabled, homing.
    Homing,
    /// Stopped by a fault, the drive disabled, until [`Axis::reset`].
    Error,
}

impl fmt::Display for AxisState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            AxisState::Disabled => "disabled",
            AxisState::Ready => "ready",
            AxisState::Moving => "moving",
            AxisState::Homing => "homing",
            AxisState::Error => "error",
        })
    }
}

/// Why an axis went to [`AxisState::Error`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AxisFault {
    /// The limit switch at the low end turned on while moving down.
    LimitMin,
    /// The limit switch at the high end turned on while moving up.
    LimitMax,
    /// The drive's fault input turned on.
    DriveFault,
    /// Homing travelled its whole `max_travel` without finding the home switch's edge
    /// (moving off it or searching it).
    HomeNotFound,
    /// A device the enabled axis needs failed (offline, stale, a bus error, a write not
    /// taken, an output changed under the drive).
    Device,
}

impl fmt::Display for AxisFault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            AxisFault::LimitMin => "the low limit switch turned on",
            AxisFault::LimitMax => "the high limit switch turned on",
            AxisFault::DriveFault => "the drive reports a fault",
            AxisFault::HomeNotFound => "homing found no edge of the home switch within max_travel",
            AxisFault::Device => "a device failed while the drive was enabled",
        })
    }
}

/// How an axis homes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HomingConfig {
    /// Search velocity, in the axis' unit per second; its sign is the search direction.
    pub velocity: f64,
    /// The position the home switch's edge gets.
    pub position: f64,
    /// How far to move back off the switch after latching (≥ 0).
    pub back_off: f64,
    /// The farthest a search may travel before it gives up (`None`: no limit).
    pub max_travel: Option<f64>,
}

/// An axis: a velocity-driven drive with position feedback.
///
/// Real-time contract: see [the module](crate::logical). Commands other than
/// [`step`](Self::step) take effect at once on the drive; `step` is called by the axis'
/// own thread every cycle and watches the switches and advances homing.
pub trait Axis: Device {
    /// The position in [`unit`](Self::unit).
    fn position(&self) -> Result<f64, DeviceError>;
    /// The position unit.
    fn unit(&self) -> &str;
    /// What the axis is doing.
    fn state(&self) -> AxisState;
    /// Why it is in error, while it is.
    fn fault(&self) -> Option<AxisFault>;
    /// True once homing finished (until the next homing starts or fails).
    fn homed(&self) -> bool;
    /// The velocity commanded now.
    fn velocity(&self) -> f64;
    /// How it homes; `None` when it cannot.
    fn homing(&self) -> Option<HomingConfig>;
    /// Enables the drive at standstill. Refused in error.
    fn enable(&self) -> Result<(), DeviceError>;
    /// Disables the drive (the zero-velocity setpoint first), stopping any motion.
    fn disable(&self) -> Result<(), DeviceError>;
    /// Moves at `velocity` (unit/s; 0 stands still). Refused unless enabled and not homing,
    /// or towards a limit switch that is on.
    fn jog(&self, velocity: f64) -> Result<(), DeviceError>;
    /// Stands still, enabled; ends homing unfinished.
    fn stop(&self) -> Result<(), DeviceError>;
    /// Starts homing. Refused unless enabled and standing still;
    /// [`Unsupported`](DeviceError::Unsupported) without a home switch and a homing
    /// configuration.
    fn home(&self) -> Result<(), DeviceError>;
    /// Leaves the error state, to disabled (the drive stays off).
    fn reset(&self) -> Result<(), DeviceError>;
    /// Says whether the axis' own thread steps it (on at its start, off at its stop):
    /// while it does not, `enable`, `jog` and `home` are refused — nothing would watch
    /// the limit switches.
    fn set_stepping(&self, on: bool);
    /// One cycle: keeps the drive's outputs alive ([`Drive::refresh`]), checks the limit
    /// switches and the drive's fault, advances homing.
    /// Errors: the device error that put the axis in error in this cycle.
    fn step(&self) -> Result<(), DeviceError>;
}

/// The parts of a [`ServoAxis`].
pub struct ServoAxisParts {
    /// The drive.
    pub drive: Arc<dyn Drive>,
    /// The encoder, read in the axis' unit (its offset is ignored: homing sets the zero).
    pub encoder: EncoderSensor,
    /// The low-end limit switch, on at the limit.
    pub limit_min: Option<DigitalInput>,
    /// The high-end limit switch.
    pub limit_max: Option<DigitalInput>,
    /// The home switch.
    pub home: Option<DigitalInput>,
    /// How to home (needs `home`).
    pub homing: Option<HomingConfig>,
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// Moving off a home switch that was on when homing started.
    Clear,
    /// Looking for the switch's edge.
    Search,
    /// Moving back off it.
    BackOff,
}

struct Core {
    state: AxisState,
    /// A disable of the drive failed: retried every step until it works.
    pending_disable: bool,
    fault: Option<AxisFault>,
    phase: Phase,
    homed: bool,
    velocity: f64,
    /// The count where the current homing phase started.
    phase_start: i64,
    /// The count latched at the home switch's edge, and the position it stands for.
    latch: (i64, f64),
}

/// An axis built from a drive, an encoder and switches.
pub struct ServoAxis {
    parts: ServoAxisParts,
    core: Mutex<Core>,
    stepping: std::sync::atomic::AtomicBool,
}

impl ServoAxis {
    /// An axis from its parts, disabled. Fails for a homing configuration without a home
    /// switch, or with a velocity that is 0 or not finite, a negative or non-finite back-off
    /// or max_travel, or a position that is not finite.
    pub fn new(parts: ServoAxisParts) -> Result<ServoAxis, DeviceError> {
        if let Some(h) = &parts.homing {
            if parts.home.is_none() {
                return Err(DeviceError::Refused {
                    reason: "homing needs a home switch",
                });
            }
            let ok = h.velocity.is_finite()
                && h.velocity != 0.0
                && h.position.is_finite()
                && h.back_off.is_finite()
                && h.back_off >= 0.0
                && h.max_travel.is_none_or(|m| m.is_finite() && m > 0.0);
            if !ok {
                return Err(DeviceError::Refused {
                    reason: "homing needs a finite velocity that is not 0, a finite position, \
                             a back-off >= 0 and a max_travel > 0",
                });
            }
        }
        Ok(ServoAxis {
            parts,
            stepping: std::sync::atomic::AtomicBool::new(false),
            core: Mutex::new(Core {
                pending_disable: false,
                state: AxisState::Disabled,
                fault: None,
                phase: Phase::Search,
                homed: false,
                velocity: 0.0,
                phase_start: 0,
                latch: (0, 0.0),
            }),
        })
    }

    fn lock(&self) -> MutexGuard<'_, Core> {
        self.core.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The drive.
    pub fn drive(&self) -> &Arc<dyn Drive> {
        &self.parts.drive
    }

    fn cpu(&self) -> f64 {
        self.parts.encoder.counts_per_unit()
    }

    fn on(input: &Option<DigitalInput>) -> Result<bool, DeviceError> {
        input.as_ref().map_or(Ok(false), DigitalInput::is_on)
    }

    /// The limit `velocity` runs into when it is on now.
    fn blocking_limit(&self, velocity: f64) -> Result<Option<AxisFault>, DeviceError> {
        if velocity < 0.0 && Self::on(&self.parts.limit_min)? {
            return Ok(Some(AxisFault::LimitMin));
        }
        if velocity > 0.0 && Self::on(&self.parts.limit_max)? {
            return Ok(Some(AxisFault::LimitMax));
        }
        Ok(None)
    }

    /// Disables the drive; a failure is retried every step until it works.
    fn disable_drive(&self, c: &mut Core) -> Result<(), DeviceError> {
        let r = self.parts.drive.disable();
        c.pending_disable = r.is_err();
        r
    }

    /// Holds the axis in error for `fault` and disables the drive; the error of a disable
    /// that failed (retried every step).
    fn trip(&self, c: &mut Core, fault: AxisFault) -> Result<(), DeviceError> {
        if c.state == AxisState::Homing || fault == AxisFault::Device {
            // Homing unfinished, or counts perhaps lost: the latch no longer holds.
            c.homed = false;
        }
        c.state = AxisState::Error;
        c.fault = Some(fault);
        c.velocity = 0.0;
        self.disable_drive(c)
    }

    /// Refuses a command that would move the axis while its own thread does not step it.
    fn check_stepping(&self) -> Result<(), DeviceError> {
        if self.stepping.load(std::sync::atomic::Ordering::Acquire) {
            Ok(())
        } else {
            Err(DeviceError::Refused {
                reason: "the axis' own thread is not stepping it (start its component)",
            })
        }
    }

    fn set_velocity(&self, c: &mut Core, velocity: f64) -> Result<(), DeviceError> {
        self.parts.drive.set_velocity(velocity)?;
        c.velocity = velocity;
        Ok(())
    }

    /// Travelled since the phase started, in units.
    fn travelled(&self, c: &Core, count: i64) -> f64 {
        (count.saturating_sub(c.phase_start) as f64 / self.cpu()).abs()
    }

    /// One homing cycle at encoder `count`.
    fn advance_homing(&self, c: &mut Core, count: i64) -> Result<(), DeviceError> {
        let (Some(h), Some(home)) = (self.parts.homing, &self.parts.home) else {
            return Ok(());
        };
        let on = home.is_on()?;
        let too_far = h.max_travel.is_some_and(|m| self.travelled(c, count) > m);
        match c.phase {
            Phase::Clear if !on => {
                c.phase = Phase::Search;
                c.phase_start = count;
                if let Some(limit) = self.blocking_limit(h.velocity)? {
                    return self.trip(c, limit);
                }
                self.set_velocity(c, h.velocity)?;
            }
            Phase::Search if on => {
                c.latch = (count, h.position);
                c.phase = Phase::BackOff;
                c.phase_start = count;
                if let Some(limit) = self.blocking_limit(-h.velocity)? {
                    return self.trip(c, limit);
                }
                self.set_velocity(c, -h.velocity)?;
            }
            Phase::Clear | Phase::Search if too_far => {
                return self.trip(c, AxisFault::HomeNotFound);
            }
            Phase::BackOff if self.travelled(c, count) >= h.back_off => {
                self.set_velocity(c, 0.0)?;
                c.state = AxisState::Ready;
                c.homed = true;
            }
            _ => {}
        }
        Ok(())
    }

    fn cycle(&self, c: &mut Core) -> Result<(), DeviceError> {
        self.parts.drive.refresh()?;
        if self.parts.drive.faulted()? {
            return self.trip(c, AxisFault::DriveFault);
        }
        if let Some(limit) = self.blocking_limit(c.velocity)? {
            return self.trip(c, limit);
        }
        if c.state == AxisState::Homing {
            let count = self.parts.encoder.count()?;
            self.advance_homing(c, count)?;
        }
        Ok(())
    }
}

impl Device for ServoAxis {
    fn health(&self) -> Health {
        let p = &self.parts;
        let all = [
            Some(p.drive.health()),
            Some(p.encoder.health()),
            p.limit_min.as_ref().map(|i| i.device().health()),
            p.limit_max.as_ref().map(|i| i.device().health()),
            p.home.as_ref().map(|i| i.device().health()),
        ];
        worst_health(all.into_iter().flatten()).unwrap_or_else(|| p.drive.health())
    }
}

impl Axis for ServoAxis {
    fn position(&self) -> Result<f64, DeviceError> {
        let count = self.parts.encoder.count()?;
        let (latched, at) = self.lock().latch;
        Ok(count.saturating_sub(latched) as f64 / self.cpu() + at)
    }

    fn unit(&self) -> &str {
        self.parts.encoder.unit()
    }

    fn state(&self) -> AxisState {
        self.lock().state
    }

    fn fault(&self) -> Option<AxisFault> {
        self.lock().fault
    }

    fn homed(&self) -> bool {
        self.lock().homed
    }

    fn velocity(&self) -> f64 {
        self.lock().velocity
    }

    fn homing(&self) -> Option<HomingConfig> {
        // `new` refuses homing without a home switch.
        self.parts.homing
    }

    fn enable(&self) -> Result<(), DeviceError> {
        self.check_stepping()?;
        let mut c = self.lock();
        match c.state {
            AxisState::Error => Err(DeviceError::Refused {
                reason: "the axis is in error; reset it first",
            }),
            AxisState::Disabled => {
                self.parts.drive.enable()?;
                c.velocity = 0.0;
                c.state = AxisState::Ready;
                Ok(())
            }
            _ => Ok(()),
        }
    }

    fn disable(&self) -> Result<(), DeviceError> {
        let mut c = self.lock();
        if c.state == AxisState::Homing {
            c.homed = false;
        }
        c.velocity = 0.0;
        match self.disable_drive(&mut c) {
            Ok(()) => {
                if c.state != AxisState::Error {
                    c.state = AxisState::Disabled;
                }
                Ok(())
            }
            // Not known to be off: in error, the disable retried every step.
            Err(e) => {
                c.state = AxisState::Error;
                c.fault = Some(AxisFault::Device);
                c.homed = false;
                Err(e)
            }
        }
    }

    fn jog(&self, velocity: f64) -> Result<(), DeviceError> {
        self.check_stepping()?;
        let mut c = self.lock();
        let reason = match c.state {
            AxisState::Ready | AxisState::Moving => None,
            AxisState::Disabled => Some("the axis is disabled; enable it first"),
            AxisState::Homing => Some("the axis is homing; stop it first"),
            AxisState::Error => Some("the axis is in error; reset it first"),
        };
        if let Some(reason) = reason {
            return Err(DeviceError::Refused { reason });
        }
        match self.blocking_limit(velocity)? {
            Some(AxisFault::LimitMin) => Err(DeviceError::Refused {
                reason: "the low limit switch is on; move up",
            }),
            Some(_) => Err(DeviceError::Refused {
                reason: "the high limit switch is on; move down",
            }),
            None => {
                self.set_velocity(&mut c, velocity)?;
                c.state = if velocity == 0.0 {
                    AxisState::Ready
                } else {
                    AxisState::Moving
                };
                Ok(())
            }
        }
    }

    fn stop(&self) -> Result<(), DeviceError> {
        let mut c = self.lock();
        match c.state {
            AxisState::Ready | AxisState::Moving | AxisState::Homing => {
                if c.state == AxisState::Homing {
                    c.homed = false;
                }
                match self.set_velocity(&mut c, 0.0) {
                    Ok(()) => {
                        c.state = AxisState::Ready;
                        Ok(())
                    }
                    // Still moving, perhaps: stopped the hard way.
                    Err(e) => {
                        let _ = self.trip(&mut c, AxisFault::Device);
                        Err(e)
                    }
                }
            }
            AxisState::Disabled | AxisState::Error => Ok(()),
        }
    }

    fn home(&self) -> Result<(), DeviceError> {
        let (Some(h), Some(home)) = (self.parts.homing, &self.parts.home) else {
            return Err(DeviceError::Unsupported {
                what: "homing (the axis has no home switch or no homing section)",
            });
        };
        self.check_stepping()?;
        let mut c = self.lock();
        if c.state != AxisState::Ready {
            return Err(DeviceError::Refused {
                reason: "homing starts from an enabled axis standing still",
            });
        }
        let on = home.is_on()?;
        let (phase, velocity) = if on {
            (Phase::Clear, -h.velocity)
        } else {
            (Phase::Search, h.velocity)
        };
        if let Some(limit) = self.blocking_limit(velocity)? {
            return Err(DeviceError::Refused {
                reason: if limit == AxisFault::LimitMin {
                    "the low limit switch is on in the direction homing moves"
                } else {
                    "the high limit switch is on in the direction homing moves"
                },
            });
        }
        c.phase_start = self.parts.encoder.count()?;
        self.set_velocity(&mut c, velocity)?;
        c.phase = phase;
        c.homed = false;
        c.state = AxisState::Homing;
        Ok(())
    }

    fn reset(&self) -> Result<(), DeviceError> {
        let mut c = self.lock();
        if c.state == AxisState::Error {
            self.disable_drive(&mut c)?;
            c.state = AxisState::Disabled;
            c.fault = None;
        }
        Ok(())
    }

    fn set_stepping(&self, on: bool) {
        self.stepping
            .store(on, std::sync::atomic::Ordering::Release);
    }

    fn step(&self) -> Result<(), DeviceError> {
        let mut c = self.lock();
        if c.pending_disable {
            return self.disable_drive(&mut c);
        }
        if matches!(c.state, AxisState::Disabled | AxisState::Error) {
            return Ok(());
        }
        // Any device failing while enabled: the drive's state is not known to be safe.
        self.cycle(&mut c).inspect_err(|_| {
            if c.state != AxisState::Error {
                let _ = self.trip(&mut c, AxisFault::Device);
            }
        })
    }
}
