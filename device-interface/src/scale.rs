//! Raw-to-physical conversion of analog channels, shared by every driver.
//!
//! Drivers deal in raw values (ADC counts, register contents, signal bits); a [`Scale`] turns
//! them into physical values in a [`Unit`] and back. It is the one place this arithmetic
//! lives, so every bus converts, rounds and range-checks the same way.
//!
//! A scale maps the raw range `[min, max]` linearly onto the physical values at its two ends.
//! It is built either from the physical range ([`Scale::linear`], the Orocos and comedi view)
//! or from a factor and offset ([`Scale::from_factor`], the DBC and Modbus view). Endpoints
//! convert exactly: the lowest raw value gives exactly the lowest physical value.
//!
//! ```
//! use device_interface::{RawRange, Scale, Unit};
//!
//! // A 12-bit ADC reading 0..10 V.
//! let s = Scale::linear(RawRange::unsigned_bits(12)?, 0.0, 10.0, Unit::new("V")?)?;
//! assert_eq!(s.to_physical(4095), 10.0);
//! assert_eq!(s.to_raw(5.0), Some(2048)); // rounds to the nearest count
//! assert_eq!(s.to_raw(10.5), None); // out of range
//! assert!((s.resolution() - 10.0 / 4095.0).abs() < 1e-15);
//!
//! // A CAN signal: physical = raw * 0.1 - 40 degC, raw is a signed byte.
//! let t = Scale::from_factor(RawRange::signed_bits(8)?, 0.1, -40.0, Unit::new("degC")?)?;
//! assert_eq!(t.range().lowest, -52.8);
//! # Ok::<(), device_interface::ScaleError>(())
//! ```

use crate::text::{Number, Quoted};
use std::fmt;

/// Why a scale, raw range or unit could not be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum ScaleError {
    /// The raw range is empty or reversed.
    #[error("raw range [{min}, {max}] is invalid: min must be below max")]
    InvalidRawRange {
        /// Given minimum.
        min: i64,
        /// Given maximum.
        max: i64,
    },
    /// A bit width that does not give a raw range (0, or over 63 bits).
    #[error("raw width of {bits} bits is invalid: expected 1..=63")]
    InvalidBits {
        /// Given width.
        bits: u32,
    },
    /// The physical range is empty, reversed or not finite.
    #[error(
        "physical range [{}, {}] is invalid: needs finite lowest < highest",
        Number(*.lowest),
        Number(*.highest)
    )]
    InvalidPhysicalRange {
        /// Given lowest value.
        lowest: f64,
        /// Given highest value.
        highest: f64,
    },
    /// A physical range whose span, `highest - lowest`, is beyond the largest `f64`: no
    /// value inside it could be computed (every one would come out NaN).
    #[error(
        "physical range [{}, {}] is too wide: its span (highest - lowest) is infinite, beyond \
         the largest number (about 1.8e308); narrow it",
        Number(*.lowest),
        Number(*.highest)
    )]
    SpanNotFinite {
        /// Lowest value.
        lowest: f64,
        /// Highest value.
        highest: f64,
    },
    /// A factor of zero, or a factor or offset that is not finite.
    #[error(
        "factor {} and offset {} are invalid: needs a finite non-zero factor and a finite offset",
        Number(*.factor),
        Number(*.offset)
    )]
    InvalidFactor {
        /// Given factor.
        factor: f64,
        /// Given offset.
        offset: f64,
    },
    /// A unit name longer than [`Unit::MAX_LEN`] bytes.
    #[error("unit {} is longer than {} bytes", Quoted(.unit), Unit::MAX_LEN)]
    UnitTooLong {
        /// The refused unit.
        unit: String,
    },
}

/// The unit of a physical value ("V", "mA", "degC", "rad/s"), stored inline.
///
/// `Copy` and allocation-free so ranges can be returned from real-time paths.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct Unit {
    len: u8,
    bytes: [u8; Unit::MAX_LEN],
}

impl Unit {
    /// Longest unit name in bytes.
    pub const MAX_LEN: usize = 23;

