//! The one error type every device method returns.
//!
//! Device methods are called from real-time threads, so errors are plain values: building
//! one never allocates (a bus error carries its cause behind an [`Arc`], built once by the
//! card's own bus activity and cloned cheaply afterwards).
//!
//! ```
//! use device_interface::DeviceError;
//!
//! let e = DeviceError::ChannelOutOfRange { channel: 9, count: 8 };
//! assert_eq!(e.to_string(), "channel 9 does not exist (the device has 8 channels: 0..=7)");
//! ```

use crate::text::Number;
use std::sync::Arc;
use std::time::Duration;

/// What a device method can report instead of a value.
///
/// `Clone` so a card can keep its last bus error and hand it to every caller without
/// allocating.
#[derive(Debug, Clone, thiserror::Error)]
#[non_exhaustive]
pub enum DeviceError {
    /// An analog channel index past the device's channel count.
    #[error("channel {channel} does not exist (the device has {count} channels: {})", span_text(*.count))]
    ChannelOutOfRange {
        /// The channel asked for.
        channel: u32,
        /// How many channels the device has.
        count: u32,
    },
    /// A digital bit index past the device's bit count.
    #[error("bit {bit} does not exist (the device has {count} bits: {})", span_text(*.count))]
    BitOutOfRange {
        /// The bit asked for.
        bit: u32,
        /// How many bits the device has.
        count: u32,
    },
    /// An inclusive bit span `start..=stop` that is empty, reversed, wider than 64 bits, or
    /// reaches past the last bit.
    #[error(
        "bit span {start}..={stop} is invalid for a device with {count} bits \
         (needs start <= stop < {count} and at most 64 bits)"
    )]
    SpanOutOfRange {
        /// First bit of the span.
        start: u32,
        /// Last bit of the span (inclusive).
        stop: u32,
        /// How many bits the device has.
        count: u32,
    },
    /// A sequence value with bits set above the span's width.
    #[error("value {value:#x} does not fit the {width}-bit span {start}..={stop}")]
    SequenceValueTooWide {
        /// First bit of the span.
        start: u32,
        /// Last bit of the span (inclusive).
        stop: u32,
        /// Width of the span in bits.
        width: u32,
        /// The refused value.
        value: u64,
    },
    /// A physical value outside the channel's range, or not a finite number.
    #[error(
        "value {} is outside channel {channel}'s range [{}, {}]",
        Number(*.value),
        Number(*.lowest),
        Number(*.highest)
    )]
    ValueOutOfRange {
        /// The channel written.
        channel: u32,
        /// The refused value.
        value: f64,
        /// Lowest accepted value.
        lowest: f64,
        /// Highest accepted value.
        highest: f64,
    },
    /// A raw value outside the channel's raw range.
    #[error("raw value {raw} is outside channel {channel}'s raw range [{min}, {max}]")]
    RawOutOfRange {
        /// The channel written.
        channel: u32,
        /// The refused raw value.
        raw: i64,
        /// Lowest raw value.
        min: i64,
        /// Highest raw value.
        max: i64,
    },
    /// An encoder position outside the interval set by the encoder's resolution.
    #[error("position {position} is outside the encoder's range {}", position_span(*.resolution))]
    PositionOutOfRange {
        /// The refused position.
        position: i64,
        /// The encoder's resolution (may be negative).
        resolution: i64,
    },
    /// A turn count the encoder's counter cannot hold.
    #[error("turn {turn} is beyond the encoder counter's range")]
    TurnOutOfRange {
        /// The refused turn count.
        turn: i64,
    },
    /// The device does not answer: link down, unplugged, or never seen.
    #[error("device is offline")]
    Offline,
    /// The output is held where it is: its owner (the gateway, stopping and driving its
    /// outputs to their safe values) takes no writes now.
    #[error("output held: {reason}")]
    Held {
        /// Why.
        reason: &'static str,
    },
    /// A write the device took did not reach the hardware: its bus refused it, gave no
    /// answer in time, or went away first (see [`Delivery`](crate::Delivery)).
    #[error("write not delivered: {reason}")]
    Undelivered {
        /// Why.
        reason: &'static str,
    },
    /// The device is reachable in principle but its inputs have not been refreshed in time.
    #[error("inputs are stale: last good sample {}", age_text(*.age))]
    Stale {
        /// How old the last good sample is; `None` if there never was one.
        age: Option<Duration>,
    },
    /// The bus reported a failure; the cause is kept.
    #[error("bus error: {source}")]
    Bus {
        /// The underlying failure, as reported by the bus activity.
        #[source]
        source: Arc<dyn std::error::Error + Send + Sync>,
    },
    /// The channel's source holds no number: a floating-point register reading NaN or an
    /// infinity. The channel's own status; the device's other channels are unaffected.
    #[error("channel {channel} holds {what}, not a number")]
    NotANumber {
        /// The channel.
        channel: u32,
        /// "NaN", "+inf" or "-inf".
        what: &'static str,
    },
    /// The device cannot do this (for example, selecting a range on a fixed-range card).
    #[error("unsupported by this device: {what}")]
    Unsupported {
        /// What was asked.
        what: &'static str,
    },
    /// A logical device refuses the command in its present state (a disabled drive given a
    /// velocity, an axis in error asked to move); nothing was written.
    #[error("refused: {reason}")]
    Refused {
        /// Why, and what would make it possible.
        reason: &'static str,
    },
}

