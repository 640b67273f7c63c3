//! A histogram a real-time thread records into without a lock: each value is one relaxed
//! atomic add (and a `fetch_max`), and any thread reads quantiles while it records. Buckets
//! are log-linear — 32 to each power of two — so a quantile is exact below 32 and within
//! 1/32 (3.1 %) above; values up to 2^40 are told apart (beyond, they share the last
//! bucket; the maximum stays exact). 1 152 buckets: 9 KiB, made once.

use std::sync::atomic::{AtomicU64, Ordering};

/// log2 of the buckets to each power of two.
const SUB_BITS: u32 = 5;
/// Buckets to each power of two; values below it have a bucket each.
const SUB: u64 = 1 << SUB_BITS;
/// Values at or beyond `1 << TOP_BITS` share the last bucket.
const TOP_BITS: u32 = 40;
/// Number of buckets.
const BUCKETS: usize = ((TOP_BITS - SUB_BITS + 1) as usize) << SUB_BITS;

/// A lock-free histogram of `u64` values (see the module).
#[derive(Debug)]
pub struct AtomicHistogram {
    counts: Box<[AtomicU64]>,
    max: AtomicU64,
}

impl Default for AtomicHistogram {
    fn default() -> Self {
        AtomicHistogram {
            counts: (0..BUCKETS).map(|_| AtomicU64::new(0)).collect(),
            max: AtomicU64::new(0),
        }
    }
}

/// The bucket of `v`.
fn index(v: u64) -> usize {
    let v = v.min((1 << TOP_BITS) - 1);
    if v < SUB {
        return v as usize;
    }
    let octave = 63 - v.leading_zeros(); // ≥ SUB_BITS
    let sub = (v >> (octave - SUB_BITS)) & (SUB - 1);
    (((octave - SUB_BITS + 1) as usize) << SUB_BITS) + sub as usize
}

/// The highest value bucket `i` holds.
fn highest(i: usize) -> u64 {
    let i = i as u64;
    if i < SUB {
        return i;
    }
    let octave = (i >> SUB_BITS) + u64::from(SUB_BITS) - 1;
    let width = 1u64 << (octave - u64::from(SUB_BITS));
    let lowest = (SUB + (i & (SUB - 1))) * width;
    lowest + width - 1
}

impl AtomicHistogram {
    /// Records `v`: two relaxed atomic operations, no lock, no allocation.
    pub fn record(&self, v: u64) {
        self.counts[index(v)].fetch_add(1, Ordering::Relaxed);
        self.max.fetch_max(v, Ordering::Relaxed);
    }

    /// Values recorded.
    pub fn len(&self) -> u64 {
        self.counts.iter().map(|c| c.load(Ordering::Relaxed)).sum()
    }

    /// True before the first value.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The largest value recorded; 0 before the first.
    pub fn max(&self) -> u64 {
        self.max.load(Ordering::Relaxed)
    }

    /// The value below or at which fraction `q` (0..=1) of the values fell: the highest
    /// value of the bucket that holds that rank, no more than the maximum; 0 when empty.
    pub fn quantile(&self, q: f64) -> u64 {
        let counts: Vec<u64> = self
            .counts
            .iter()
            .map(|c| c.load(Ordering::Relaxed))
            .collect();
        let total: u64 = counts.iter().sum();
        if total == 0 {
            return 0;
        }
        // The rank, less a hair for the float's error (0.07 × 100 is 7.000000000000001).
        let want = ((q.clamp(0.0, 1.0) * total as f64 - 1e-9).ceil() as u64).max(1);
        let max = self.max();
        let mut seen = 0;
        for (i, n) in counts.iter().enumerate() {
            seen += n;
            if seen >= want {
                // The last bucket holds everything beyond: its values are known up to the
                // maximum only.
                return if i == BUCKETS - 1 {
                    max
                } else {
                    highest(i).min(max)
                };
            }
        }
        max
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buckets_cover_every_value_in_order_and_hold_their_values() {
        let mut last = 0;
        for v in (0..100_000u64).chain([1 << 20, (1 << 40) - 1, 1 << 40, u64::MAX]) {
            let i = index(v);
            assert!(i < BUCKETS, "{v} -> {i}");
            assert!(i >= last || v > 100_000, "{v} -> {i} after {last}");
            last = i;
            if v < 1 << TOP_BITS {
                assert!(highest(i) >= v, "{v} -> {i} holds up to {}", highest(i));
                assert!(i == 0 || highest(i - 1) < v, "{v} also fits {}", i - 1);
            }
        }
        assert_eq!(index(u64::MAX), BUCKETS - 1);
    }

    #[test]
    fn quantiles_are_exact_below_32_and_within_a_32nd_above() {
        let h = AtomicHistogram::default();
        assert_eq!((h.quantile(0.99), h.max(), h.is_empty()), (0, 0, true));
        for v in 1..=1000u64 {
            h.record(v);
        }
        assert_eq!(h.len(), 1000);
        assert_eq!(h.max(), 1000);
        assert_eq!(h.quantile(0.0), 1);
        assert_eq!(h.quantile(0.02), 20);
        assert_eq!(h.quantile(0.007), 7);
        let p99 = h.quantile(0.99);
        assert!((990..=990 + 990 / 32).contains(&p99), "{p99}");
        assert_eq!(h.quantile(1.0), 1000);
        h.record(5_000_000_000_000);
        assert_eq!(h.max(), 5_000_000_000_000);
        assert_eq!(h.quantile(1.0), 5_000_000_000_000);
    }
}
