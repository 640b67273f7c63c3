//! Bit spans and lock-free bit images: the shared mechanics of digital devices.
//!
//! Orocos sequences are inclusive spans `start..=stop` whose start bit becomes bit 0 of the
//! value. [`BitSpan`] validates a span once and does the shifting; [`BitImage`] is a card's
//! input or output image as atomic words, so trait methods running on real-time threads
//! read and update it without locks while the card's bus activity refreshes it.
//!
//! ```
//! use device_interface::bits::{BitImage, BitSpan};
//!
//! let image = BitImage::new(70);
//! image.write_span(BitSpan::new(62, 65, 70)?, 0b1011)?; // crosses a word boundary
//! assert!(image.get(62)? && image.get(63)? && !image.get(64)? && image.get(65)?);
//! assert_eq!(image.read_span(BitSpan::new(63, 65, 70)?), 0b101);
//! # Ok::<(), device_interface::DeviceError>(())
//! ```

use crate::DeviceError;
use std::sync::atomic::{AtomicU64, Ordering};

/// A validated inclusive span of bits `start..=stop`, at most 64 bits wide.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct BitSpan {
    start: u32,
    stop: u32,
}

impl BitSpan {
    /// The span `start..=stop` on a device with `count` bits.
    ///
    /// Errors with [`DeviceError::SpanOutOfRange`] when `start > stop`, `stop >= count`, or
    /// the span is wider than 64 bits.
    pub fn new(start: u32, stop: u32, count: u32) -> Result<BitSpan, DeviceError> {
        if start > stop || stop >= count || stop - start >= 64 {
            return Err(DeviceError::SpanOutOfRange { start, stop, count });
        }
        Ok(BitSpan { start, stop })
    }

    /// First bit.
    pub fn start(&self) -> u32 {
        self.start
    }

    /// Last bit (inclusive).
    pub fn stop(&self) -> u32 {
        self.stop
    }

    /// Number of bits, 1 to 64.
    pub fn width(&self) -> u32 {
        self.stop - self.start + 1
    }

    /// A mask of `width()` low bits.
    pub fn mask(&self) -> u64 {
        u64::MAX >> (64 - self.width())
    }

    /// The bits in `0..=63` of the span as an iterator of (device bit, value bit index).
    pub fn bits(&self) -> impl Iterator<Item = (u32, u32)> {
        let start = self.start;
        (start..=self.stop).map(move |b| (b, b - start))
    }

    /// Checks that `value` has no bits above the span's width.
    pub fn check_value(&self, value: u64) -> Result<(), DeviceError> {
        if value & !self.mask() != 0 {
            return Err(DeviceError::SequenceValueTooWide {
                start: self.start,
                stop: self.stop,
                width: self.width(),
                value,
            });
        }
        Ok(())
    }
}

/// A fixed-size image of bits in atomic 64-bit words.
///
/// Single-bit operations are atomic. A span inside one word is read and written atomically;
/// a span crossing a word boundary is two atomic operations, so a concurrent reader may see
/// half of it (document this where a device allows spans across words).
#[derive(Debug)]
pub struct BitImage {
    words: Box<[AtomicU64]>,
    len: u32,
}

impl BitImage {
    /// An image of `len` bits, all off.
    pub fn new(len: u32) -> BitImage {
        let words = (0..len.div_ceil(64)).map(|_| AtomicU64::new(0)).collect();
        BitImage { words, len }
    }

    /// Number of bits.
    pub fn len(&self) -> u32 {
        self.len
    }

