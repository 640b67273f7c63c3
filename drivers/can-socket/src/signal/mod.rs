//! Signals inside CAN frames, as a DBC file describes them.
//!
//! A signal is `length` bits of a frame's payload starting at `start`, in one of the two
//! DBC byte orders, signed or not, with `physical = raw * factor + offset` (the shared
//! [`Scale`]). Bit numbering follows DBC files exactly:
//!
//! - **Intel** (`@1`, little endian): `start` is the least significant bit, counted from
//!   bit 0 of byte 0 upwards through the bytes.
//! - **Motorola** (`@0`, big endian): `start` is the *most* significant bit, numbered
//!   `byte * 8 + bit` with bit 7 the most significant of its byte; the following bits run
//!   down to bit 0 of that byte and on at bit 7 of the next byte.
//!
//! ```
//! use can_socket::signal::{ByteOrder, Signal};
//!
//! // Engine temperature: one byte at bit 16, degC = raw - 40.
//! let t = Signal::new(16, 8, ByteOrder::Intel, false, 1.0, -40.0, "degC")?;
//! assert_eq!(t.decode(&[0, 0, 130, 0, 0, 0, 0, 0])?, 90.0);
//!
//! // A Motorola 16-bit value whose most significant bit is bit 7 of byte 0.
//! let s = Signal::new(7, 16, ByteOrder::Motorola, false, 1.0, 0.0, "")?;
//! assert_eq!(s.extract(&[0x12, 0x34])?, 0x1234);
//! # Ok::<(), can_socket::signal::SignalError>(())
//! ```

use device_interface::{DeviceError, Linear, RawRange, Scale, ScaleError, Unit};
use serde::Deserialize;

/// How a signal's bits hold its value (DBC `SIG_VALTYPE_`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum ValueKind {
    /// An integer, signed or not (the default).
    #[default]
    Integer,
    /// An IEEE 754 single (`SIG_VALTYPE_ … : 1`, 32 bits).
    Float32,
    /// An IEEE 754 double (`SIG_VALTYPE_ … : 2`, 64 bits).
    Float64,
}

/// The DBC byte orders.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ByteOrder {
    /// Little endian (`@1` in a DBC file).
    Intel,
    /// Big endian (`@0` in a DBC file).
    Motorola,
}

/// The longest payload a signal can sit in, bytes: a J1939 message carried by the kernel's
/// transport (a CAN FD frame has 64).
pub const MAX_PAYLOAD: usize = 65_536;

/// Why a signal is invalid or does not fit a frame.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum SignalError {
    /// A length outside 1..=64.
    #[error("a signal is 1 to 64 bits long, not {0}")]
    Length(u32),
    /// A bit past the largest payload mapped ([`MAX_PAYLOAD`] bytes: a J1939 message).
    #[error("start bit {0} is past the end of the largest payload ({MAX_PAYLOAD} bytes)")]
    Start(u32),
    /// The payload is too short for the signal.
    #[error("the signal needs {need} bytes of payload, the frame has {got}")]
    Short {
        /// Bytes the signal reaches into.
        need: usize,
        /// Bytes the frame has.
        got: usize,
    },
    /// A raw value outside the signal's range (when encoding).
    #[error("raw value {raw} does not fit {length} {} bits", if *.signed { "signed" } else { "unsigned" })]
    RawOutOfRange {
        /// The value.
        raw: i64,
        /// Signal length.
        length: u32,
        /// Signedness.
        signed: bool,
    },
    /// A DBC `[min|max]` no raw value of the signal falls into.
    #[error("no raw value of the signal lies in its range [{min}|{max}]")]
    Limits {
        /// Physical minimum.
        min: f64,
        /// Physical maximum.
        max: f64,
    },
    /// Factor, offset or unit that make no scale.
    #[error(transparent)]
    Scale(#[from] ScaleError),
    /// A float value type on a signal of the wrong length.
    #[error("a {kind} signal is {need} bits long, not {length}")]
    FloatLength {
        /// "float" or "double".
        kind: &'static str,
        /// The length it must have.
        need: u32,
        /// Its length.
        length: u32,
    },
}