    /// A unit named `name`; the empty string means dimensionless.
    pub fn new(name: &str) -> Result<Unit, ScaleError> {
        if name.len() > Self::MAX_LEN {
            return Err(ScaleError::UnitTooLong {
                unit: name.to_string(),
            });
        }
        let mut bytes = [0u8; Self::MAX_LEN];
        bytes[..name.len()].copy_from_slice(name.as_bytes());
        Ok(Unit {
            // Fits: checked against MAX_LEN above.
            len: name.len() as u8,
            bytes,
        })
    }

    /// A dimensionless unit.
    pub const fn none() -> Unit {
        Unit {
            len: 0,
            bytes: [0; Self::MAX_LEN],
        }
    }

    /// The unit's name.
    pub fn as_str(&self) -> &str {
        // Built from a &str cut at its own length, so always valid UTF-8.
        std::str::from_utf8(&self.bytes[..usize::from(self.len)]).unwrap_or("")
    }
}

impl fmt::Debug for Unit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Unit({:?})", self.as_str())
    }
}

impl fmt::Display for Unit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl serde::Serialize for Unit {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.as_str())
    }
}

impl<'de> serde::Deserialize<'de> for Unit {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = <std::borrow::Cow<'de, str>>::deserialize(d)?;
        Unit::new(&s).map_err(serde::de::Error::custom)
    }
}

/// The physical range of an analog channel.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct AnalogRange {
    /// Lowest value the channel can read or write.
    pub lowest: f64,
    /// Highest value the channel can read or write.
    pub highest: f64,
    /// Unit of the values.
    pub unit: Unit,
}

impl fmt::Display for AnalogRange {
    /// `[0, 10] V` (the unit left out when there is none).
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "[{}, {}]", Number(self.lowest), Number(self.highest))?;
        if !self.unit.as_str().is_empty() {
            write!(f, " {}", self.unit)?;
        }
        Ok(())
    }
}

/// The inclusive range of raw values of a channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub struct RawRange {
    /// Lowest raw value.
    pub min: i64,
    /// Highest raw value.
    pub max: i64,
}

impl RawRange {
    /// `[min, max]`; `min` must be below `max`.
    pub fn new(min: i64, max: i64) -> Result<RawRange, ScaleError> {
        if min < max {
            Ok(RawRange { min, max })
        } else {
            Err(ScaleError::InvalidRawRange { min, max })
        }
    }

    /// `[0, 2^bits - 1]`: an unsigned converter of `bits` bits.
    pub fn unsigned_bits(bits: u32) -> Result<RawRange, ScaleError> {
        if !(1..=63).contains(&bits) {
            return Err(ScaleError::InvalidBits { bits });
        }
        Ok(RawRange {
            min: 0,
            // 2^bits - 1 without overflowing at 63 bits.
            max: i64::MAX >> (63 - bits),
        })
    }

    /// `[-2^(bits-1), 2^(bits-1) - 1]`: a two's-complement value of `bits` bits.
    pub fn signed_bits(bits: u32) -> Result<RawRange, ScaleError> {
        if !(2..=63).contains(&bits) {
            return Err(ScaleError::InvalidBits { bits });
        }
        let half = 1i64 << (bits - 1);
        Ok(RawRange {
            min: -half,
            max: half - 1,
        })
    }

    /// True when `raw` lies in the range.
    pub fn contains(&self, raw: i64) -> bool {
        (self.min..=self.max).contains(&raw)
    }

    /// `raw` moved into the range.
    pub fn clamp(&self, raw: i64) -> i64 {
        raw.clamp(self.min, self.max)
    }

    fn steps(&self) -> f64 {
        // i128 avoids overflow for ranges spanning most of i64.
        (i128::from(self.max) - i128::from(self.min)) as f64
    }
}

impl fmt::Display for RawRange {
    /// `[0, 65535]`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "[{}, {}]", self.min, self.max)
    }
}

