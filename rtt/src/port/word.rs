//! The last value of a one-word sample (`f64`, `bool`, the integers, `char`) passed from one
//! writer to any number of readers with plain loads and stores: no read-modify-write, no
//! lock, no allocation, wait-free on both sides. What a data connection of such a type is,
//! and what a port keeps of its last value for introspection.
//!
//! The protocol (a versioned four-slot register): the writer's `n`-th write stores the
//! value in slot `n % 4`, then publishes `n` as the sequence number (both release). A
//! reader loads the sequence `s` (acquire), the value of slot `s % 4` (acquire), and the
//! sequence again: if it is still below `s + 3`, the slot held write `s`'s value — write
//! `s + 4`, the next to use the slot, begins only after `s + 3` was published, and a reader
//! that saw any of its store sees that publication too. A reader overtaken three times
//! within one look tries again, at most [`TRIES`] times; a reader overtaken every time (a
//! writer that writes more than three times while the reader makes one look, each of
//! [`TRIES`] times: the reader preempted again and again) reports no new value this time,
//! never a torn or stale one, and takes the latest at its next read.
//!
//! The protocol is generic over [`Word`] so that `rtt/tests/word_model.rs` runs it under
//! loom's model checker, every interleaving of a writer and a reader.

use std::any::{Any, TypeId};
use std::sync::atomic::{AtomicU64, Ordering};

/// Looks a reader makes before it reports no new value (see the module doc).
pub const TRIES: usize = 4;

/// A 64-bit atomic cell: the standard one, or a model checker's.
pub trait Word {
    /// A cell holding `v`.
    fn new(v: u64) -> Self;
    /// Loads.
    fn load(&self, order: Ordering) -> u64;
    /// Stores.
    fn store(&self, v: u64, order: Ordering);
}

impl Word for AtomicU64 {
    fn new(v: u64) -> Self {
        AtomicU64::new(v)
    }
    #[inline]
    fn load(&self, order: Ordering) -> u64 {
        AtomicU64::load(self, order)
    }
    #[inline]
    fn store(&self, v: u64, order: Ordering) {
        AtomicU64::store(self, v, order)
    }
}

/// Slots of the register (a power of two: the slot of a version is a mask away).
const SLOTS: u64 = 4;

/// The register: a sequence number and four slots, on a cache line of its own (its writer
/// stores to it at every write; a neighbour another thread writes must not share it).
#[repr(align(128))]
pub struct WordCell<A = AtomicU64> {
    seq: A,
    slots: [A; SLOTS as usize],
}

/// What a reader found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Found {
    /// Nothing newer than the version the reader has.
    Nothing,
    /// Write `version`'s value.
    New {
        /// The writer's sequence number of the value.
        version: u64,
        /// The value.
        value: u64,
    },
}

impl<A: Word> Default for WordCell<A> {
    fn default() -> Self {
        WordCell::new()
    }
}

impl<A: Word> WordCell<A> {
    /// A register never written (version 0).
    pub fn new() -> Self {
        WordCell {
            seq: A::new(0),
            slots: [A::new(0), A::new(0), A::new(0), A::new(0)],
        }
    }

    /// The writer's `version`-th write of `value` (versions 1, 2, 3, … from one thread).
    #[inline]
    pub fn write(&self, version: u64, value: u64) {
        self.slots[(version % SLOTS) as usize].store(value, Ordering::Release);
        self.seq.store(version, Ordering::Release);
    }

    /// The latest version published (0: never written).
    #[inline]
    pub fn version(&self) -> u64 {
        self.seq.load(Ordering::Acquire)
    }

    /// The latest value written, for a look from another thread (`None`: never written).
    /// Never waits: a reader overtaken [`TRIES`] times takes the slot of the latest version
    /// as it is then — a value the writer wrote at that version or after (each slot is one
    /// atomic word, never torn).
    pub fn latest(&self) -> Option<u64> {
        match self.read(0) {
            Found::New { value, .. } => Some(value),
            Found::Nothing => {
                let s = self.seq.load(Ordering::Acquire);
                (s != 0).then(|| self.slots[(s % SLOTS) as usize].load(Ordering::Acquire))
            }
        }
    }

    /// The latest value if its version is not `seen`.
    #[inline]
    pub fn read(&self, seen: u64) -> Found {
        for _ in 0..TRIES {
            let s = self.seq.load(Ordering::Acquire);
            if s == seen {
                return Found::Nothing;
            }
            let value = self.slots[(s % SLOTS) as usize].load(Ordering::Acquire);
            if self.seq.load(Ordering::Relaxed) < s.saturating_add(SLOTS - 1) {
                return Found::New { version: s, value };
            }
        }
        Found::Nothing
    }
}

