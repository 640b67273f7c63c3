//! A CiA 402 node as a logical [`Drive`]: `enable` asks for operation enabled, `disable`
//! for ready to switch on (and resets a fault), `quick_stop` for the drive's quick stop
//! (its own braking ramp), `set_velocity` sets the target velocity in profile velocity
//! mode. The calls only say what is wanted and wake the bus side (they
//! do not block, as the drive contract asks); the bus side's [`step`] reads each drive's
//! statusword from its TPDO and writes the controlword that moves it one transition
//! nearer, and the target velocity only while operation is enabled — nothing while the
//! drive is disabled and stays so.

use crate::card::CanopenCard;
use crate::cia402::{State, controlword, state};
use device_interface::logical::Drive;
use device_interface::{Device, DeviceError, Health};
use std::sync::Arc;
use std::sync::atomic::Ordering;

/// Drive `d`'s state from its statusword, if its node runs and the TPDO came.
fn drive_state(card: &CanopenCard, d: usize) -> Result<State, DeviceError> {
    let m = &card.map().drives[d];
    let (sw, _) = card.input_bits(m.statusword as u32)?;
    Ok(state(sw as u16))
}

/// One step of every drive, from the bus side: controlword and target velocity.
pub fn step(card: &CanopenCard) {
    for (d, m) in card.map().drives.iter().enumerate() {
        let Ok(s) = drive_state(card, d) else {
            continue;
        };
        let w = &card.drives[d];
        let last = card.drive_out(m.controlword) as u16;
        if matches!(s, State::Fault | State::FaultReactionActive) {
            // It dropped out: enabled again only when asked again.
            w.enable.store(false, Ordering::Release);
        } else {
            w.reset.store(false, Ordering::Release);
        }
        let enable = w.enable.load(Ordering::Acquire);
        let quick = w.quick_stop.load(Ordering::Acquire);
        let cw = match (enable, s) {
            (false, State::OperationEnabled | State::QuickStopActive) if quick => {
                Some(crate::cia402::command::QUICK_STOP)
            }
            (true, _) => Some(controlword(s, true, last)),
            (false, State::Fault) if w.reset.load(Ordering::Acquire) => {
                Some(controlword(s, false, last))
            }
            (false, State::SwitchedOn | State::OperationEnabled | State::QuickStopActive) => {
                Some(controlword(s, false, last))
            }
            // Disabled and staying so: nothing is written.
            (false, _) => None,
        };
        if let Some(cw) = cw {
            card.set_drive_out(m.controlword, i64::from(cw));
        }
        let velocity = if enable && s == State::OperationEnabled {
            w.velocity.load(Ordering::Acquire)
        } else {
            0
        };
        card.set_drive_out(m.velocity, velocity);
    }
}

/// A CiA 402 node of a card, as a [`Drive`].
pub struct Cia402Drive {
    card: Arc<CanopenCard>,
    index: usize,
}

impl Cia402Drive {
    /// Drive `index` of `card`.
    pub fn new(card: Arc<CanopenCard>, index: usize) -> Cia402Drive {
        Cia402Drive { card, index }
    }

    fn wanted(&self) -> &crate::card::Wanted {
        &self.card.drives[self.index]
    }
}

impl Device for Cia402Drive {
    fn health(&self) -> Health {
        let mut h = self.card.health();
        let node = self.card.map().drives[self.index].node;
        if !self.card.node_operational(node) {
            h.status = device_interface::Status::Offline;
            h.last_error = Some(DeviceError::Offline);
        }
        h
    }
}

impl Drive for Cia402Drive {
    fn enable(&self) -> Result<(), DeviceError> {
        if self.faulted()? {
            return Err(DeviceError::Refused {
                reason: "the drive reports a fault: disable resets it",
            });
        }
        let w = self.wanted();
        w.quick_stop.store(false, Ordering::Release);
        w.velocity.store(0, Ordering::Release);
        w.enable.store(true, Ordering::Release);
        self.card.wake_bus();
        Ok(())
    }

    fn disable(&self) -> Result<(), DeviceError> {
        let w = self.wanted();
        w.quick_stop.store(false, Ordering::Release);
        w.velocity.store(0, Ordering::Release);
        w.enable.store(false, Ordering::Release);
        let faulted = self.faulted();
        if matches!(faulted, Ok(true)) {
            w.reset.store(true, Ordering::Release);
        }
        self.card.wake_bus();
        faulted.map(|_| ())
    }

    fn quick_stop(&self) -> Result<(), DeviceError> {
        let w = self.wanted();
        w.velocity.store(0, Ordering::Release);
        w.enable.store(false, Ordering::Release);
        w.quick_stop.store(true, Ordering::Release);
        self.card.wake_bus();
        Ok(())
    }

    fn is_enabled(&self) -> bool {
        self.wanted().enable.load(Ordering::Acquire)
    }

    fn set_velocity(&self, velocity: f64) -> Result<(), DeviceError> {
        if !self.is_enabled() {
            return Err(DeviceError::Refused {
                reason: "the drive is disabled",
            });
        }
        let m = &self.card.map().drives[self.index];
        let counts = (velocity / m.factor).round();
        let (lowest, highest) = self.velocity_range()?;
        if !(f64::from(i32::MIN)..=f64::from(i32::MAX)).contains(&counts) {
            return Err(DeviceError::ValueOutOfRange {
                channel: 0,
                value: velocity,
                lowest,
                highest,
            });
        }
        self.wanted()
            .velocity
            .store(counts as i64, Ordering::Release);
        self.card.wake_bus();
        Ok(())
    }

    fn velocity(&self) -> f64 {
        let m = &self.card.map().drives[self.index];
        self.wanted().velocity.load(Ordering::Acquire) as f64 * m.factor
    }

    fn velocity_range(&self) -> Result<(f64, f64), DeviceError> {
        let f = self.card.map().drives[self.index].factor;
        let (a, b) = (f64::from(i32::MIN) * f, f64::from(i32::MAX) * f);
        Ok((a.min(b), a.max(b)))
    }

    fn faulted(&self) -> Result<bool, DeviceError> {
        Ok(matches!(
            drive_state(&self.card, self.index)?,
            State::Fault | State::FaultReactionActive
        ))
    }

    fn unit(&self) -> &str {
        &self.card.map().drives[self.index].unit
    }
}