/// A linear map between a raw range and physical values.
///
/// `Copy`: devices hand it out from real-time paths.
///
/// It crosses a wire as its parts (`raw`, `at_min`, `at_max`, `formula`, `unit`,
/// `ties_to_even`); reading it back builds it again through the constructors, so a
/// hostile peer's scale is refused as one from a configuration would be.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "ScaleParts")]
pub struct Scale {
    raw: RawRange,
    /// Physical value at `raw.min`.
    at_min: f64,
    /// Physical value at `raw.max` (below `at_min` for a negative factor).
    at_max: f64,
    /// How a raw value becomes physical.
    formula: Formula,
    unit: Unit,
    /// A value half a step between two raw values goes to the even one (else away from
    /// zero).
    ties_to_even: bool,
}

/// `raw × factor + offset` rounded once where it can be: an integral factor and offset are
/// multiplied and added as integers (exact), then rounded to f64; an integral factor
/// with a fractional offset rounds the exact product, then adds; any other factor is
/// f64 arithmetic. For values below 2^53 all three are the plain f64 formula; beyond, this
/// is what cantools computes (Python's integers are exact) and never less exact than it.
pub fn linear(raw: i128, factor: f64, offset: f64) -> f64 {
    Linear::new(factor, offset).apply(raw)
}

/// [`linear`] with its factor and offset looked at once, when it is made, rather than at
/// every value: which of the three ways applies is decided here, and [`apply`](Self::apply)
/// gives the same value to the bit. For a decoder's hot path (a CAN signal per frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Linear(LinearWay);

#[derive(Debug, Clone, Copy, PartialEq)]
enum LinearWay {
    /// Integral factor and offset: multiplied and added as integers.
    Integers(i128, i128),
    /// An integral factor, a fractional offset: the exact product, rounded, plus it.
    IntegerFactor(i128, f64),
    /// f64 arithmetic.
    Floats(f64, f64),
}

impl Linear {
    /// `raw × factor + offset` as [`linear`] computes it.
    pub fn new(factor: f64, offset: f64) -> Linear {
        /// `x` as the integer it is, when a product with a 64-bit raw value cannot
        /// overflow i128 (|x| < 2^63).
        fn integral(x: f64) -> Option<i128> {
            (x.fract() == 0.0 && x.abs() < 9.2e18).then_some(x as i128)
        }
        Linear(match (integral(factor), integral(offset)) {
            (Some(f), Some(o)) => LinearWay::Integers(f, o),
            (Some(f), None) => LinearWay::IntegerFactor(f, offset),
            (None, _) => LinearWay::Floats(factor, offset),
        })
    }

    /// The physical value of `raw`.
    #[inline]
    pub fn apply(&self, raw: i128) -> f64 {
        match self.0 {
            LinearWay::Integers(f, o) => to_f64(raw * f + o),
            LinearWay::IntegerFactor(f, offset) => to_f64(raw * f) + offset,
            LinearWay::Floats(factor, offset) => to_f64(raw) * factor + offset,
        }
    }
}

/// `x as f64`, rounded to nearest (ties to even) as that cast is: one conversion
/// instruction when `x` fits in i64 (the same rounding), the 128-bit routine beyond.
#[inline]
fn to_f64(x: i128) -> f64 {
    match i64::try_from(x) {
        Ok(v) => v as f64,
        Err(_) => x as f64,
    }
}

/// How a [`Scale`] computes a physical value, so that it is the value the device's own
/// documentation (or library) gives, to the last bit.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
enum Formula {
    /// Interpolated from the nearer end of the range, so both ends are exact.
    Ends,
    /// `raw * factor + offset` (factor, offset): the DBC and Modbus view.
    Factor(f64, f64),
    /// `lowest + (raw - raw.min) / steps * (highest - lowest)`, in that order: comedilib's
    /// `comedi_to_phys`.
    Fraction,
}

/// A [`Scale`] as read from a wire, before it is built again.
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct ScaleParts {
    raw: RawRange,
    at_min: f64,
    at_max: f64,
    formula: Formula,
    unit: Unit,
    ties_to_even: bool,
}

impl TryFrom<ScaleParts> for Scale {
    type Error = ScaleError;

    fn try_from(p: ScaleParts) -> Result<Scale, ScaleError> {
        let s = match p.formula {
            Formula::Ends => Scale::linear(p.raw, p.at_min, p.at_max, p.unit)?,
            Formula::Fraction => Scale::fraction(p.raw, p.at_min, p.at_max, p.unit)?,
            Formula::Factor(f, o) => Scale::from_factor(p.raw, f, o, p.unit)?,
        };
        Ok(if p.ties_to_even { s.ties_to_even() } else { s })
    }
}

