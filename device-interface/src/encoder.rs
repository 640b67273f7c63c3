//! Position/turn arithmetic for encoders, shared by every driver that counts.
//!
//! An [`EncoderCounter`] keeps one signed count of motion (positive = the positive
//! direction) in an atomic and derives position and turn from it by the rules of the
//! [`Encoder`](crate::Encoder) trait, so a simulated axis, a CAN position signal with turn
//! counting on wrap and a software quadrature decoder all agree on what "position 0,
//! turn 1" means.
//!
//! ```
//! use device_interface::encoder::EncoderCounter;
//!
//! let enc = EncoderCounter::new(1000, true)?;
//! enc.set_position(999)?;
//! enc.advance(2); // roll over
//! assert_eq!((enc.position(), enc.turn()), (1, 1));
//! # Ok::<(), device_interface::DeviceError>(())
//! ```

use crate::DeviceError;
use std::sync::atomic::{AtomicI64, Ordering};

/// Resolution and counting direction of an encoder.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EncoderGeometry {
    resolution: i64,
    upcounting: bool,
}

impl EncoderGeometry {
    /// An encoder with `resolution` counts per turn (negative: positions run from
    /// `resolution+1` to 0). A resolution of 0 or `i64::MIN` is refused with
    /// [`DeviceError::PositionOutOfRange`].
    pub fn new(resolution: i64, upcounting: bool) -> Result<Self, DeviceError> {
        if resolution == 0 || resolution == i64::MIN {
            return Err(DeviceError::PositionOutOfRange {
                position: 0,
                resolution,
            });
        }
        Ok(EncoderGeometry {
            resolution,
            upcounting,
        })
    }

    /// Counts per turn, with its sign.
    pub fn resolution(&self) -> i64 {
        self.resolution
    }

    /// True when positive motion raises the position.
    pub fn upcounting(&self) -> bool {
        self.upcounting
    }

    /// Checks that `position` lies in the interval the resolution allows.
    pub fn check_position(&self, position: i64) -> Result<(), DeviceError> {
        let ok = if self.resolution > 0 {
            (0..self.resolution).contains(&position)
        } else {
            (self.resolution + 1..=0).contains(&position)
        };
        if ok {
            Ok(())
        } else {
            Err(DeviceError::PositionOutOfRange {
                position,
                resolution: self.resolution,
            })
        }
    }

    /// (position, turn) of a motion count.
    pub fn split(&self, total: i64) -> (i64, i64) {
        let m = self.resolution.abs();
        // Downcounting mirrors the count, so the roll-over from 0 to the last position adds
        // the turn.
        let k = if self.upcounting {
            i128::from(total)
        } else {
            -i128::from(total)
        };
        let (p, q) = (k.rem_euclid(i128::from(m)), k.div_euclid(i128::from(m)));
        let turn = if self.upcounting { q } else { -q };
        let position = if self.resolution > 0 { p } else { -p };
        // |p| < m <= i64::MAX and |q| <= |total|, so both fit.
        (position as i64, turn as i64)
    }

    /// The motion count of (position, turn); the inverse of [`split`](Self::split).
    pub fn join(&self, position: i64, turn: i64) -> Result<i64, DeviceError> {
        self.check_position(position)?;
        let m = i128::from(self.resolution.abs());
        let p = i128::from(position.abs());
        let total = if self.upcounting {
            i128::from(turn) * m + p
        } else {
            -(-i128::from(turn) * m + p)
        };
        i64::try_from(total).map_err(|_| DeviceError::TurnOutOfRange { turn })
    }
}

/// A lock-free encoder count: read and set from any thread, advanced by the bus activity.
#[derive(Debug)]
pub struct EncoderCounter {
    geometry: EncoderGeometry,
    total: AtomicI64,
}

impl EncoderCounter {
    /// A counter at position 0, turn 0. Errors as [`EncoderGeometry::new`].
    pub fn new(resolution: i64, upcounting: bool) -> Result<Self, DeviceError> {
        Ok(EncoderCounter {
            geometry: EncoderGeometry::new(resolution, upcounting)?,
            total: AtomicI64::new(0),
        })
    }

    /// The counter's geometry.
    pub fn geometry(&self) -> EncoderGeometry {
        self.geometry
    }

    /// The position within the current turn.
    pub fn position(&self) -> i64 {
        self.geometry.split(self.total()).0
    }

    /// The number of turns.
    pub fn turn(&self) -> i64 {
        self.geometry.split(self.total()).1
    }