/// True for the sample types kept in one word: `f64`, `f32`, `bool`, `char` and the
/// integers up to 64 bits.
pub fn is_word<T: 'static>() -> bool {
    let t = TypeId::of::<T>();
    [
        TypeId::of::<f64>(),
        TypeId::of::<f32>(),
        TypeId::of::<bool>(),
        TypeId::of::<char>(),
        TypeId::of::<u8>(),
        TypeId::of::<u16>(),
        TypeId::of::<u32>(),
        TypeId::of::<u64>(),
        TypeId::of::<usize>(),
        TypeId::of::<i8>(),
        TypeId::of::<i16>(),
        TypeId::of::<i32>(),
        TypeId::of::<i64>(),
        TypeId::of::<isize>(),
    ]
    .contains(&t)
}

/// A one-word sample as its word (0 for a type [`is_word`] refuses, which never gets here).
#[inline]
pub fn to_word<T: 'static>(v: &T) -> u64 {
    let a = v as &dyn Any;
    macro_rules! as_word {
        ($($t:ty => $f:expr),* $(,)?) => {
            $(if let Some(x) = a.downcast_ref::<$t>() {
                return $f(*x);
            })*
        };
    }
    as_word!(
        f64 => f64::to_bits,
        f32 => |x: f32| u64::from(x.to_bits()),
        bool => u64::from,
        char => |c: char| u64::from(u32::from(c)),
        u8 => u64::from,
        u16 => u64::from,
        u32 => u64::from,
        u64 => |x| x,
        usize => |x: usize| x as u64,
        i8 => |x: i8| x as u64,
        i16 => |x: i16| x as u64,
        i32 => |x: i32| x as u64,
        i64 => |x: i64| x as u64,
        isize => |x: isize| x as u64,
    );
    0
}

/// Writes word `w` (made by [`to_word`] from a `T`) into `into`.
#[inline]
pub fn from_word<T: 'static>(w: u64, into: &mut T) {
    let a = into as &mut dyn Any;
    macro_rules! from_word {
        ($($t:ty => $f:expr),* $(,)?) => {
            $(if let Some(x) = a.downcast_mut::<$t>() {
                *x = $f(w);
                return;
            })*
        };
    }
    // The words came from values of the same type: the narrowing casts give them back.
    from_word!(
        f64 => f64::from_bits,
        f32 => |w: u64| f32::from_bits(w as u32),
        bool => |w: u64| w != 0,
        u8 => |w: u64| w as u8,
        u16 => |w: u64| w as u16,
        u32 => |w: u64| w as u32,
        u64 => |w| w,
        usize => |w: u64| w as usize,
        i8 => |w: u64| w as i8,
        i16 => |w: u64| w as i16,
        i32 => |w: u64| w as i32,
        i64 => |w: u64| w as i64,
        isize => |w: u64| w as isize,
    );
    if let Some(c) = a.downcast_mut::<char>()
        && let Some(v) = u32::try_from(w).ok().and_then(char::from_u32)
    {
        *c = v;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round<T: 'static + Copy + PartialEq + std::fmt::Debug>(v: T, zero: T) {
        assert!(is_word::<T>());
        let mut back = zero;
        from_word(to_word(&v), &mut back);
        assert_eq!(back, v);
    }

    #[test]
    fn one_word_types_round_trip() {
        round(-1.5e300f64, 0.0);
        round(f64::NAN.to_bits(), 0);
        round(-2.5f32, 0.0);
        round(true, false);
        round('€', 'a');
        round(u64::MAX, 0);
        round(i64::MIN, 0);
        round(-7i8, 0);
        round(usize::MAX, 0);
        assert!(!is_word::<String>());
        assert!(!is_word::<[f64; 2]>());
    }

    #[test]
    fn a_reader_gets_each_version_once_and_the_latest() {
        let c: WordCell = WordCell::new();
        assert_eq!(c.read(0), Found::Nothing);
        c.write(1, 10);
        assert_eq!(
            c.read(0),
            Found::New {
                version: 1,
                value: 10
            }
        );
        assert_eq!(c.read(1), Found::Nothing);
        for v in 2..=7 {
            c.write(v, v * 10);
        }
        assert_eq!(
            c.read(1),
            Found::New {
                version: 7,
                value: 70
            }
        );
    }
}