impl Scale {
    /// Maps `raw.min` to `lowest` and `raw.max` to `highest`.
    pub fn linear(
        raw: RawRange,
        lowest: f64,
        highest: f64,
        unit: Unit,
    ) -> Result<Scale, ScaleError> {
        RawRange::new(raw.min, raw.max)?;
        if !(lowest.is_finite() && highest.is_finite() && lowest < highest) {
            return Err(ScaleError::InvalidPhysicalRange { lowest, highest });
        }
        if !(highest - lowest).is_finite() {
            return Err(ScaleError::SpanNotFinite { lowest, highest });
        }
        Ok(Scale {
            raw,
            at_min: lowest,
            at_max: highest,
            formula: Formula::Ends,
            unit,
            ties_to_even: false,
        })
    }

    /// Maps `raw.min` to `lowest` and `raw.max` to `highest` the way comedilib's
    /// `comedi_to_phys` does: the raw value's fraction of the raw range times the span,
    /// plus `lowest` — so a value equals comedilib's to the last bit (`highest` itself may
    /// then come out a rounding step off, where `lowest + span` is not exact).
    pub fn fraction(
        raw: RawRange,
        lowest: f64,
        highest: f64,
        unit: Unit,
    ) -> Result<Scale, ScaleError> {
        let mut s = Scale::linear(raw, lowest, highest, unit)?;
        s.formula = Formula::Fraction;
        Ok(s)
    }

    /// `physical = raw * factor + offset` over `raw`. A negative factor is allowed.
    pub fn from_factor(
        raw: RawRange,
        factor: f64,
        offset: f64,
        unit: Unit,
    ) -> Result<Scale, ScaleError> {
        RawRange::new(raw.min, raw.max)?;
        if !(factor.is_finite() && offset.is_finite() && factor != 0.0) {
            return Err(ScaleError::InvalidFactor { factor, offset });
        }
        let at_min = linear(i128::from(raw.min), factor, offset);
        let at_max = linear(i128::from(raw.max), factor, offset);
        if !(at_min.is_finite() && at_max.is_finite()) || at_min == at_max {
            return Err(ScaleError::InvalidFactor { factor, offset });
        }
        if !(at_max - at_min).is_finite() {
            return Err(ScaleError::SpanNotFinite {
                lowest: at_min.min(at_max),
                highest: at_min.max(at_max),
            });
        }
        Ok(Scale {
            raw,
            at_min,
            at_max,
            formula: Formula::Factor(factor, offset),
            unit,
            ties_to_even: false,
        })
    }

    /// The same scale rounding a value half a step between two raw values to the even
    /// one, as IEEE 754 and Python do (cantools encodes so), instead of away from zero.
    pub fn ties_to_even(mut self) -> Scale {
        self.ties_to_even = true;
        self
    }

    /// The raw range.
    pub fn raw_range(&self) -> RawRange {
        self.raw
    }

    /// The physical range and unit.
    pub fn range(&self) -> AnalogRange {
        AnalogRange {
            lowest: self.at_min.min(self.at_max),
            highest: self.at_min.max(self.at_max),
            unit: self.unit,
        }
    }

    /// The unit of physical values.
    pub fn unit(&self) -> Unit {
        self.unit
    }

    /// Physical size of one raw step (always positive).
    pub fn resolution(&self) -> f64 {
        (self.at_max - self.at_min).abs() / self.raw.steps()
    }

    /// The physical value of `raw`. Raw values outside the raw range extrapolate linearly.
    pub fn to_physical(&self, raw: i64) -> f64 {
        let t = (i128::from(raw) - i128::from(self.raw.min)) as f64 / self.raw.steps();
        match self.formula {
            // The documented formula, which also gave the range's ends (so they are exact).
            Formula::Factor(factor, offset) => return linear(i128::from(raw), factor, offset),
            Formula::Fraction => return t * (self.at_max - self.at_min) + self.at_min,
            Formula::Ends => {}
        }
        // Interpolate from the nearer end so both endpoints come out exactly.
        if t < 0.5 {
            self.at_min + t * (self.at_max - self.at_min)
        } else {
            self.at_max - (1.0 - t) * (self.at_max - self.at_min)
        }
    }

