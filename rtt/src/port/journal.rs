//! A journal: one ring that many output ports of one-word samples append to, each write an
//! entry (the port's tap number, the time it was written, the value's word), read in the
//! order written by one reader off the real-time threads. What a recording taps a
//! component's ports with ([`tap`]).
//!
//! Why not a ring per port: a recorded write then touched the port's own ring — its
//! position and its next slot, both on lines the recorder's thread had read since, so two
//! lines fetched back from the other core per port and step. Appending to one journal, the
//! ports of a step write one position line (fetched once per step) and entries side by
//! side, three to a line pair: a hundred recorded ports cost about forty line fetches a step
//! where they cost two hundred.
//!
//! The ports of a journal are normally written from their component's steps, but nothing
//! makes them: a port may be written from an operation in the caller's thread, or handed
//! to a thread of the component's own. So a journal has lanes, each a single-writer ring
//! that a writer takes at its first write and keeps: a step's writes go to the lane of its
//! activity (whose steps never overlap, whatever thread runs them, so the lane stays its
//! own across a stop and start), a write outside any step to the lane of its thread. A
//! write finds its lane with a plain load and compare and appends with plain stores — no
//! locked instruction, which would wait for the stores of the writes before it to reach
//! memory and so pay each entry's cache miss in full. The first lane holds the journal's
//! capacity, the others an eighth of it; a write finding every lane taken by other writers
//! (more than three threads writing outside steps over the journal's life), or its lane
//! full, is dropped and counted. Never waits, never allocates, no lock.
//!
//! Every field is an atomic, so no `unsafe`: an entry is written with relaxed stores before
//! the release store of the position that publishes it, and read after the acquire load
//! that sees that position; the writer reuses an entry only once the reader has published,
//! with a release store after its loads, that it is done with it.

use super::channel::{TapEnd, journal_tap};
use super::{ConnectError, ConnectionInfo, OutputPort, OutputShared};
use crossbeam_utils::CachePadded;
use std::cell::Cell as ThreadCell;
use std::sync::Arc;
use std::sync::atomic::{AtomicU32, AtomicU64, AtomicUsize, Ordering};

/// The most entries a journal holds.
pub const MAX_ENTRIES: usize = 1 << 22;

/// One entry's place in the journal.
#[derive(Default)]
struct Cell {
    tap: AtomicU32,
    at: AtomicU64,
    word: AtomicU64,
}

/// Lanes of a journal: the component's thread and three more.
const LANES: usize = 4;

/// The key of the lane a write goes to: its step's activity, or outside any step its
/// thread (tokens with the top bit set: never an activity's key, never reused).
#[inline]
fn writer_key() -> u64 {
    match crate::activity::step_owner() {
        0 => thread_token() | 1 << 63,
        owner => owner,
    }
}

/// This thread's token (from 1 up).
fn thread_token() -> u64 {
    static NEXT: AtomicU64 = AtomicU64::new(1);
    thread_local! {
        static TOKEN: ThreadCell<u64> = const { ThreadCell::new(0) };
    }
    TOKEN.with(|t| match t.get() {
        0 => {
            let token = NEXT.fetch_add(1, Ordering::Relaxed);
            t.set(token);
            token
        }
        token => token,
    })
}

/// What the appending side keeps, on a line of its own.
#[derive(Default)]
struct Tail {
    /// The key of the writer whose lane it is (0: free; see [`writer_key`]).
    owner: AtomicU64,
    /// Entries appended (published with a release store).
    pos: AtomicU64,
    /// `pos` wrapped to the journal's length.
    slot: AtomicUsize,
    /// The reader's position at the last look.
    seen: AtomicU64,
}

/// One entry as read: the tap it came through, when it was written (ns on the monotonic
/// clock: the start of the step that wrote it), and the value's word.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Entry {
    /// The tap's number, as given to [`tap`].
    pub tap: u32,
    /// When it was written.
    pub at: u64,
    /// The value (see [`word`](super::word)).
    pub word: u64,
}