/// One signal of a frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Signal {
    start: u32,
    length: u32,
    order: ByteOrder,
    signed: bool,
    kind: ValueKind,
    factor: f64,
    offset: f64,
    /// `factor` and `offset` as an integer signal's raw value becomes physical.
    linear: Linear,
    /// A float signal's declared physical [min|max], if given (its raw grid cannot carry
    /// them).
    float_limits: Option<(f64, f64)>,
    scale: Scale,
    /// Payload bit (as `byte * 8 + bit`, bit 0 the least significant of its byte) of each
    /// signal bit, most significant first.
    bits: Vec<u32>,
    /// The whole bytes the bits lie in, as one integer: see [`Window`].
    window: Window,
}

/// Where a signal's bits are, as whole bytes: `bytes` bytes from `first`, read as one
/// integer (little endian for Intel, big endian for Motorola), hold the value at `shift`
/// bits up. A signal's bits are contiguous in that integer in both byte orders, so a value
/// is read with at most nine byte loads and one shift instead of bit by bit.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Window {
    first: usize,
    bytes: usize,
    shift: u32,
}

impl Window {
    fn new(start: u32, length: u32, order: ByteOrder) -> Window {
        let (first, last, shift) = match order {
            ByteOrder::Intel => (start / 8, (start + length - 1) / 8, start % 8),
            ByteOrder::Motorola => {
                // Bits numbered from the first byte's most significant, downwards through
                // each byte and on into the next: the MSB at `msb`, the LSB `length - 1`
                // further.
                let msb = start / 8 * 8 + (7 - start % 8);
                let lsb = msb + length - 1;
                (msb / 8, lsb / 8, 7 - lsb % 8)
            }
        };
        Window {
            first: first as usize,
            bytes: (last - first + 1) as usize,
            shift,
        }
    }

    /// The window's bytes of `payload` as one integer.
    fn load(&self, order: ByteOrder, payload: &[u8]) -> u128 {
        let bytes = &payload[self.first..self.first + self.bytes];
        match order {
            ByteOrder::Intel => bytes.iter().rev().fold(0, |a, &b| a << 8 | u128::from(b)),
            ByteOrder::Motorola => bytes.iter().fold(0, |a, &b| a << 8 | u128::from(b)),
        }
    }

    /// Writes `v` (the window's integer) back into `payload`.
    fn store(&self, order: ByteOrder, payload: &mut [u8], mut v: u128) {
        let bytes = &mut payload[self.first..self.first + self.bytes];
        let mut put = |b: &mut u8| {
            *b = v as u8;
            v >>= 8;
        };
        match order {
            ByteOrder::Intel => bytes.iter_mut().for_each(&mut put),
            ByteOrder::Motorola => bytes.iter_mut().rev().for_each(&mut put),
        }
    }
}

impl Signal {
    /// A signal of `length` bits at DBC start bit `start`.
    pub fn new(
        start: u32,
        length: u32,
        order: ByteOrder,
        signed: bool,
        factor: f64,
        offset: f64,
        unit: &str,
    ) -> Result<Signal, SignalError> {
        if !(1..=64).contains(&length) {
            return Err(SignalError::Length(length));
        }
        if start as usize >= MAX_PAYLOAD * 8 {
            return Err(SignalError::Start(start));
        }
        let bits: Vec<u32> = match order {
            // LSB at `start`, upwards: most significant first is the reverse.
            ByteOrder::Intel => (start..start + length).rev().collect(),
            ByteOrder::Motorola => {
                let mut v = Vec::with_capacity(length as usize);
                let mut pos = start;
                for _ in 0..length {
                    v.push(pos);
                    // Down through the byte, then on at the top of the next byte.
                    pos = if pos.is_multiple_of(8) {
                        pos + 15
                    } else {
                        pos - 1
                    };
                }
                v
            }
        };
        if let Some(&beyond) = bits.iter().find(|&&b| b as usize >= MAX_PAYLOAD * 8) {
            return Err(SignalError::Start(beyond));
        }
        let raw = if signed {
            if length == 1 {
                RawRange { min: -1, max: 0 }
            } else if length == 64 {
                RawRange {
                    min: i64::MIN,
                    max: i64::MAX,
                }
            } else {
                RawRange::signed_bits(length)?
            }
        } else if length == 64 {
            RawRange {
                min: 0,
                max: i64::MAX,
            }
        } else {
            RawRange::unsigned_bits(length)?
        };
        // Ties to even, as cantools (Python) encodes.
        let scale = Scale::from_factor(raw, factor, offset, Unit::new(unit)?)?.ties_to_even();
        Ok(Signal {
            start,
            length,
            order,
            signed,
            kind: ValueKind::Integer,
            factor,
            offset,
            linear: Linear::new(factor, offset),
            float_limits: None,
            scale,
            bits,
            window: Window::new(start, length, order),
        })
    }

