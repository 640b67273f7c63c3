//! Single-channel handles: a device plus a channel (or bit), in the spirit of Orocos'
//! AnalogInput, AnalogOutput, DigitalInput and DigitalOutput.
//!
//! A component that needs "the pressure sensor" rather than "channel 3 of card 0" keeps one
//! of these. The channel is checked once, when the handle is made; a digital handle can
//! invert its bit (active-low wiring).
//!
//! ```
//! use device_interface::channel::DigitalOutput;
//! # use device_interface::{Device, DeviceError, DigitalOut, Health, Status, time::Timestamp};
//! # use std::sync::atomic::{AtomicBool, Ordering};
//! # struct One(AtomicBool);
//! # impl Device for One { fn health(&self) -> Health { Health { status: Status::Online, last_good: None, checked_at: Timestamp::ZERO, last_error: None } } }
//! # impl DigitalOut for One {
//! #     fn output_count(&self) -> u32 { 1 }
//! #     fn set_bit(&self, _: u32, v: bool) -> Result<(), DeviceError> { self.0.store(v, Ordering::SeqCst); Ok(()) }
//! #     fn check_bit(&self, _: u32) -> Result<bool, DeviceError> { Ok(self.0.load(Ordering::SeqCst)) }
//! # }
//! use std::sync::Arc;
//!
//! let card = Arc::new(One(AtomicBool::new(false)));
//! let lamp = DigitalOutput::new(card.clone(), 0, true)?; // wired active-low
//! lamp.switch_on()?;
//! assert!(lamp.is_on()?);
//! assert!(!card.check_bit(0)?); // the wire is low
//! # Ok::<(), DeviceError>(())
//! ```

use crate::{AnalogIn, AnalogOut, AnalogRange, DeviceError, DigitalIn, DigitalOut};
use std::sync::Arc;

/// Channel `channel` of a card's per-channel `items` (its scales, its channel states):
/// [`DeviceError::ChannelOutOfRange`] past the end. For cards' `scale`, `read_raw` and the
/// like.
pub fn nth<T>(items: &[T], channel: u32) -> Result<&T, DeviceError> {
    items
        .get(channel as usize)
        .ok_or(DeviceError::ChannelOutOfRange {
            channel,
            count: u32::try_from(items.len()).unwrap_or(u32::MAX),
        })
}

fn check_channel(channel: u32, count: u32) -> Result<(), DeviceError> {
    if channel < count {
        Ok(())
    } else {
        Err(DeviceError::ChannelOutOfRange { channel, count })
    }
}

fn check_bit(bit: u32, count: u32) -> Result<(), DeviceError> {
    if bit < count {
        Ok(())
    } else {
        Err(DeviceError::BitOutOfRange { bit, count })
    }
}

/// One analog input channel.
#[derive(Clone)]
pub struct AnalogInput {
    device: Arc<dyn AnalogIn>,
    channel: u32,
}

impl AnalogInput {
    /// Channel `channel` of `device`; fails if the device has no such channel.
    pub fn new(device: Arc<dyn AnalogIn>, channel: u32) -> Result<Self, DeviceError> {
        check_channel(channel, device.channel_count())?;
        Ok(AnalogInput { device, channel })
    }

    /// The latest value in physical units (see [`AnalogIn::read`]).
    pub fn read(&self) -> Result<f64, DeviceError> {
        self.device.read(self.channel)
    }

    /// The latest raw value (see [`AnalogIn::read_raw`]).
    pub fn read_raw(&self) -> Result<i64, DeviceError> {
        self.device.read_raw(self.channel)
    }

    /// The channel's range and unit.
    pub fn range(&self) -> Result<AnalogRange, DeviceError> {
        self.device.range(self.channel)
    }

    /// The channel number on the device.
    pub fn channel(&self) -> u32 {
        self.channel
    }

    /// The device.
    pub fn device(&self) -> &Arc<dyn AnalogIn> {
        &self.device
    }
}

/// One analog output channel.
#[derive(Clone)]
pub struct AnalogOutput {
    device: Arc<dyn AnalogOut>,
    channel: u32,
}