/// One thread's single-writer ring.
struct Lane {
    entries: Box<[Cell]>,
    tail: CachePadded<Tail>,
    /// Entries taken by the reader, on a line of its own.
    head: CachePadded<AtomicU64>,
    /// The reader's `head` wrapped to the lane's length (only the reader touches it).
    head_slot: AtomicUsize,
}

impl Lane {
    fn new(capacity: usize) -> Lane {
        Lane {
            entries: (0..capacity.max(1)).map(|_| Cell::default()).collect(),
            tail: CachePadded::new(Tail::default()),
            head: CachePadded::new(AtomicU64::new(0)),
            head_slot: AtomicUsize::new(0),
        }
    }

    /// Appends, from the lane's owner only; false when full.
    #[inline]
    fn append(&self, tap: u32, at: u64, word: u64) -> bool {
        let t = &*self.tail;
        let pos = t.pos.load(Ordering::Relaxed);
        let len = self.entries.len() as u64;
        if pos - t.seen.load(Ordering::Relaxed) >= len {
            let head = self.head.load(Ordering::Acquire);
            t.seen.store(head, Ordering::Relaxed);
            if pos - head >= len {
                return false;
            }
        }
        let slot = t.slot.load(Ordering::Relaxed);
        let cell = &self.entries[slot];
        cell.tap.store(tap, Ordering::Relaxed);
        cell.at.store(at, Ordering::Relaxed);
        cell.word.store(word, Ordering::Relaxed);
        let next = slot + 1;
        t.slot.store(
            if next == self.entries.len() { 0 } else { next },
            Ordering::Relaxed,
        );
        t.pos.store(pos + 1, Ordering::Release);
        true
    }

    /// Takes at most `max` entries, oldest first; how many.
    fn drain(&self, max: usize, take: &mut impl FnMut(Entry)) -> usize {
        let head = self.head.load(Ordering::Relaxed);
        let tail = self.tail.pos.load(Ordering::Acquire);
        let n = usize::try_from(tail - head).unwrap_or(usize::MAX).min(max);
        let mut slot = self.head_slot.load(Ordering::Relaxed);
        for _ in 0..n {
            let cell = &self.entries[slot];
            take(Entry {
                tap: cell.tap.load(Ordering::Relaxed),
                at: cell.at.load(Ordering::Relaxed),
                word: cell.word.load(Ordering::Relaxed),
            });
            slot += 1;
            if slot == self.entries.len() {
                slot = 0;
            }
        }
        self.head_slot.store(slot, Ordering::Relaxed);
        self.head.store(head + n as u64, Ordering::Release);
        n
    }
}

/// A journal of at most a fixed number of entries a lane (see the module).
pub struct Journal {
    lanes: [Lane; LANES],
    /// Writes dropped: a lane full, or every lane taken by other threads.
    dropped: AtomicU64,
}

impl Journal {
    /// A journal whose first lane holds `capacity` entries (at least 1, at most
    /// [`MAX_ENTRIES`]) and each other an eighth of that (at least 64).
    pub fn new(capacity: usize) -> Journal {
        let capacity = capacity.clamp(1, MAX_ENTRIES);
        let other = (capacity / 8).max(64);
        Journal {
            lanes: std::array::from_fn(|i| Lane::new(if i == 0 { capacity } else { other })),
            dropped: AtomicU64::new(0),
        }
    }

    /// How many entries its first lane (the component's thread's) holds.
    pub fn capacity(&self) -> usize {
        self.lanes[0].entries.len()
    }

    /// Writes dropped so far (a lane full, or every lane taken by other threads).
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Appends an entry to the calling thread's lane; false when it was dropped (counted).
    /// Wait-free, and no locked instruction once the thread has its lane (see the module).
    #[inline]
    pub(crate) fn append(&self, tap: u32, at: u64, word: u64) -> bool {
        let me = writer_key();
        for lane in &self.lanes {
            let owner = lane.tail.owner.load(Ordering::Relaxed);
            let mine = owner == me
                || (owner == 0
                    && lane
                        .tail
                        .owner
                        .compare_exchange(0, me, Ordering::Acquire, Ordering::Relaxed)
                        .is_ok());
            if mine {
                if lane.append(tap, at, word) {
                    return true;
                }
                break;
            }
        }
        self.dropped.fetch_add(1, Ordering::Relaxed);
        false
    }