    /// The same signal holding an IEEE float (32 bits) or double (64 bits). Its value is
    /// the float times the factor plus the offset; its scale's raw values are coarse steps
    /// over the type's whole range (±2^23 steps for a float, ±2^52 for a double, as the
    /// Modbus driver's floats): the value itself is exact, read with [`physical`](Self::physical).
    pub fn with_kind(mut self, kind: ValueKind) -> Result<Signal, SignalError> {
        // Steps of a power of two, so every step is a value of the type: for a float
        // ±(2^24 − 1) steps of 2^104, exactly its finite values (f32::MAX is (2^24 − 1) ×
        // 2^104); for a double ±(2^53 − 1) steps of 2^970, up to 2^1023 — half its largest
        // value, so that the scale's span stays finite — or less by the factor's power of
        // two.
        let (need, name, steps, step) = match kind {
            ValueKind::Integer => return Ok(self),
            ValueKind::Float32 => (32, "float", (1i64 << 24) - 1, 2f64.powi(104)),
            ValueKind::Float64 => {
                let k = self.factor.abs().log2().ceil().max(0.0) as i32;
                (64, "double", (1i64 << 53) - 1, 2f64.powi(970 - k))
            }
        };
        if self.length != need {
            return Err(SignalError::FloatLength {
                kind: name,
                need,
                length: self.length,
            });
        }
        self.kind = kind;
        self.scale = Scale::from_factor(
            RawRange {
                min: -steps,
                max: steps,
            },
            self.factor * step,
            self.offset,
            self.scale.unit(),
        )?
        .ties_to_even();
        Ok(self)
    }

    /// How the bits hold the value.
    pub fn kind(&self) -> ValueKind {
        self.kind
    }

    /// The DBC factor and offset.
    pub fn factor_offset(&self) -> (f64, f64) {
        (self.factor, self.offset)
    }

    /// The physical value of raw bits `raw` (as [`extract`](Self::extract) returns them):
    /// `raw * factor + offset` with the raw value as the DBC says — signed, unsigned (all 64
    /// bits unsigned up to 2^64 − 1), or the IEEE float the bits hold — computed as cantools
    /// computes it: an integral factor or offset is an integer there, multiplied and added
    /// exactly (then rounded once to f64), any other in f64 ([`device_interface::linear`],
    /// as the channel's scale computes it); a float with factor 1 and offset 0 is the float
    /// itself (−0.0 included). (cantools keeps a factor the file writes as `1.0` a float;
    /// the two differ only for raw values beyond 2^53.)
    pub fn physical(&self, raw: i64) -> f64 {
        let value = match self.kind {
            ValueKind::Float32 => f64::from(f32::from_bits(raw as u32)),
            ValueKind::Float64 => f64::from_bits(raw as u64),
            ValueKind::Integer => {
                let raw = if !self.signed && self.length == 64 {
                    i128::from(raw as u64)
                } else {
                    i128::from(raw)
                };
                return self.linear.apply(raw);
            }
        };
        if self.factor == 1.0 && self.offset == 0.0 {
            value
        } else {
            value * self.factor + self.offset
        }
    }

