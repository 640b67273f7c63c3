//! The five device interfaces: AnalogIn, AnalogOut, DigitalIn, DigitalOut, Encoder.
//!
//! These are the Orocos Hardware Device Interfaces with Rust names. A driver implements the
//! ones its card offers; components use them through `Arc<dyn Trait>` handles from the
//! [`Registry`](crate::Registry) and never see the driver's type.
//!
//! # The real-time contract
//!
//! Every method may be called from a real-time thread: it does not block, runs in bounded
//! time and does not allocate. Bus I/O happens on the card's own activity; these methods read
//! the card's latest input image and update its output image. Failures are
//! [`DeviceError`] values, never panics.
//!
//! Inputs of a device that is [offline](crate::Status::Offline) fail with
//! [`DeviceError::Offline`]; of a [stale](crate::Status::Stale) one with
//! [`DeviceError::Stale`]. Outputs of an offline device fail with [`DeviceError::Offline`]
//! and the output image is left unchanged, so nothing is silently lost.
//!
//! ```
//! use device_interface::{DeviceError, DigitalOut};
//!
//! fn blink(out: &dyn DigitalOut, bit: u32) -> Result<(), DeviceError> {
//!     let on = out.check_bit(bit)?;
//!     out.set_bit(bit, !on)
//! }
//! ```

use crate::bits::BitSpan;
use crate::{AnalogRange, Scale};
use crate::{Delivery, DeviceError, Health, RawRange};

/// What every device has: a health report.
pub trait Device: Send + Sync {
    /// The device's health now: online, stale or offline, and the age of its last good
    /// sample. Never fails; an unreachable device reports [`Status::Offline`](crate::Status).
    fn health(&self) -> Health;
}

/// How an analog input's voltage is referenced (comedi's AREF_*).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum AnalogReference {
    /// Single-ended, to ground.
    Ground,
    /// Single-ended, to a common reference.
    Common,
    /// Differential, against the paired channel.
    Differential,
    /// Card-specific.
    Other,
}

/// Analog input channels read in physical units.
///
/// Channels are numbered `0..channel_count()`. Every method taking a channel fails with
/// [`DeviceError::ChannelOutOfRange`] for a channel past the end.
pub trait AnalogIn: Device {
    /// Number of channels.
    fn channel_count(&self) -> u32;

    /// The channel's raw-to-physical scale: raw range, physical range, unit.
    fn scale(&self, channel: u32) -> Result<Scale, DeviceError>;

    /// The latest raw sample of `channel`, within [`raw_range`](Self::raw_range).
    ///
    /// Errors: channel out of range, [`Offline`](DeviceError::Offline),
    /// [`Stale`](DeviceError::Stale), or a [`Bus`](DeviceError::Bus) error.
    fn read_raw(&self, channel: u32) -> Result<i64, DeviceError>;

    /// The latest sample of `channel` in physical units: `scale(channel).to_physical(raw)`.
    ///
    /// Errors as [`read_raw`](Self::read_raw).
    fn read(&self, channel: u32) -> Result<f64, DeviceError> {
        let scale = self.scale(channel)?;
        Ok(scale.to_physical(self.read_raw(channel)?))
    }

    /// Lowest and highest physical value of `channel`, and its unit.
    fn range(&self, channel: u32) -> Result<AnalogRange, DeviceError> {
        Ok(self.scale(channel)?.range())
    }

    /// Lowest and highest raw value of `channel`.
    fn raw_range(&self, channel: u32) -> Result<RawRange, DeviceError> {
        Ok(self.scale(channel)?.raw_range())
    }

    /// Physical size of one raw step of `channel` (positive).
    fn resolution(&self, channel: u32) -> Result<f64, DeviceError> {
        Ok(self.scale(channel)?.resolution())
    }

    /// Number of selectable ranges of `channel` (1 for a fixed-range channel).
    fn range_count(&self, channel: u32) -> Result<u32, DeviceError> {
        self.scale(channel).map(|_| 1)
    }

    /// Selects range `index` (`0..range_count`) of `channel`; [`scale`](Self::scale) then
    /// reports it. Default: [`Unsupported`](DeviceError::Unsupported).
    fn select_range(&self, channel: u32, index: u32) -> Result<(), DeviceError> {
        let _ = (channel, index);
        Err(DeviceError::Unsupported {
            what: "range selection",
        })
    }