    /// Takes at most `max` entries from each lane into `take`, each lane's oldest first
    /// (lanes one after the other: entries of different writers are not ordered among
    /// themselves); how many it took. For one reader at a time (a second one would take
    /// entries the first is taking: never torn, but not each once).
    pub fn drain(&self, max: usize, mut take: impl FnMut(Entry)) -> usize {
        self.lanes.iter().map(|l| l.drain(max, &mut take)).sum()
    }
}

/// A tap of an output port into a [`Journal`] (made by [`tap`]): while it lives, each write
/// of the port appends an entry. Dropped, it closes: the port lets go at its next write,
/// and the connection is freed off the port's thread.
pub struct Tap {
    ch: Option<Arc<dyn TapEnd>>,
}

impl Tap {
    /// The connection's counters: written, and dropped (the journal full, or another
    /// thread appending to it at that instant).
    pub fn info(&self) -> Option<ConnectionInfo> {
        self.ch.as_ref().map(|c| c.info())
    }
}

impl Tap {
    /// Counts `n` entries of this tap taken from the journal (its connection's written and
    /// read counters: the writer appends without touching them).
    pub fn taken(&self, n: u64) {
        if let Some(ch) = &self.ch {
            ch.taken(n);
        }
    }
}

impl Drop for Tap {
    fn drop(&mut self) {
        if let Some(ch) = self.ch.take() {
            ch.close();
            ch.bury();
        }
    }
}

impl std::fmt::Debug for Tap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Tap").field("info", &self.info()).finish()
    }
}

/// Taps `output` into `journal` as number `tap`, the journal's reader named `reader` (what
/// the port's connections list shows). The port takes the tap up at its next write, as it
/// does a connection. A port whose samples are not one word is refused
/// ([`ConnectError::NotOneWord`]).
///
/// ```
/// use rtt::port::OutputPort;
/// use rtt::port::journal::{Journal, tap};
/// use std::sync::Arc;
///
/// let mut a = OutputPort::<f64>::new("a");
/// let mut b = OutputPort::<bool>::new("b");
/// let journal = Arc::new(Journal::new(16));
/// let _ta = tap(&a, &journal, 0, "recording")?;
/// let _tb = tap(&b, &journal, 1, "recording")?;
/// a.write(&1.5);
/// b.write(&true);
/// a.write(&2.5);
/// let mut got = Vec::new();
/// journal.drain(usize::MAX, |e| got.push((e.tap, e.word)));
/// assert_eq!(got, [(0, 1.5f64.to_bits()), (1, 1), (0, 2.5f64.to_bits())]);
/// # Ok::<(), rtt::port::ConnectError>(())
/// ```
pub fn tap<T: Clone + Send + 'static>(
    output: &OutputPort<T>,
    journal: &Arc<Journal>,
    tap: u32,
    reader: &str,
) -> Result<Tap, ConnectError> {
    tap_shared(output.shared(), journal, tap, reader)
}

pub(crate) fn tap_shared<T: Clone + Send + 'static>(
    out: &Arc<OutputShared<T>>,
    journal: &Arc<Journal>,
    tap: u32,
    reader: &str,
) -> Result<Tap, ConnectError> {
    if !super::word::is_word::<T>() {
        return Err(ConnectError::NotOneWord {
            port: out.name.to_string(),
            type_name: crate::typename::of::<T>(),
        });
    }
    let from = super::channel::From {
        name: out.name.clone(),
        changed: out.links.changed.clone(),
        word: None,
    };
    let writer = journal_tap::<T>(from, Arc::from(reader), journal.clone(), tap);
    let ch = writer.ch.clone();
    out.links.offer(&out.name, &ch, writer, |w| &w.ch)?;
    Ok(Tap { ch: Some(ch) })
}

