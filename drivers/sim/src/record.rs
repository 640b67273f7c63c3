//! The record of output writes: what a test reads back to see exactly what was driven.
//!
//! Writes come from any thread, real-time ones included, so recording is a push onto a
//! pre-allocated lock-free queue; a full queue drops the write from the record (never
//! from the outputs) and counts it.

use crossbeam_queue::ArrayQueue;
use device_interface::time::Timestamp;
use std::sync::atomic::{AtomicU64, Ordering};

/// One output write.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OutputWrite {
    /// An analog output set to a raw value.
    Analog {
        /// The channel.
        channel: u32,
        /// The raw value written.
        raw: i64,
    },
    /// A digital output bit set.
    Bit {
        /// The bit.
        bit: u32,
        /// Its new value.
        value: bool,
    },
    /// Digital outputs `start..=stop` set from `value` (bit 0 at `start`).
    Sequence {
        /// First bit.
        start: u32,
        /// Last bit (inclusive).
        stop: u32,
        /// The value written.
        value: u64,
    },
    /// An encoder's position set.
    EncoderPosition {
        /// The encoder.
        encoder: u32,
        /// The new position.
        position: i64,
    },
    /// An encoder's turn count set.
    EncoderTurn {
        /// The encoder.
        encoder: u32,
        /// The new turn count.
        turn: i64,
    },
}

/// A recorded write with its place in the order of all writes to the card.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OutputEvent {
    /// Position in the card's total order of writes, from 0.
    pub seq: u64,
    /// When the write was made, on the card's clock.
    pub time: Timestamp,
    /// What was written.
    pub write: OutputWrite,
}

pub(crate) struct OutputRecord {
    queue: ArrayQueue<OutputEvent>,
    seq: AtomicU64,
    dropped: AtomicU64,
}

impl OutputRecord {
    pub(crate) fn new(capacity: usize) -> Self {
        OutputRecord {
            queue: ArrayQueue::new(capacity),
            seq: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
        }
    }

    pub(crate) fn push(&self, time: Timestamp, write: OutputWrite) {
        let seq = self.seq.fetch_add(1, Ordering::AcqRel);
        if self.queue.push(OutputEvent { seq, time, write }).is_err() {
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    pub(crate) fn take(&self) -> Vec<OutputEvent> {
        let mut v: Vec<OutputEvent> = std::iter::from_fn(|| self.queue.pop()).collect();
        // Writers on different threads may push in a different order than they numbered.
        v.sort_by_key(|e| e.seq);
        v
    }

    pub(crate) fn count(&self) -> u64 {
        self.seq.load(Ordering::Acquire)
    }

    pub(crate) fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
}