    /// The raw motion count.
    pub fn total(&self) -> i64 {
        self.total.load(Ordering::Acquire)
    }

    /// Adds `counts` of motion (negative: the negative direction). Wraps at the ends of
    /// `i64`, as a hardware counter does.
    pub fn advance(&self, counts: i64) {
        self.total.fetch_add(counts, Ordering::AcqRel);
    }

    /// Sets the position and keeps the turn.
    pub fn set_position(&self, position: i64) -> Result<(), DeviceError> {
        self.update(|g, _, turn| g.join(position, turn))
    }

    /// Sets the turn and keeps the position.
    pub fn set_turn(&self, turn: i64) -> Result<(), DeviceError> {
        self.update(|g, position, _| g.join(position, turn))
    }

    fn update(
        &self,
        f: impl Fn(&EncoderGeometry, i64, i64) -> Result<i64, DeviceError>,
    ) -> Result<(), DeviceError> {
        // A compare-and-swap loop, so motion counted concurrently is not lost.
        let mut cur = self.total();
        loop {
            let (p, t) = self.geometry.split(cur);
            let new = f(&self.geometry, p, t)?;
            match self
                .total
                .compare_exchange_weak(cur, new, Ordering::AcqRel, Ordering::Acquire)
            {
                Ok(_) => return Ok(()),
                Err(now) => cur = now,
            }
        }
    }
}

/// An [`EncoderCounter`] fed by readings of a wrapping hardware counter (a Modbus counter
/// register, a CAN position signal): each reading advances the count by the difference to
/// the previous one, across the wrap, the shorter way round. The first reading is the
/// baseline.
#[derive(Debug)]
pub struct WrappingCounter {
    counter: EncoderCounter,
    last: AtomicI64,
    seen: std::sync::atomic::AtomicBool,
    bits: u32,
}

impl WrappingCounter {
    /// Follows a `bits`-wide counter (it wraps at 2^bits; 64 for a full `i64`). Errors as
    /// [`EncoderGeometry::new`].
    pub fn new(resolution: i64, upcounting: bool, bits: u32) -> Result<Self, DeviceError> {
        Ok(WrappingCounter {
            counter: EncoderCounter::new(resolution, upcounting)?,
            last: AtomicI64::new(0),
            seen: std::sync::atomic::AtomicBool::new(false),
            bits: bits.clamp(1, 64),
        })
    }

    /// Makes the next reading a new baseline (the count keeps its value): for a hardware
    /// counter that restarted (its board reset, unplugged and back), whose next reading
    /// has nothing to do with the last.
    pub fn rebase(&self) {
        self.seen.store(false, Ordering::Release);
    }

    /// Takes a new counter reading (signed or unsigned, as the counter gives it).
    pub fn sample(&self, raw: i64) {
        let prev = self.last.swap(raw, Ordering::AcqRel);
        if !self.seen.swap(true, Ordering::AcqRel) {
            return;
        }
        let delta = if self.bits >= 64 {
            raw.wrapping_sub(prev)
        } else {
            let m = 1i128 << self.bits;
            let d = (i128::from(raw) - i128::from(prev)).rem_euclid(m);
            (if d >= m / 2 { d - m } else { d }) as i64
        };
        self.counter.advance(delta);
    }

    /// The count.
    pub fn counter(&self) -> &EncoderCounter {
        &self.counter
    }
}

/// A card that keeps its encoders' counts in software ([`EncoderCounter`] or
/// [`WrappingCounter`]) and says when they are current: what [`CardEncoder`] needs to be
/// an [`Encoder`](crate::Encoder) device.
pub trait EncoderHost: crate::Device + Send + Sync + 'static {
    /// The count of encoder `index` (an index the card handed to [`CardEncoder::new`]).
    fn encoder_counter(&self, index: usize) -> &EncoderCounter;
    /// `Ok` when encoder `index`'s count is current; else why not (stale, offline).
    fn check_encoder(&self, index: usize) -> Result<(), DeviceError>;
    /// `Ok` when the card takes writes (homing an encoder is refused while offline).
    fn check_writable(&self) -> Result<(), DeviceError>;
    /// Encoder `index`'s health: the card's, unless the card can say better (an encoder
    /// fed by a message of its own).
    fn encoder_health(&self, index: usize) -> crate::Health {
        let _ = index;
        self.health()
    }
}

/// Encoder `index` of a card, as a device of its own. Homing (`set_position`,
/// `set_turn`) changes the software count only; nothing is written to the device.
pub struct CardEncoder<H: EncoderHost> {
    host: std::sync::Arc<H>,
    index: usize,
}

