//! The FIFO of a buffer connection that drops the newest sample when full
//! ([`ConnKind::Buffer`](super::ConnKind::Buffer)): a single-producer single-consumer ring
//! of samples made when the connection is, each end keeping its own position and its last
//! look at the other's.
//!
//! A push writes the sample (and its stamp) in place and publishes its position with one
//! release store; it reads the reader's position only when its last look says the ring is
//! full. A pop mirrors it. So an end that is not kept waiting touches the other end's
//! cache line about once per lap, not once per sample — the write of a recorded port costs
//! a copy and a store, where the two shared queues before it cost two compare-and-swaps on
//! lines the reader's thread had just written. No lock, no allocation (`clone_from` into a
//! sample made at connect time), wait-free on both sides.
//!
//! Why it is sound: slot `i` is written only by the writer while `i - head < capacity`
//! (the reader has published that it is done with the slot's last lap), and read only by
//! the reader while `i < tail` (the writer has published the sample). The release stores
//! of the positions and the acquire loads that see them order the slot's accesses.

use crossbeam_utils::CachePadded;
use std::cell::UnsafeCell;
use std::sync::atomic::{AtomicU64, Ordering};

/// One sample with the time it was written (0 unless the connection is stamped).
pub(super) struct Slot<T> {
    pub(super) at: u64,
    pub(super) value: T,
}

/// An end's own position and what it last saw of the other's.
#[derive(Default)]
pub(super) struct End {
    /// Samples this end has pushed (writer) or popped (reader).
    pos: u64,
    /// The other end's position at this end's last look.
    seen: u64,
    /// `pos` wrapped to the ring's length: the slot it is at.
    slot: usize,
}

impl End {
    /// Moves on one sample.
    #[inline]
    fn advance(&mut self, len: usize) {
        self.pos += 1;
        self.slot += 1;
        if self.slot == len {
            self.slot = 0;
        }
    }
}

pub(super) struct Ring<T> {
    /// As many as it holds at most.
    slots: Box<[UnsafeCell<Slot<T>>]>,
    /// `slots.len()`.
    capacity: u64,
    /// Samples popped (written by the reader), on a line of its own.
    head: CachePadded<AtomicU64>,
    /// Samples pushed (written by the writer), on a line of its own.
    tail: CachePadded<AtomicU64>,
}

// SAFETY: the slots are handed between the one writer and the one reader by the positions
// (see the module doc); a sample crosses threads, so `T: Send` is enough.
#[allow(
    unsafe_code,
    reason = "the positions hand each slot between the writer and the reader"
)]
unsafe impl<T: Send> Sync for Ring<T> {}

impl<T: Clone> Ring<T> {
    /// A ring of `capacity` samples (at least 1), each a copy of `sample`.
    pub(super) fn new(capacity: usize, sample: &T) -> Self {
        let capacity = capacity.max(1);
        Ring {
            slots: (0..capacity)
                .map(|_| {
                    UnsafeCell::new(Slot {
                        at: 0,
                        value: sample.clone(),
                    })
                })
                .collect(),
            capacity: capacity as u64,
            head: CachePadded::new(AtomicU64::new(0)),
            tail: CachePadded::new(AtomicU64::new(0)),
        }
    }

    /// Writer side: appends `value` stamped `at`; false when full (the sample is dropped).
    #[allow(
        unsafe_code,
        reason = "the slot at the writer's position is the writer's (module doc)"
    )]
    #[inline]
    pub(super) fn push(&self, end: &mut End, value: &T, at: u64) -> bool {
        if end.pos - end.seen >= self.capacity {
            end.seen = self.head.load(Ordering::Acquire);
            if end.pos - end.seen >= self.capacity {
                return false;
            }
        }
        let cell = &self.slots[end.slot];
        // SAFETY: `pos - head < capacity`: the reader is done with this slot and touches
        // it again only after the store below publishes it.
        let slot = unsafe { &mut *cell.get() };
        slot.value.clone_from(value);
        slot.at = at;
        end.advance(self.slots.len());
        self.tail.store(end.pos, Ordering::Release);
        true
    }

    /// Reader side: takes the oldest sample into `into` and returns its stamp; `None` when
    /// empty.
    #[allow(
        unsafe_code,
        reason = "the slot at the reader's position is the reader's (module doc)"
    )]
    #[inline]
    pub(super) fn pop(&self, end: &mut End, into: &mut T) -> Option<u64> {
        if end.pos == end.seen {
            end.seen = self.tail.load(Ordering::Acquire);
            if end.pos == end.seen {
                return None;
            }
        }
        let cell = &self.slots[end.slot];
        // SAFETY: `pos < tail`: the writer published this slot and writes it again only
        // after the store below tells it the reader is done.
        let slot = unsafe { &*cell.get() };
        into.clone_from(&slot.value);
        let at = slot.at;
        end.advance(self.slots.len());
        self.head.store(end.pos, Ordering::Release);
        Some(at)
    }

    /// True when it holds nothing (a look from either end).
    pub(super) fn is_empty(&self) -> bool {
        self.head.load(Ordering::Acquire) == self.tail.load(Ordering::Acquire)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keeps_order_drops_the_newest_when_full_and_goes_round() {
        let ring = Ring::new(3, &0u32);
        let (mut w, mut r) = (End::default(), End::default());
        let mut got = 0;
        for lap in 0..5u32 {
            for i in 0..3 {
                assert!(ring.push(&mut w, &(lap * 10 + i), u64::from(i)));
            }
            assert!(!ring.push(&mut w, &99, 0), "full: the newest is dropped");
            for i in 0..3 {
                assert_eq!(ring.pop(&mut r, &mut got), Some(u64::from(i)));
                assert_eq!(got, lap * 10 + i);
            }
            assert_eq!(ring.pop(&mut r, &mut got), None);
            assert!(ring.is_empty());
        }
    }

    #[test]
    fn a_writer_and_a_reader_on_two_threads_lose_and_tear_nothing() {
        const N: u64 = 200_000;
        let ring = std::sync::Arc::new(Ring::new(16, &vec![0u64; 8]));
        let writer = {
            let ring = ring.clone();
            std::thread::spawn(move || {
                let mut end = End::default();
                let mut sample = vec![0u64; 8];
                let mut n = 0;
                while n < N {
                    sample.fill(n);
                    if ring.push(&mut end, &sample, n) {
                        n += 1;
                    } else {
                        std::hint::spin_loop();
                    }
                }
            })
        };
        let mut end = End::default();
        let mut into = vec![0u64; 8];
        let mut next = 0;
        while next < N {
            match ring.pop(&mut end, &mut into) {
                Some(at) => {
                    assert_eq!(at, next);
                    assert!(into.iter().all(|&v| v == next), "sample {next} torn");
                    next += 1;
                }
                None => std::hint::spin_loop(),
            }
        }
        writer.join().unwrap();
        assert!(ring.is_empty());
    }
}