    /// Selects how `channel` is referenced. Default:
    /// [`Unsupported`](DeviceError::Unsupported).
    fn select_reference(
        &self,
        channel: u32,
        reference: AnalogReference,
    ) -> Result<(), DeviceError> {
        let _ = (channel, reference);
        Err(DeviceError::Unsupported {
            what: "analog reference selection",
        })
    }
}

/// Analog output channels written in physical units.
///
/// Channels are numbered `0..channel_count()`; every method taking a channel fails with
/// [`DeviceError::ChannelOutOfRange`] for a channel past the end. A refused write leaves the
/// output unchanged.
pub trait AnalogOut: Device {
    /// Number of channels.
    fn channel_count(&self) -> u32;

    /// The channel's raw-to-physical scale: raw range, physical range, unit.
    fn scale(&self, channel: u32) -> Result<Scale, DeviceError>;

    /// Sets `channel` to the raw value `raw`.
    ///
    /// Errors: channel out of range, [`RawOutOfRange`](DeviceError::RawOutOfRange),
    /// [`Offline`](DeviceError::Offline), [`Bus`](DeviceError::Bus).
    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError>;

    /// Sets `channel` to `value` in physical units, rounded to the nearest raw step.
    ///
    /// Errors: channel out of range, [`ValueOutOfRange`](DeviceError::ValueOutOfRange)
    /// (outside [`range`](Self::range), NaN or infinite), and as
    /// [`write_raw`](Self::write_raw).
    fn write(&self, channel: u32, value: f64) -> Result<(), DeviceError> {
        let raw = self.scale(channel)?.to_raw_checked(channel, value)?;
        self.write_raw(channel, raw)
    }

    /// The raw value last written to `channel` (its initial value before any write).
    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError>;

    /// Where the writes to `channel` stand, for a device whose bus carries them after
    /// [`write_raw`](Self::write_raw) returned (see [`Delivery`]); `None` (the default)
    /// when a write that returned `Ok` is on the device already. Not for real-time paths.
    fn delivery(&self, _channel: u32) -> Option<Delivery> {
        None
    }

    /// The value last written to `channel`, in physical units as the hardware will output it
    /// (that is, after rounding to a raw step).
    fn read_back(&self, channel: u32) -> Result<f64, DeviceError> {
        let scale = self.scale(channel)?;
        Ok(scale.to_physical(self.read_back_raw(channel)?))
    }

    /// Lowest and highest physical value of `channel`, and its unit.
    fn range(&self, channel: u32) -> Result<AnalogRange, DeviceError> {
        Ok(self.scale(channel)?.range())
    }

    /// Lowest and highest raw value of `channel`.
    fn raw_range(&self, channel: u32) -> Result<RawRange, DeviceError> {
        Ok(self.scale(channel)?.raw_range())
    }

    /// Physical size of one raw step of `channel` (positive).
    fn resolution(&self, channel: u32) -> Result<f64, DeviceError> {
        Ok(self.scale(channel)?.resolution())
    }
}

/// Digital inputs, addressed by bit number.
///
/// Bits are numbered `0..input_count()`; a bit past the end fails with
/// [`DeviceError::BitOutOfRange`]. Input errors as for [`AnalogIn::read_raw`].
pub trait DigitalIn: Device {
    /// Number of input bits.
    fn input_count(&self) -> u32;

    /// The state of input `bit`.
    fn read_bit(&self, bit: u32) -> Result<bool, DeviceError>;

    /// True when input `bit` is on.
    fn is_on(&self, bit: u32) -> Result<bool, DeviceError> {
        self.read_bit(bit)
    }

    /// True when input `bit` is off.
    fn is_off(&self, bit: u32) -> Result<bool, DeviceError> {
        self.read_bit(bit).map(|b| !b)
    }

    /// Inputs `start..=stop` as a number: bit `start` becomes bit 0 of the result.
    ///
    /// Errors with [`SpanOutOfRange`](DeviceError::SpanOutOfRange) when `start > stop`,
    /// `stop >= input_count()` or the span is wider than 64 bits. The default reads bit by
    /// bit; drivers with an image override it to read the span at once.
    fn read_sequence(&self, start: u32, stop: u32) -> Result<u64, DeviceError> {
        let span = BitSpan::new(start, stop, self.input_count())?;
        span.bits().try_fold(0u64, |acc, (bit, i)| {
            Ok(acc | (u64::from(self.read_bit(bit)?) << i))
        })
    }
}