impl DeviceError {
    /// [`NotANumber`](DeviceError::NotANumber) for channel `channel` holding `v` (NaN or
    /// an infinity), naming which.
    pub fn not_a_number(channel: u32, v: f64) -> DeviceError {
        DeviceError::NotANumber {
            channel,
            what: if v.is_nan() {
                "NaN"
            } else if v > 0.0 {
                "+inf"
            } else {
                "-inf"
            },
        }
    }

    /// True for a condition of the device or its bus that may pass by itself — offline,
    /// stale, a bus error — as opposed to a call that can never succeed (a channel, value
    /// or operation the device does not have) or outputs held at stop. A component may
    /// wait such a condition out in RunTimeError rather than fail.
    pub fn is_transient(&self) -> bool {
        matches!(
            self,
            DeviceError::Offline | DeviceError::Stale { .. } | DeviceError::Bus { .. }
        )
    }

    /// Wraps any error as a bus error.
    ///
    /// Allocates once; do it on the card's bus activity, not on a real-time path, and clone
    /// the result from there.
    pub fn bus(source: impl std::error::Error + Send + Sync + 'static) -> Self {
        DeviceError::Bus {
            source: Arc::new(source),
        }
    }
}

fn span_text(count: u32) -> String {
    match count {
        0 => "none".to_string(),
        n => format!("0..={}", n - 1),
    }
}

fn position_span(resolution: i64) -> String {
    if resolution > 0 {
        format!("0..={}", resolution - 1)
    } else {
        format!("{}..=0", resolution + 1)
    }
}

fn age_text(age: Option<Duration>) -> String {
    match age {
        Some(a) => format!("{:.3} s ago", a.as_secs_f64()),
        None => "never".to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_name_what_and_where() {
        let cases: Vec<(DeviceError, &str)> = vec![
            (
                DeviceError::BitOutOfRange { bit: 3, count: 0 },
                "bit 3 does not exist (the device has 0 bits: none)",
            ),
            (
                DeviceError::SpanOutOfRange {
                    start: 5,
                    stop: 2,
                    count: 8,
                },
                "bit span 5..=2 is invalid for a device with 8 bits (needs start <= stop < 8 and at most 64 bits)",
            ),
            (
                DeviceError::PositionOutOfRange {
                    position: -4,
                    resolution: -4,
                },
                "position -4 is outside the encoder's range -3..=0",
            ),
            (
                DeviceError::Stale {
                    age: Some(Duration::from_millis(1500)),
                },
                "inputs are stale: last good sample 1.500 s ago",
            ),
            (
                DeviceError::bus(std::io::Error::from_raw_os_error(19)),
                "bus error: No such device (os error 19)",
            ),
        ];
        for (e, text) in cases {
            assert_eq!(e.to_string(), text);
        }
    }

    #[test]
    fn bus_error_keeps_its_source() {
        let e = DeviceError::bus(std::io::Error::from_raw_os_error(5));
        let src = std::error::Error::source(&e).expect("bus error has a source");
        assert!(src.to_string().contains("os error 5"));
    }
}