    /// The raw value nearest to `value`, or `None` when `value` is outside the physical range
    /// or not a number.
    pub fn to_raw(&self, value: f64) -> Option<i64> {
        let r = self.range();
        if !(value >= r.lowest && value <= r.highest) {
            return None;
        }
        Some(self.nearest_raw(value))
    }

    /// [`to_raw`](Self::to_raw) for a write to `channel`: out of range is
    /// [`DeviceError::ValueOutOfRange`](crate::DeviceError::ValueOutOfRange) naming the channel
    /// and the range.
    pub fn to_raw_checked(&self, channel: u32, value: f64) -> Result<i64, crate::DeviceError> {
        self.to_raw(value).ok_or_else(|| {
            let r = self.range();
            crate::DeviceError::ValueOutOfRange {
                channel,
                value,
                lowest: r.lowest,
                highest: r.highest,
            }
        })
    }

    /// Checks a raw value written to `channel`: outside the raw range is
    /// [`DeviceError::RawOutOfRange`](crate::DeviceError::RawOutOfRange).
    pub fn check_raw(&self, channel: u32, raw: i64) -> Result<(), crate::DeviceError> {
        if self.raw.contains(raw) {
            Ok(())
        } else {
            Err(crate::DeviceError::RawOutOfRange {
                channel,
                raw,
                min: self.raw.min,
                max: self.raw.max,
            })
        }
    }

    /// The raw value nearest to `value`, clamped into the raw range (NaN gives the raw minimum).
    ///
    /// For simulations and loopbacks, where an out-of-range value saturates like a real
    /// converter does.
    pub fn to_raw_saturating(&self, value: f64) -> i64 {
        if value.is_nan() {
            return self.raw.min;
        }
        self.nearest_raw(value)
    }

    /// `q` to the nearest integer, a tie as this scale rounds ties.
    fn round(&self, q: f64) -> f64 {
        if self.ties_to_even {
            q.round_ties_even()
        } else {
            q.round()
        }
    }