impl AnalogOutput {
    /// Channel `channel` of `device`; fails if the device has no such channel.
    pub fn new(device: Arc<dyn AnalogOut>, channel: u32) -> Result<Self, DeviceError> {
        check_channel(channel, device.channel_count())?;
        Ok(AnalogOutput { device, channel })
    }

    /// Writes `value` in physical units (see [`AnalogOut::write`]).
    pub fn write(&self, value: f64) -> Result<(), DeviceError> {
        self.device.write(self.channel, value)
    }

    /// Writes a raw value (see [`AnalogOut::write_raw`]).
    pub fn write_raw(&self, raw: i64) -> Result<(), DeviceError> {
        self.device.write_raw(self.channel, raw)
    }

    /// The value last written, as output (see [`AnalogOut::read_back`]).
    pub fn read_back(&self) -> Result<f64, DeviceError> {
        self.device.read_back(self.channel)
    }

    /// The channel's range and unit.
    pub fn range(&self) -> Result<AnalogRange, DeviceError> {
        self.device.range(self.channel)
    }

    /// The channel number on the device.
    pub fn channel(&self) -> u32 {
        self.channel
    }

    /// The device.
    pub fn device(&self) -> &Arc<dyn AnalogOut> {
        &self.device
    }
}

/// One digital input bit, optionally inverted.
#[derive(Clone)]
pub struct DigitalInput {
    device: Arc<dyn DigitalIn>,
    bit: u32,
    invert: bool,
}

impl DigitalInput {
    /// Bit `bit` of `device`, read inverted when `invert`; fails if there is no such bit.
    pub fn new(device: Arc<dyn DigitalIn>, bit: u32, invert: bool) -> Result<Self, DeviceError> {
        check_bit(bit, device.input_count())?;
        Ok(DigitalInput {
            device,
            bit,
            invert,
        })
    }

    /// True when the (logical, after inversion) input is on.
    pub fn is_on(&self) -> Result<bool, DeviceError> {
        Ok(self.device.read_bit(self.bit)? != self.invert)
    }

    /// True when the (logical) input is off.
    pub fn is_off(&self) -> Result<bool, DeviceError> {
        self.is_on().map(|v| !v)
    }

    /// The bit number on the device.
    pub fn bit(&self) -> u32 {
        self.bit
    }

    /// True when the bit is read inverted.
    pub fn inverted(&self) -> bool {
        self.invert
    }

    /// The device.
    pub fn device(&self) -> &Arc<dyn DigitalIn> {
        &self.device
    }
}

/// One digital output bit, optionally inverted.
#[derive(Clone)]
pub struct DigitalOutput {
    device: Arc<dyn DigitalOut>,
    bit: u32,
    invert: bool,
}

impl DigitalOutput {
    /// Bit `bit` of `device`, driven inverted when `invert`; fails if there is no such bit.
    pub fn new(device: Arc<dyn DigitalOut>, bit: u32, invert: bool) -> Result<Self, DeviceError> {
        check_bit(bit, device.output_count())?;
        Ok(DigitalOutput {
            device,
            bit,
            invert,
        })
    }

    /// Sets the logical output to `on`.
    pub fn set(&self, on: bool) -> Result<(), DeviceError> {
        self.device.set_bit(self.bit, on != self.invert)
    }

    /// Turns the logical output on.
    pub fn switch_on(&self) -> Result<(), DeviceError> {
        self.set(true)
    }

    /// Turns the logical output off.
    pub fn switch_off(&self) -> Result<(), DeviceError> {
        self.set(false)
    }

    /// True when the logical output was last set on.
    pub fn is_on(&self) -> Result<bool, DeviceError> {
        Ok(self.device.check_bit(self.bit)? != self.invert)
    }

    /// The bit number on the device.
    pub fn bit(&self) -> u32 {
        self.bit
    }

    /// True when the bit is driven inverted.
    pub fn inverted(&self) -> bool {
        self.invert
    }

    /// The device.
    pub fn device(&self) -> &Arc<dyn DigitalOut> {
        &self.device
    }
}