    /// True when the image has no bits.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    fn check(&self, bit: u32) -> Result<(usize, u64), DeviceError> {
        if bit >= self.len {
            return Err(DeviceError::BitOutOfRange {
                bit,
                count: self.len,
            });
        }
        Ok(((bit / 64) as usize, 1u64 << (bit % 64)))
    }

    /// `Ok` when `bit` exists, else [`DeviceError::BitOutOfRange`]: for devices that must
    /// refuse a bad bit before looking at anything else.
    pub fn check_bit(&self, bit: u32) -> Result<(), DeviceError> {
        self.check(bit).map(|_| ())
    }

    /// The value of `bit`.
    pub fn get(&self, bit: u32) -> Result<bool, DeviceError> {
        let (w, m) = self.check(bit)?;
        Ok(self.words[w].load(Ordering::Acquire) & m != 0)
    }

    /// Sets `bit` to `value`; returns its previous value.
    pub fn set(&self, bit: u32, value: bool) -> Result<bool, DeviceError> {
        let (w, m) = self.check(bit)?;
        let prev = if value {
            self.words[w].fetch_or(m, Ordering::AcqRel)
        } else {
            self.words[w].fetch_and(!m, Ordering::AcqRel)
        };
        Ok(prev & m != 0)
    }

    /// The bits of `span`, `span.start()` at bit 0.
    ///
    /// The span must have been validated against this image's length (see [`BitSpan::new`]);
    /// bits past the end read as 0.
    pub fn read_span(&self, span: BitSpan) -> u64 {
        let (w, off) = ((span.start / 64) as usize, span.start % 64);
        let lo = self.word(w) >> off;
        let hi = if off != 0 && off + span.width() > 64 {
            self.word(w + 1) << (64 - off)
        } else {
            0
        };
        (lo | hi) & span.mask()
    }

    /// Writes `value` into `span`, `value` bit 0 at `span.start()`; other bits keep their
    /// values.
    pub fn write_span(&self, span: BitSpan, value: u64) -> Result<(), DeviceError> {
        span.check_value(value)?;
        if span.stop >= self.len {
            return Err(DeviceError::SpanOutOfRange {
                start: span.start,
                stop: span.stop,
                count: self.len,
            });
        }
        let (w, off) = ((span.start / 64) as usize, span.start % 64);
        let mask = span.mask();
        self.merge(w, mask << off, value << off);
        if off != 0 && off + span.width() > 64 {
            let shift = 64 - off;
            self.merge(w + 1, mask >> shift, value >> shift);
        }
        Ok(())
    }

    /// Copies the bits of `other` that are on in `select` and not on in `except` into this
    /// image; the other bits keep their values. Bits past any image's length count as off.
    ///
    /// Used by loopbacks and by bus activities that refresh part of an image (`except`:
    /// bits held by someone else). Allocation-free.
    pub fn copy_from(&self, other: &BitImage, select: &BitImage, except: Option<&BitImage>) {
        for (k, word) in self.words.iter().enumerate() {
            let held = except.map_or(0, |e| e.word(k));
            let sel = select.word(k) & !held & self.valid_mask(k);
            let src = other.word(k);
            let _ = word.fetch_update(Ordering::AcqRel, Ordering::Acquire, |cur| {
                Some((cur & !sel) | (src & sel))
            });
        }
    }

    /// Sets every bit to `value`.
    pub fn fill(&self, value: bool) {
        for (k, word) in self.words.iter().enumerate() {
            word.store(
                if value { self.valid_mask(k) } else { 0 },
                Ordering::Release,
            );
        }
    }

    fn word(&self, k: usize) -> u64 {
        self.words.get(k).map_or(0, |w| w.load(Ordering::Acquire))
    }

    fn valid_mask(&self, k: usize) -> u64 {
        let bits_before = k as u64 * 64;
        let remaining = u64::from(self.len).saturating_sub(bits_before);
        if remaining >= 64 {
            u64::MAX
        } else {
            (1u64 << remaining) - 1
        }
    }

    fn merge(&self, k: usize, mask: u64, bits: u64) {
        let _ = self.words[k].fetch_update(Ordering::AcqRel, Ordering::Acquire, |cur| {
            Some((cur & !mask) | (bits & mask))
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn span_validation() {
        assert!(BitSpan::new(0, 0, 1).is_ok());
        assert!(BitSpan::new(0, 63, 64).is_ok());
        assert!(BitSpan::new(0, 64, 100).is_err()); // 65 bits
        assert!(BitSpan::new(3, 2, 8).is_err());
        assert!(BitSpan::new(7, 8, 8).is_err());
        assert_eq!(BitSpan::new(0, 63, 64).unwrap().mask(), u64::MAX);
        assert_eq!(BitSpan::new(4, 6, 8).unwrap().mask(), 0b111);
    }

    #[test]
    fn too_wide_values_are_refused() {
        let img = BitImage::new(8);
        let span = BitSpan::new(2, 4, 8).unwrap();
        assert!(matches!(
            img.write_span(span, 0b1000),
            Err(DeviceError::SequenceValueTooWide { width: 3, .. })
        ));
        assert_eq!(img.read_span(BitSpan::new(0, 7, 8).unwrap()), 0);
    }

    #[test]
    fn spans_match_single_bits_everywhere() {
        // Every span of a 130-bit image, against a bit-by-bit reference.
        let img = BitImage::new(130);
        let pattern = |b: u32| (b * 7 + b / 5).is_multiple_of(3);
        for b in 0..130 {
            img.set(b, pattern(b)).unwrap();
        }
        for start in 0..130 {
            for stop in start..(start + 64).min(130) {
                let span = BitSpan::new(start, stop, 130).unwrap();
                let want = span
                    .bits()
                    .fold(0u64, |acc, (dev, i)| acc | (u64::from(pattern(dev)) << i));
                assert_eq!(img.read_span(span), want, "{start}..={stop}");
            }
        }
    }

    #[test]
    fn write_span_leaves_neighbours_alone() {
        let img = BitImage::new(128);
        img.fill(true);
        img.write_span(BitSpan::new(60, 70, 128).unwrap(), 0)
            .unwrap();
        for b in 0..128 {
            assert_eq!(img.get(b).unwrap(), !(60..=70).contains(&b), "bit {b}");
        }
        assert!(img.write_span(BitSpan::new(0, 3, 200).unwrap(), 0).is_ok());
        assert!(
            img.write_span(BitSpan::new(127, 130, 200).unwrap(), 0)
                .is_err()
        );
    }

    #[test]
    fn copy_from_selected_bits() {
        let (dst, src, sel) = (BitImage::new(70), BitImage::new(70), BitImage::new(70));
        src.fill(true);
        sel.set(1, true).unwrap();
        sel.set(5, true).unwrap();
        sel.set(69, true).unwrap();
        let except = BitImage::new(8);
        except.set(5, true).unwrap();
        dst.copy_from(&src, &sel, Some(&except));
        let on: Vec<u32> = (0..70).filter(|&b| dst.get(b).unwrap()).collect();
        assert_eq!(on, vec![1, 69]);
    }
}

/// A card whose digital inputs are a [`BitImage`] its bus side keeps current; with this
/// it is a [`DigitalIn`](crate::DigitalIn) (bits and spans checked, then the card's own
/// freshness check, then the image read).
pub trait DigitalInputImage: crate::Device + Send + Sync {
    /// The input bits.
    fn inputs(&self) -> &BitImage;
    /// `Ok` when the bits of `span` can be read now; else why not (stale, offline).
    fn check_inputs(&self, span: BitSpan) -> Result<(), DeviceError>;
}

impl<T: DigitalInputImage> crate::DigitalIn for T {
    fn input_count(&self) -> u32 {
        self.inputs().len()
    }

    fn read_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        let v = self.inputs().get(bit)?;
        self.check_inputs(BitSpan::new(bit, bit, self.inputs().len())?)?;
        Ok(v)
    }

    fn read_sequence(&self, start: u32, stop: u32) -> Result<u64, DeviceError> {
        let span = BitSpan::new(start, stop, self.inputs().len())?;
        self.check_inputs(span)?;
        Ok(self.inputs().read_span(span))
    }
}

/// What a [`DigitalOutputImage`] card was just asked to write (after the image took it).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Written {
    /// One bit.
    Bit {
        /// The bit.
        bit: u32,
        /// Its new value.
        value: bool,
    },
    /// A span, bit 0 of `value` at its start.
    Span {
        /// The bits.
        span: BitSpan,
        /// Their new values.
        value: u64,
    },
}