    /// The raw bits that carry physical `value`, if it is one the signal can carry: a
    /// number within its DBC range, and then an integer signal's raw value in its bits
    /// (an unsigned 64-bit one up to 2^64 − 1), a float's value within its scale's range.
    pub fn raw_of(&self, value: f64) -> Option<i64> {
        if let Some((min, max)) = self.float_limits
            && !(value >= min && value <= max)
        {
            return None;
        }
        let x = (value - self.offset) / self.factor;
        let r = self.scale.range();
        if self.kind != ValueKind::Integer && !(value >= r.lowest && value <= r.highest) {
            return None;
        }
        match self.kind {
            ValueKind::Float32 => {
                let f = x as f32;
                f.is_finite().then_some(i64::from(f.to_bits()))
            }
            ValueKind::Float64 => x.is_finite().then_some(x.to_bits() as i64),
            ValueKind::Integer => {
                // (value − offset) / factor to the nearest raw value, a tie to the even one,
                // as cantools encodes (the signal's scale rounds so too). An unsigned 64-bit
                // value from 2^63 on is beyond the scale's raw range (i64): the bits of the
                // unsigned value (2^63 and 2^64 are exact in f64).
                let raw = x.round_ties_even();
                if !self.signed && self.length == 64 && raw >= 2f64.powi(63) {
                    return (raw < 2f64.powi(64)).then_some(raw as u64 as i64);
                }
                self.scale.to_raw(value)
            }
        }
    }

    /// True when raw bits `raw` (a received value) lie in the signal's declared range.
    pub fn in_range(&self, raw: i64) -> bool {
        match self.kind {
            ValueKind::Integer if !self.signed && self.length == 64 && raw < 0 => {
                // Above 2^63, beyond what the raw range (i64) holds: the declared limits
                // decide, in physical units; none declared, the type's range holds it.
                let v = self.physical(raw);
                self.float_limits
                    .is_none_or(|(min, max)| v >= min && v <= max)
            }
            ValueKind::Integer => {
                self.scale.raw_range().contains(raw)
                    && self.float_limits.is_none_or(|(min, max)| {
                        let v = self.physical(raw);
                        v >= min && v <= max
                    })
            }
            _ => {
                let v = self.physical(raw);
                let (min, max) = self
                    .float_limits
                    .unwrap_or((f64::NEG_INFINITY, f64::INFINITY));
                v >= min && v <= max
            }
        }
    }

    /// The same signal with its raw range narrowed to the raw values whose physical value
    /// lies in `[min, max]` (a DBC range); `min == max == 0` means "not given", as in DBC
    /// files, and changes nothing.
    pub fn with_limits(mut self, min: f64, max: f64) -> Result<Signal, SignalError> {
        if min == 0.0 && max == 0.0 {
            return Ok(self);
        }
        let bad = SignalError::Limits { min, max };
        if !(min.is_finite() && max.is_finite() && min <= max) {
            return Err(bad);
        }
        if self.kind != ValueKind::Integer {
            self.float_limits = Some((min, max));
            return Ok(self);
        }
        if !self.signed && self.length == 64 {
            // Raw values above 2^63 are checked against these (see `in_range`).
            self.float_limits = Some((min, max));
        }
        // A raw value within a millionth of a step of the limit counts as on it: DBC
        // limits are decimal texts of values that are exact in raw steps.
        let near = |x: f64, up: bool| {
            let r = x.round();
            if (x - r).abs() < 1e-6 {
                r
            } else if up {
                x.ceil()
            } else {
                x.floor()
            }
        };
        let (a, b) = (
            (min - self.offset) / self.factor,
            (max - self.offset) / self.factor,
        );
        let (lo, hi) = (near(a.min(b), true), near(a.max(b), false));
        let full = self.scale.raw_range();
        let lo = if lo <= full.min as f64 {
            full.min
        } else {
            lo as i64
        };
        let hi = if hi >= full.max as f64 {
            full.max
        } else {
            hi as i64
        };
        if lo == hi {
            // One raw value (a constant or reserved signal, [5|5]): a scale needs two, so
            // the limits are checked as physical values instead.
            self.float_limits = Some((min, max));
            return Ok(self);
        }
        let range = RawRange::new(lo, hi).map_err(|_| bad)?;
        self.scale =
            Scale::from_factor(range, self.factor, self.offset, self.scale.unit())?.ties_to_even();
        Ok(self)
    }

    /// True when the two signals share a payload bit.
    pub fn overlaps(&self, other: &Signal) -> bool {
        self.bits.iter().any(|b| other.bits.contains(b))
    }

    /// The payload bytes the signal reaches into.
    pub fn bytes_needed(&self) -> usize {
        self.window.first + self.window.bytes
    }

    /// The raw-to-physical scale (raw range from length and signedness).
    pub fn scale(&self) -> &Scale {
        &self.scale
    }