    fn nearest_raw(&self, value: f64) -> i64 {
        if let Formula::Factor(factor, offset) = self.formula {
            // Rounded and clamped in f64 first, so infinities saturate; `as` then saturates too.
            let steps = self.round((value - offset) / factor);
            return self
                .raw
                .clamp(steps.clamp(self.raw.min as f64, self.raw.max as f64) as i64);
        }
        let t = (value - self.at_min) / (self.at_max - self.at_min);
        // Clamped in step space, so infinities saturate and the sum stays within the range.
        let steps = self
            .round(t * self.raw.steps())
            .clamp(0.0, self.raw.steps());
        let raw = i128::from(self.raw.min) + steps as i128;
        self.raw
            .clamp(raw.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn v() -> Unit {
        Unit::new("V").expect("short unit")
    }

    #[test]
    fn endpoints_are_exact() {
        for (lo, hi, bits) in [
            (-10.0, 10.0, 16),
            (0.0, 5.0, 12),
            (-0.3, 0.7, 24),
            (1e-3, 2e-3, 10),
        ] {
            let s = Scale::linear(RawRange::unsigned_bits(bits).unwrap(), lo, hi, v()).unwrap();
            assert_eq!(s.to_physical(0), lo);
            assert_eq!(s.to_physical(s.raw_range().max), hi);
            assert_eq!(s.to_raw(lo), Some(0));
            assert_eq!(s.to_raw(hi), Some(s.raw_range().max));
        }
    }

    #[test]
    fn fraction_scales_compute_as_comedi_to_phys() {
        let s = Scale::fraction(RawRange::new(0, 65535).unwrap(), -10.0, 10.0, v()).unwrap();
        for raw in [0i64, 1, 32767, 32768, 40000, 65534, 65535] {
            let x = raw as f64 / 65535.0;
            assert_eq!(s.to_physical(raw), x * 20.0 + -10.0, "raw {raw}");
        }
        assert_eq!(s.to_raw(10.0), Some(65535));
        assert_eq!(s.to_raw(-10.0), Some(0));
    }

    #[test]
    fn round_trip_within_half_a_step() {
        let s = Scale::linear(RawRange::signed_bits(16).unwrap(), -5.0, 5.0, v()).unwrap();
        for i in 0..=1000 {
            let x = -5.0 + 10.0 * f64::from(i) / 1000.0;
            let back = s.to_physical(s.to_raw(x).unwrap());
            assert!(
                (back - x).abs() <= s.resolution() / 2.0 + 1e-12,
                "{x} -> {back}"
            );
        }
    }

    #[test]
    fn factor_scales_compute_as_documented() {
        // An i16 temperature in tenths: the in-between values are raw * 0.1, not an
        // interpolation between the ends (which drifts in the last digits).
        let s = Scale::from_factor(RawRange::signed_bits(16).unwrap(), 0.1, 0.0, v()).unwrap();
        assert_eq!(s.to_physical(-123), -123.0 * 0.1);
        assert_eq!(s.to_physical(-123).to_string(), "-12.3");
        assert_eq!(s.to_raw(-12.3), Some(-123));
        assert_eq!(s.to_physical(i64::from(i16::MAX)), s.range().highest);
        assert_eq!(s.to_raw_saturating(f64::INFINITY), i64::from(i16::MAX));
        assert_eq!(s.to_raw_saturating(f64::NEG_INFINITY), i64::from(i16::MIN));
    }

    #[test]
    fn negative_factor_swaps_the_range() {
        let s = Scale::from_factor(RawRange::new(0, 100).unwrap(), -0.5, 10.0, v()).unwrap();
        let r = s.range();
        assert_eq!((r.lowest, r.highest), (-40.0, 10.0));
        assert_eq!(s.to_raw(-40.0), Some(100));
        assert_eq!(s.to_raw(9.75), Some(1)); // half a step: rounds away from zero
        assert_eq!(s.resolution(), 0.5);
    }

    #[test]
    fn out_of_range_and_nan_are_refused() {
        let s = Scale::linear(RawRange::unsigned_bits(8).unwrap(), 0.0, 1.0, v()).unwrap();
        assert_eq!(s.to_raw(f64::NAN), None);
        assert_eq!(s.to_raw(1.0 + 1e-9), None);
        assert_eq!(s.to_raw(f64::NEG_INFINITY), None);
        assert_eq!(s.to_raw_saturating(7.0), 255);
        assert_eq!(s.to_raw_saturating(f64::NAN), 0);
        assert_eq!(s.to_raw_saturating(f64::INFINITY), 255);
        assert_eq!(s.to_raw_saturating(f64::NEG_INFINITY), 0);
    }

    #[test]
    fn bad_parameters_are_errors() {
        assert!(RawRange::new(5, 5).is_err());
        assert!(RawRange::unsigned_bits(0).is_err());
        assert!(RawRange::signed_bits(64).is_err());
        assert_eq!(RawRange::unsigned_bits(63).unwrap().max, i64::MAX);
        assert_eq!(RawRange::unsigned_bits(1).unwrap().max, 1);
        assert_eq!(RawRange::unsigned_bits(16).unwrap().max, 65535);
        assert_eq!(RawRange::signed_bits(63).unwrap().min, -(1 << 62));
        let r = RawRange::new(0, 1).unwrap();
        assert!(Scale::linear(r, 1.0, 1.0, v()).is_err());
        assert!(Scale::linear(r, f64::NAN, 1.0, v()).is_err());
        assert!(Scale::from_factor(r, 0.0, 1.0, v()).is_err());
        assert!(Scale::from_factor(r, 1.0, f64::INFINITY, v()).is_err());
        // Both ends finite, the span between them not: every value would read NaN.
        let e = Scale::linear(r, -1.7e308, 1.7e308, v()).unwrap_err();
        assert_eq!(
            e,
            ScaleError::SpanNotFinite {
                lowest: -1.7e308,
                highest: 1.7e308
            }
        );
        assert_eq!(
            e.to_string(),
            "physical range [-1.7e308, 1.7e308] is too wide: its span (highest - lowest) is \
             infinite, beyond the largest number (about 1.8e308); narrow it"
        );
        assert!(Scale::fraction(r, -1e308, 1e308, v()).is_err());
        assert!(matches!(
            Scale::from_factor(RawRange::new(-1, 1).unwrap(), 1e308, 0.0, v()),
            Err(ScaleError::SpanNotFinite { .. })
        ));
        // The widest span that is finite still converts without NaN.
        let wide = Scale::linear(RawRange::unsigned_bits(16).unwrap(), -8e307, 8e307, v()).unwrap();
        assert!((0..=65535).all(|raw| wide.to_physical(raw).is_finite()));
        assert_eq!(
            Scale::linear(r, 5.0, 1.0, v()).unwrap_err().to_string(),
            "physical range [5, 1] is invalid: needs finite lowest < highest"
        );
        assert!(matches!(
            Unit::new("a-unit-name-that-is-much-too-long"),
            Err(ScaleError::UnitTooLong { .. })
        ));
    }

    #[test]
    fn ranges_read_as_text() {
        let s = Scale::linear(RawRange::unsigned_bits(16).unwrap(), 0.0, 10.0, v()).unwrap();
        assert_eq!(s.range().to_string(), "[0, 10] V");
        assert_eq!(s.raw_range().to_string(), "[0, 65535]");
        let none = AnalogRange {
            lowest: -1e308,
            highest: 0.5,
            unit: Unit::none(),
        };
        assert_eq!(none.to_string(), "[-1e308, 0.5]");
        let e = Unit::new(&"u".repeat(100)).unwrap_err().to_string();
        assert!(
            e.starts_with("unit \"uuu")
                && e.ends_with("…\" (100 characters) is longer than 23 bytes"),
            "{e}"
        );
    }

    #[test]
    fn linear_made_once_gives_the_formula_bit_for_bit() {
        // The formula as `linear` computed it before `Linear` decided its way once: every
        // conversion through i128.
        fn reference(raw: i128, factor: f64, offset: f64) -> f64 {
            let integral = |x: f64| (x.fract() == 0.0 && x.abs() < 9.2e18).then_some(x as i128);
            match (integral(factor), integral(offset)) {
                (Some(f), Some(o)) => (raw * f + o) as f64,
                (Some(f), None) => (raw * f) as f64 + offset,
                (None, _) => raw as f64 * factor + offset,
            }
        }
        let raws = [
            0i128,
            1,
            -1,
            (1 << 53) + 1,
            -(1 << 53) - 1,
            i128::from(i64::MAX),
            i128::from(i64::MIN),
            i128::from(u64::MAX),
            i128::from(u64::MAX) - 1,
        ];
        let ways = [
            (1.0, 0.0),
            (3.0, -7.0),
            (1000.0, 0.5),
            (-2.0, 1e-3),
            (0.1, -100.0),
            (1e-5, 0.0),
            (4.0, 2e20),
            (1e19, 0.0),
        ];
        let mut seed = 0x9E37_79B9_7F4A_7C15_u64;
        let mut next = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        let random = (0..2000).map(|k| match k % 3 {
            0 => i128::from(next() as i64),
            1 => i128::from(next()),
            _ => i128::from(next() as i64 >> (next() % 64)),
        });
        for raw in raws.into_iter().chain(random) {
            for (factor, offset) in ways {
                assert_eq!(
                    Linear::new(factor, offset).apply(raw).to_bits(),
                    reference(raw, factor, offset).to_bits(),
                    "{raw} × {factor} + {offset}"
                );
            }
        }
    }

    #[test]
    fn wide_raw_ranges_do_not_overflow() {
        let s = Scale::linear(RawRange::new(i64::MIN, i64::MAX).unwrap(), -1.0, 1.0, v()).unwrap();
        assert_eq!(s.to_physical(i64::MIN), -1.0);
        assert_eq!(s.to_physical(i64::MAX), 1.0);
        assert_eq!(s.to_raw(1.0), Some(i64::MAX));
    }
}