/// A card whose digital outputs are a [`BitImage`] its bus side sends; with this it is a
/// [`DigitalOut`](crate::DigitalOut): bits, spans and values checked, then the card's
/// writability, then the image written, then the card told (to mark, wake, record).
pub trait DigitalOutputImage: crate::Device + Send + Sync {
    /// The output bits.
    fn outputs(&self) -> &BitImage;
    /// `Ok` when the card takes writes now (not offline).
    fn check_outputs_writable(&self) -> Result<(), DeviceError>;
    /// `Ok` when the card takes a write of `span` now: for a card whose bits go to
    /// several devices that come and go on their own (CANopen nodes). Default: the card's
    /// [`check_outputs_writable`](Self::check_outputs_writable).
    fn check_span_writable(&self, span: BitSpan) -> Result<(), DeviceError> {
        let _ = span;
        self.check_outputs_writable()
    }
    /// Called after each accepted write.
    fn outputs_written(&self, written: Written);
    /// Where the writes to output `bit` stand, for a card whose bus carries them later
    /// (see [`DigitalOut::delivery`](crate::DigitalOut::delivery)). Default `None`: a write
    /// that returned `Ok` is on the device already.
    fn output_delivery(&self, bit: u32) -> Option<crate::Delivery> {
        let _ = bit;
        None
    }
}

impl<T: DigitalOutputImage> crate::DigitalOut for T {
    fn output_count(&self) -> u32 {
        self.outputs().len()
    }

    fn set_bit(&self, bit: u32, value: bool) -> Result<(), DeviceError> {
        self.outputs().check_bit(bit)?;
        self.check_span_writable(BitSpan::new(bit, bit, self.outputs().len())?)?;
        self.outputs().set(bit, value)?;
        self.outputs_written(Written::Bit { bit, value });
        Ok(())
    }

    fn check_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        self.outputs().get(bit)
    }

    fn set_sequence(&self, start: u32, stop: u32, value: u64) -> Result<(), DeviceError> {
        let span = BitSpan::new(start, stop, self.outputs().len())?;
        span.check_value(value)?;
        self.check_span_writable(span)?;
        self.outputs().write_span(span, value)?;
        self.outputs_written(Written::Span { span, value });
        Ok(())
    }

    fn check_sequence(&self, start: u32, stop: u32) -> Result<u64, DeviceError> {
        Ok(self
            .outputs()
            .read_span(BitSpan::new(start, stop, self.outputs().len())?))
    }

    fn delivery(&self, bit: u32) -> Option<crate::Delivery> {
        self.output_delivery(bit)
    }
}
