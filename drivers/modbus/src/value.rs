//! An analog point's value as the card's image holds it (one atomic word a channel).
//!
//! An integer point holds its raw value, the register's integer. A float point holds its
//! *physical* value itself (`register × scale + offset`, as f64 bits): a float register has
//! no integer, and counting steps of `resolution` would put a grid between the device and
//! the reader (an f32 of 12345.678 read as 8388.608 once the grid's range ran out). So
//! `read` and `read_back` give a float point's value exactly; `read_raw` and
//! `read_back_raw` give its nearest step of `resolution` within the point's raw range, and
//! an error naming the value beyond it. NaN and the infinities are kept as they are: that
//! channel reads [`DeviceError::NotANumber`], the card's other channels are unaffected.

use crate::codec::Number;
use crate::map::Point;
use device_interface::DeviceError;

/// The image word of a decoded register value (None: an integer point given a float, which
/// the codec never does).
pub fn word_of(point: &Point, n: Number) -> Option<i64> {
    if point.layout.ty.is_float() {
        let v = n.as_f64() * point.config.scale + point.config.offset;
        return Some(v.to_bits() as i64);
    }
    match n {
        Number::Int(v) => Some(v),
        Number::UInt(v) => Some(i64::try_from(v).unwrap_or(i64::MAX)),
        Number::Float(_) => None,
    }
}

/// The image word a channel starts with (before any reply): physical 0 (float) or the raw
/// value nearest to it (integer).
pub fn initial_word(point: &Point) -> i64 {
    if point.layout.ty.is_float() {
        0.0f64.to_bits() as i64
    } else {
        point.scale.to_raw_saturating(0.0)
    }
}

/// The physical value of image word `word` of `channel`.
pub fn physical(point: &Point, channel: u32, word: i64) -> Result<f64, DeviceError> {
    if !point.layout.ty.is_float() {
        return Ok(point.scale.to_physical(word));
    }
    let v = f64::from_bits(word as u64);
    if !v.is_finite() {
        return Err(DeviceError::not_a_number(channel, v));
    }
    Ok(v)
}

/// The raw value of image word `word` of `channel`: a float's nearest step, if its raw
/// range reaches it.
pub fn raw(point: &Point, channel: u32, word: i64) -> Result<i64, DeviceError> {
    if !point.layout.ty.is_float() {
        return Ok(word);
    }
    let v = physical(point, channel, word)?;
    let r = point.scale.range();
    // Within half a step of the range's ends is the end's step (an f32 rounds the end
    // value itself a little beyond it); farther is beyond the raw range.
    let half = point.scale.resolution() / 2.0;
    if v >= r.lowest - half && v <= r.highest + half {
        return Ok(point.scale.to_raw_saturating(v));
    }
    Err(DeviceError::ValueOutOfRange {
        channel,
        value: v,
        lowest: r.lowest,
        highest: r.highest,
    })
}

/// The image word for a write of physical `value` to `channel` (checked against its range).
pub fn word_for_value(point: &Point, channel: u32, value: f64) -> Result<i64, DeviceError> {
    let raw = point.scale.to_raw_checked(channel, value)?;
    Ok(if point.layout.ty.is_float() {
        value.to_bits() as i64
    } else {
        raw
    })
}

/// The image word for a write of raw `raw` to `channel` (checked against its raw range).
pub fn word_for_raw(point: &Point, channel: u32, raw: i64) -> Result<i64, DeviceError> {
    point.scale.check_raw(channel, raw)?;
    Ok(if point.layout.ty.is_float() {
        point.scale.to_physical(raw).to_bits() as i64
    } else {
        raw
    })
}

/// The register value to send for image word `word`.
pub fn number(point: &Point, word: i64) -> Number {
    if point.layout.ty.is_float() {
        let v = f64::from_bits(word as u64);
        Number::Float((v - point.config.offset) / point.config.scale)
    } else if word < 0 {
        Number::Int(word)
    } else {
        Number::UInt(word as u64)
    }
}