    /// DBC start bit, length, byte order, signedness.
    pub fn layout(&self) -> (u32, u32, ByteOrder, bool) {
        (self.start, self.length, self.order, self.signed)
    }

    fn check(&self, len: usize) -> Result<(), SignalError> {
        let need = self.bytes_needed();
        if len < need {
            return Err(SignalError::Short { need, got: len });
        }
        Ok(())
    }

    /// The physical value of `bits` (as [`extract`](Self::extract) gives them) read as
    /// device channel `channel`: an error for NaN and the infinities a float can carry.
    pub fn channel_value(&self, channel: u32, bits: i64) -> Result<f64, DeviceError> {
        let v = self.physical(bits);
        if v.is_finite() {
            return Ok(v);
        }
        Err(DeviceError::not_a_number(channel, v))
    }

    /// The raw value of `bits` as device channel `channel`'s scale counts it: the integer
    /// itself; a float's nearest step; an unsigned 64-bit value above 2^63 − 1 is out of
    /// the raw range (its physical value reads).
    pub fn channel_raw(&self, channel: u32, bits: i64) -> Result<i64, DeviceError> {
        match self.kind {
            ValueKind::Integer if self.length == 64 && !self.signed && bits < 0 => {
                let r = self.scale.range();
                Err(DeviceError::ValueOutOfRange {
                    channel,
                    value: self.physical(bits),
                    lowest: r.lowest,
                    highest: r.highest,
                })
            }
            ValueKind::Integer => Ok(bits),
            _ => Ok(self
                .scale
                .to_raw_saturating(self.channel_value(channel, bits)?)),
        }
    }

    /// The bits that carry physical `value` written to device channel `channel`: an error
    /// when the signal cannot hold it.
    pub fn channel_bits_of_value(&self, channel: u32, value: f64) -> Result<i64, DeviceError> {
        self.raw_of(value).ok_or_else(|| {
            let r = self.scale.range();
            DeviceError::ValueOutOfRange {
                channel,
                value,
                lowest: r.lowest,
                highest: r.highest,
            }
        })
    }

    /// The bits that carry raw value `raw` of device channel `channel`'s scale: the
    /// integer itself; for a float, the value that step of the scale stands for.
    pub fn channel_bits_of_raw(&self, channel: u32, raw: i64) -> Result<i64, DeviceError> {
        self.scale.check_raw(channel, raw)?;
        match self.kind {
            ValueKind::Integer => Ok(raw),
            _ => self
                .raw_of(self.scale.to_physical(raw))
                .ok_or(DeviceError::RawOutOfRange {
                    channel,
                    raw,
                    min: self.scale.raw_range().min,
                    max: self.scale.raw_range().max,
                }),
        }
    }

    /// The raw value in `payload` (sign-extended when signed).
    pub fn extract(&self, payload: &[u8]) -> Result<i64, SignalError> {
        self.check(payload.len())?;
        let v = (self.window.load(self.order, payload) >> self.window.shift) as u64
            & (u64::MAX >> (64 - self.length));
        Ok(
            if self.signed && self.length < 64 && v >> (self.length - 1) & 1 == 1 {
                (v | (u64::MAX << self.length)) as i64
            } else {
                v as i64
            },
        )
    }

    /// The physical value in `payload`.
    pub fn decode(&self, payload: &[u8]) -> Result<f64, SignalError> {
        Ok(self.physical(self.extract(payload)?))
    }

    /// Writes `raw` into `payload`; the other bits keep their values.
    pub fn insert(&self, payload: &mut [u8], raw: i64) -> Result<(), SignalError> {
        self.check(payload.len())?;
        // A float's bits, and an unsigned 64-bit value's above 2^63, are any 64-bit pattern.
        let any_bits = self.kind != ValueKind::Integer || (!self.signed && self.length == 64);
        if !any_bits && !self.scale.raw_range().contains(raw) {
            return Err(SignalError::RawOutOfRange {
                raw,
                length: self.length,
                signed: self.signed,
            });
        }
        let mask = u128::from(u64::MAX >> (64 - self.length)) << self.window.shift;
        let v = u128::from(raw as u64) << self.window.shift & mask;
        let w = self.window.load(self.order, payload);
        self.window.store(self.order, payload, w & !mask | v);
        Ok(())
    }
}

#[cfg(test)]
mod tests;