impl<H: EncoderHost> CardEncoder<H> {
    /// Encoder `index` of `host`.
    pub fn new(host: std::sync::Arc<H>, index: usize) -> Self {
        CardEncoder { host, index }
    }

    /// Encoders `0..count` of `host` as the card's devices, named `encoder0`,
    /// `encoder1`, … (what [`CardDevices::encoders`](crate::CardDevices) takes).
    pub fn all(
        host: &std::sync::Arc<H>,
        count: usize,
    ) -> Vec<(String, std::sync::Arc<dyn crate::Encoder>)> {
        (0..count)
            .map(|i| {
                (
                    format!("encoder{i}"),
                    std::sync::Arc::new(CardEncoder::new(host.clone(), i))
                        as std::sync::Arc<dyn crate::Encoder>,
                )
            })
            .collect()
    }

    fn counter(&self) -> &EncoderCounter {
        self.host.encoder_counter(self.index)
    }
}

impl<H: EncoderHost> crate::Device for CardEncoder<H> {
    fn health(&self) -> crate::Health {
        self.host.encoder_health(self.index)
    }
}

impl<H: EncoderHost> crate::Encoder for CardEncoder<H> {
    fn position(&self) -> Result<i64, DeviceError> {
        self.host.check_encoder(self.index)?;
        Ok(self.counter().position())
    }

    fn turn(&self) -> Result<i64, DeviceError> {
        self.host.check_encoder(self.index)?;
        Ok(self.counter().turn())
    }

    fn set_position(&self, position: i64) -> Result<(), DeviceError> {
        self.counter().geometry().check_position(position)?;
        self.host.check_writable()?;
        self.counter().set_position(position)
    }

    fn set_turn(&self, turn: i64) -> Result<(), DeviceError> {
        self.host.check_writable()?;
        self.counter().set_turn(turn)
    }

    fn resolution(&self) -> i64 {
        self.counter().geometry().resolution()
    }

    fn upcounting(&self) -> bool {
        self.counter().geometry().upcounting()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrapping_counter_follows_across_the_wrap() {
        let w = WrappingCounter::new(1000, true, 16).unwrap();
        w.sample(65_530); // baseline
        w.sample(4); // +10 across the wrap
        assert_eq!(w.counter().total(), 10);
        w.sample(65_534); // -6 back across it
        assert_eq!(w.counter().total(), 4);
        let s = WrappingCounter::new(1000, true, 8).unwrap();
        s.sample(127);
        s.sample(-128); // signed 8-bit: +1
        assert_eq!(s.counter().total(), 1);
    }

    #[test]
    fn split_join_round_trip_all_geometries() {
        for (res, up) in [(4, true), (4, false), (-4, true), (-4, false), (1, true)] {
            let g = EncoderGeometry::new(res, up).unwrap();
            for total in -20..=20 {
                let (p, t) = g.split(total);
                g.check_position(p).unwrap();
                assert_eq!(
                    g.join(p, t).unwrap(),
                    total,
                    "res {res} up {up} total {total}"
                );
            }
        }
    }

    #[test]
    fn roll_over_direction() {
        // Upcounting: 3 -> 0 adds a turn.
        let up = EncoderGeometry::new(4, true).unwrap();
        assert_eq!(up.split(3), (3, 0));
        assert_eq!(up.split(4), (0, 1));
        assert_eq!(up.split(-1), (3, -1));
        // Downcounting: positive motion lowers the position; 0 -> 3 adds a turn.
        let down = EncoderGeometry::new(4, false).unwrap();
        assert_eq!(down.split(1), (3, 1));
        assert_eq!(down.split(2), (2, 1));
        assert_eq!(down.split(4), (0, 1));
        assert_eq!(down.split(5), (3, 2));
        // Negative resolution: positions 0, -1, -2, -3.
        let neg = EncoderGeometry::new(-4, true).unwrap();
        assert_eq!(neg.split(3), (-3, 0));
        assert_eq!(neg.split(4), (0, 1));
    }

    #[test]
    fn refusals() {
        assert!(EncoderGeometry::new(0, true).is_err());
        let c = EncoderCounter::new(100, true).unwrap();
        c.set_turn(5).unwrap();
        c.set_position(42).unwrap();
        assert!(c.set_position(100).is_err());
        assert!(c.set_position(-1).is_err());
        assert!(matches!(
            c.set_turn(i64::MAX),
            Err(DeviceError::TurnOutOfRange { .. })
        ));
        assert_eq!((c.position(), c.turn()), (42, 5));
    }
}