/// Digital outputs, addressed by bit number.
///
/// Bits are numbered `0..output_count()`; a bit past the end fails with
/// [`DeviceError::BitOutOfRange`]. A refused write leaves every output unchanged.
pub trait DigitalOut: Device {
    /// Number of output bits.
    fn output_count(&self) -> u32;

    /// Sets output `bit` to `value`.
    ///
    /// Errors: bit out of range, [`Offline`](DeviceError::Offline),
    /// [`Bus`](DeviceError::Bus).
    fn set_bit(&self, bit: u32, value: bool) -> Result<(), DeviceError>;

    /// Turns output `bit` on.
    fn switch_on(&self, bit: u32) -> Result<(), DeviceError> {
        self.set_bit(bit, true)
    }

    /// Turns output `bit` off.
    fn switch_off(&self, bit: u32) -> Result<(), DeviceError> {
        self.set_bit(bit, false)
    }

    /// The state output `bit` was last set to.
    fn check_bit(&self, bit: u32) -> Result<bool, DeviceError>;

    /// Where the writes to `bit` stand, for a device whose bus carries them after
    /// [`set_bit`](Self::set_bit) returned (see [`Delivery`]); `None` (the default) when a
    /// write that returned `Ok` is on the device already. Not for real-time paths.
    fn delivery(&self, _bit: u32) -> Option<Delivery> {
        None
    }

    /// Sets outputs `start..=stop` from `value`: bit 0 of `value` goes to output `start`.
    ///
    /// Errors: [`SpanOutOfRange`](DeviceError::SpanOutOfRange) as for
    /// [`DigitalIn::read_sequence`];
    /// [`SequenceValueTooWide`](DeviceError::SequenceValueTooWide) when `value` has bits
    /// above the span's width. The default sets bit by bit; drivers with an image override
    /// it to write the span at once.
    fn set_sequence(&self, start: u32, stop: u32, value: u64) -> Result<(), DeviceError> {
        let span = BitSpan::new(start, stop, self.output_count())?;
        span.check_value(value)?;
        span.bits()
            .try_for_each(|(bit, i)| self.set_bit(bit, value >> i & 1 == 1))
    }

    /// The states outputs `start..=stop` were last set to, bit `start` at bit 0.
    ///
    /// Errors as for [`DigitalIn::read_sequence`].
    fn check_sequence(&self, start: u32, stop: u32) -> Result<u64, DeviceError> {
        let span = BitSpan::new(start, stop, self.output_count())?;
        span.bits().try_fold(0u64, |acc, (bit, i)| {
            Ok(acc | (u64::from(self.check_bit(bit)?) << i))
        })
    }
}

/// A position/turn encoder.
///
/// The position counts within one turn: in `0..resolution` when the resolution is positive,
/// in `resolution+1..=0` when it is negative. The turn counts completed turns. With
/// [`upcounting`](Encoder::upcounting), motion in the positive direction raises the position
/// and a roll-over from the last position to 0 adds one turn; otherwise the position falls
/// and a roll-over from 0 to the last position adds one turn.
pub trait Encoder: Device {
    /// The position within the current turn.
    ///
    /// Errors: [`Offline`](DeviceError::Offline), [`Stale`](DeviceError::Stale),
    /// [`Bus`](DeviceError::Bus).
    fn position(&self) -> Result<i64, DeviceError>;

    /// The number of turns.
    ///
    /// Errors as [`position`](Self::position).
    fn turn(&self) -> Result<i64, DeviceError>;

    /// Sets the position within the current turn (homing).
    ///
    /// Errors: [`PositionOutOfRange`](DeviceError::PositionOutOfRange) outside the interval
    /// the resolution allows; [`Offline`](DeviceError::Offline), [`Bus`](DeviceError::Bus).
    fn set_position(&self, position: i64) -> Result<(), DeviceError>;

    /// Sets the turn count; the position is kept.
    ///
    /// Errors: [`TurnOutOfRange`](DeviceError::TurnOutOfRange) when the counter cannot hold
    /// it; [`Offline`](DeviceError::Offline), [`Bus`](DeviceError::Bus).
    fn set_turn(&self, turn: i64) -> Result<(), DeviceError>;

    /// Counts per turn; negative when positions run from `resolution+1` to 0. Never 0.
    fn resolution(&self) -> i64;

    /// True when motion in the positive direction raises the position.
    fn upcounting(&self) -> bool;
}