impl std::fmt::Debug for Journal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Journal")
            .field("capacity", &self.capacity())
            .field("dropped", &self.dropped())
            .finish_non_exhaustive()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    fn all(j: &Journal) -> Vec<Entry> {
        let mut v = Vec::new();
        j.drain(usize::MAX, |e| v.push(e));
        v
    }

    #[test]
    fn entries_come_out_in_order_and_a_full_journal_drops_the_newest() {
        let j = Journal::new(3);
        for i in 0..5u32 {
            let _ = j.append(i % 2, u64::from(i) * 10, u64::from(i) + 100);
        }
        assert_eq!(j.dropped(), 2);
        let got = all(&j);
        assert_eq!(
            got,
            [
                Entry {
                    tap: 0,
                    at: 0,
                    word: 100
                },
                Entry {
                    tap: 1,
                    at: 10,
                    word: 101
                },
                Entry {
                    tap: 0,
                    at: 20,
                    word: 102
                },
            ]
        );
        // Laps round the ring: each entry once, in order.
        let mut next = 0u64;
        for lap in 0..7u64 {
            for k in 0..2u64 {
                assert!(j.append(0, lap, next + k));
            }
            let got = all(&j);
            assert_eq!(
                got.iter().map(|e| e.word).collect::<Vec<_>>(),
                [next, next + 1]
            );
            next += 2;
        }
        assert_eq!(j.drain(1, |_| {}), 0);
    }

    /// Each of four threads takes a lane; a fifth finds none and its writes are counted.
    #[test]
    fn a_thread_finding_every_lane_taken_is_dropped_and_counted() {
        let j = Arc::new(Journal::new(8));
        for t in 0..5u32 {
            let j = j.clone();
            let took = std::thread::spawn(move || j.append(t, 1, 2))
                .join()
                .unwrap();
            assert_eq!(took, t < 4, "thread {t}");
        }
        assert_eq!(j.dropped(), 1);
        let mut taps = Vec::new();
        j.drain(usize::MAX, |e| taps.push(e.tap));
        assert_eq!(taps, [0, 1, 2, 3]);
    }

    /// Two writer threads append to one journal while a reader drains it: no entry is torn
    /// (each entry's three words agree), each writer's entries come in its order, and every
    /// write is either read or counted as dropped.
    #[test]
    fn two_writers_and_a_reader_lose_nothing_uncounted() {
        const N: u64 = 200_000;
        let j = Arc::new(Journal::new(64));
        let writers: Vec<_> = (0..2u32)
            .map(|w| {
                let j = j.clone();
                std::thread::spawn(move || {
                    let mut written = 0u64;
                    for i in 0..N {
                        if j.append(w, i, i.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ u64::from(w)) {
                            written += 1;
                        }
                    }
                    written
                })
            })
            .collect();
        let mut last = [None::<u64>; 2];
        let mut read = 0u64;
        let check = |e: Entry, last: &mut [Option<u64>; 2]| {
            assert!(e.tap < 2, "{e:?}");
            assert_eq!(
                e.word,
                e.at.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ u64::from(e.tap),
                "torn: {e:?}"
            );
            let l = &mut last[e.tap as usize];
            assert!(
                l.is_none_or(|l| e.at > l),
                "out of order: {e:?} after {l:?}"
            );
            *l = Some(e.at);
        };
        while !writers.iter().all(|w| w.is_finished()) {
            read += j.drain(usize::MAX, |e| check(e, &mut last)) as u64;
        }
        let written: u64 = writers.into_iter().map(|w| w.join().unwrap()).sum();
        read += j.drain(usize::MAX, |e| check(e, &mut last)) as u64;
        assert_eq!(read, written);
        assert_eq!(written + j.dropped(), 2 * N);
        assert!(read > 0);
    }
}
