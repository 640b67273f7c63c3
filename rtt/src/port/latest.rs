//! The last value passed from one writer to its reader: what a data connection carries,
//! and what a port keeps of its last sample for introspection (an output port's one-word
//! register is both: its data connections read it). A one-word sample
//! (`f64`, `bool`, the integers, `char`) goes through a [`WordCell`]: plain loads and
//! stores, as cheap as a seqlock, and wait-free; any other type through a triple buffer
//! (one atomic exchange on each side), which copies with `clone_from` and so allocates
//! nothing for a `Vec` or `String` within its data sample's size.

use super::word::{Found, WordCell, from_word, is_word, to_word};
use crossbeam_utils::CachePadded;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

/// The writing half.
pub(crate) enum LatestIn<T: Send> {
    /// A one-word sample: the register and the writer's last version.
    Word {
        /// The register.
        cell: Arc<WordCell>,
        /// Versions written so far.
        written: u64,
    },
    /// A one-word sample kept only to be looked at (a port's last value): one store, no
    /// version.
    Plain(Arc<CachePadded<AtomicU64>>),
    /// Any other sample.
    Triple(triple_buffer::Input<T>),
}

/// The reading half.
pub(crate) enum LatestOut<T: Send> {
    /// A one-word sample: the register and the version last taken.
    Word {
        /// The register.
        cell: Arc<WordCell>,
        /// The version last taken (0: none).
        seen: u64,
    },
    /// A one-word sample kept only to be looked at: its word, every look a new value.
    Plain(Arc<CachePadded<AtomicU64>>),
    /// Any other sample.
    Triple(triple_buffer::Output<T>),
}

/// A writing and a reading half for an input port's last read value, looked at now and
/// then from another thread: a one-word sample is one relaxed store per read (no version: every
/// look takes the value as it is).
pub(crate) fn snapshot<T: Clone + Send + 'static>(sample: &T) -> (LatestIn<T>, LatestOut<T>) {
    if is_word::<T>() {
        // On a line of its own: its reader's thread stores to it at every new sample.
        let cell = Arc::new(CachePadded::new(AtomicU64::new(to_word(sample))));
        (LatestIn::Plain(cell.clone()), LatestOut::Plain(cell))
    } else {
        let (i, o) = triple_buffer::triple_buffer(sample);
        (LatestIn::Triple(i), LatestOut::Triple(o))
    }
}

/// A writing and a reading half; `sample` sizes a triple buffer's copies.
pub(crate) fn latest<T: Clone + Send + 'static>(sample: &T) -> (LatestIn<T>, LatestOut<T>) {
    if is_word::<T>() {
        let cell = Arc::new(WordCell::new());
        (
            LatestIn::Word {
                cell: cell.clone(),
                written: 0,
            },
            LatestOut::Word { cell, seen: 0 },
        )
    } else {
        let (i, o) = triple_buffer::triple_buffer(sample);
        (LatestIn::Triple(i), LatestOut::Triple(o))
    }
}

impl<T: Clone + Send + 'static> LatestIn<T> {
    /// Publishes `value`. Wait-free; allocation-free when `clone_from` is.
    #[inline]
    pub(crate) fn publish(&mut self, value: &T) {
        match self {
            LatestIn::Word { cell, written } => {
                *written += 1;
                cell.write(*written, to_word(value));
            }
            LatestIn::Plain(cell) => cell.store(to_word(value), Ordering::Relaxed),
            LatestIn::Triple(input) => {
                input.input_buffer_mut().clone_from(value);
                input.publish();
            }
        }
    }
}

impl<T: Clone + Send + 'static> LatestOut<T> {
    /// Copies the latest value into `into` if it was not taken before; false when there is
    /// none new. Wait-free; allocation-free when `clone_from` is.
    #[inline]
    pub(crate) fn take(&mut self, into: &mut T) -> bool {
        match self {
            LatestOut::Word { cell, seen } => match cell.read(*seen) {
                Found::New { version, value } => {
                    *seen = version;
                    from_word(value, into);
                    true
                }
                Found::Nothing => false,
            },
            LatestOut::Plain(cell) => {
                from_word(cell.load(Ordering::Relaxed), into);
                true
            }
            LatestOut::Triple(output) => {
                if output.update() {
                    into.clone_from(output.output_buffer());
                    true
                } else {
                    false
                }
            }
        }
    }

    /// True when a value not taken yet is waiting.
    pub(crate) fn has_new(&self) -> bool {
        match self {
            LatestOut::Word { cell, seen } => cell.version() != *seen,
            LatestOut::Plain(_) => true,
            LatestOut::Triple(output) => output.updated(),
        }
    }
}
