//! One connection between an output and an input port: what both ends share (its
//! identity, state and counters), the writing and the reading end with their samples (the
//! last value of a data connection, the queues of a buffer), and the list of a port's
//! connections that other threads add to.
//!
//! A data connection of a one-word sample has no register of its own: its reader reads the
//! output port's register (the port's last value), each reader with its own last version
//! taken, so the port's write is one register write however many such connections it has,
//! and its writing end is touched per write only to wake an event port.

use super::journal::Journal;
use super::latest::{LatestIn, LatestOut, latest};
use super::ring::{End, Ring, Slot};
use super::word::WordCell;
use super::{ConnKind, ConnPolicy, ConnectError, ConnectionInfo};
use crate::activity::Waker;
use crate::lock::lock;
use crossbeam_queue::ArrayQueue;
use crossbeam_utils::CachePadded;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};

static NEXT_CONNECTION: AtomicU64 = AtomicU64::new(1);

/// A port's "look at your connections" flag, on a cache line of its own: read at every
/// write or read of the port, it must not share a line with what other threads write.
pub(super) type Flag = Arc<CachePadded<AtomicBool>>;

/// Adds one to a counter only one thread writes: a plain load and store, no atomic
/// read-modify-write on the hot path.
#[inline]
fn bump(counter: &AtomicU64) {
    counter.store(
        counter.load(Ordering::Relaxed).wrapping_add(1),
        Ordering::Relaxed,
    );
}

/// What both ends of one connection share: its identity, state and counters. `written`
/// and `dropped` are only written by the writer, `read` only by the reader (see [`bump`]).
pub(crate) struct Channel<T> {
    id: u64,
    from: Arc<str>,
    to: Arc<str>,
    policy: ConnPolicy,
    /// The sample pool of a buffer connection; `None` for a data connection, whose last
    /// value's halves live in the two ends.
    queues: Option<Fifo<T>>,
    /// A data connection reading its output port's register: what it counts from.
    shared: Option<SharedWord>,
    /// Closed for good: disconnected, or its reader went away. Neither end uses it again.
    pub(super) closed: AtomicBool,
    /// Its writer went away: the reader still takes what was written, then lets go.
    writer_gone: AtomicBool,
    /// The "look at your connections" flags of the output and of the input port: set
    /// whenever this connection closes or loses an end.
    out_changed: Flag,
    in_changed: Flag,
    /// Each counter on a line of its own: the writer bumps `written` and the reader `read`
    /// at every sample, and neither may take the other's line, or the fields both read at
    /// every sample, away from the other's core.
    written: CachePadded<AtomicU64>,
    read: CachePadded<AtomicU64>,
    dropped: AtomicU64,
    waker: Option<Arc<dyn Waker>>,
    /// A stamped buffer connection: each sample carries the time it was written (see
    /// [`crate::activity::stamp_now`]).
    stamped: bool,
}

/// A data connection of a one-word sample, reading the output port's register.
struct SharedWord {
    cell: Arc<WordCell>,
    /// The register's version when the connection was made.
    base: u64,
    /// 1 when the connection started with the last value written (`init`), else 0.
    init: u64,
}

/// A buffer connection's samples.
#[allow(
    clippy::large_enum_variant,
    reason = "one per connection, inside its Arc: boxing would add a pointer to each write"
)]
enum Fifo<T> {
    /// Dropping the newest when full: a single-producer single-consumer ring.
    Newest(Ring<T>),
    /// Dropping the oldest when full: the writer takes from the reader's end too.
    Oldest(Queues<T>),
    /// A tap into a journal shared with other ports: each write appends (tap, stamp,
    /// word) through the writing end's own handle; the journal's reader takes them. Held
    /// here too, so that the journal is freed with the connection, off the writer's
    /// thread, never by the writer letting go of its end.
    Journal(#[allow(dead_code, reason = "held for its lifetime only")] Arc<Journal>),
}

/// A circular buffer connection's samples, cycling between `free` and `full`.
struct Queues<T> {
    free: ArrayQueue<Slot<T>>,
    full: ArrayQueue<Slot<T>>,
}

impl<T> Channel<T> {
    #[inline]
    pub(super) fn is_closed(&self) -> bool {
        self.closed.load(Ordering::Acquire)
    }

    /// Closes it for good and tells both ports to look.
    pub(super) fn close(&self) {
        self.closed.store(true, Ordering::Release);
        self.out_changed.store(true, Ordering::Release);
        self.in_changed.store(true, Ordering::Release);
    }

    /// Counts one sample its reader took (from the reader's thread only).
    #[inline]
    pub(super) fn count_read(&self) {
        bump(&self.read);
    }

    /// True when the connection carries nothing any more: closed, or its writer gone.
    #[inline]
    fn is_finished(&self) -> bool {
        self.is_closed() || self.writer_gone.load(Ordering::Acquire)
    }

    pub(super) fn info(&self) -> ConnectionInfo {
        ConnectionInfo {
            id: self.id,
            from: self.from.to_string(),
            to: self.to.to_string(),
            policy: self.policy,
            // A shared register's writes since the connection was made are the
            // connection's: no counter to keep per write.
            written: match &self.shared {
                Some(w) => w.cell.version().wrapping_sub(w.base) + w.init,
                None => self.written.load(Ordering::Relaxed),
            },
            read: self.read.load(Ordering::Relaxed),
            dropped: self.dropped.load(Ordering::Relaxed),
        }
    }
}

/// The writing end of one connection, owned by its output port.
pub(crate) struct Writer<T: Send> {
    /// A journal tap's journal and number, kept here so that a write appends without
    /// looking at the connection (one line fewer per recorded port and step). Declared
    /// before `ch` so that it is dropped first: while the connection lives, it holds the
    /// journal too, so the writer letting go never frees the journal (once the connection
    /// goes to the graveyard, another thread may free it at any time).
    tap: Option<(Arc<Journal>, u32)>,
    pub(super) ch: Arc<Channel<T>>,
    latest: Option<LatestIn<T>>,
    /// Its place in a [`Ring`].
    end: End,
}

/// The reading end of one connection, owned by its input port.
pub(crate) struct Reader<T: Send> {
    pub(super) ch: Arc<Channel<T>>,
    latest: Option<LatestOut<T>>,
    /// Its place in a [`Ring`].
    end: End,
}

// An end that goes away ends its connection, so the other end lets go of it (a flag: no
// allocation, no lock on either side). A reader that goes away closes it: the writer lets
// go at its next write. A writer that goes away leaves what it wrote to be read: the reader
// lets go once it has taken it; the writer wakes an event port's component so that happens
// at once rather than at its next wake-up.
impl<T: Send> Drop for Writer<T> {
    fn drop(&mut self) {
        if !self.ch.writer_gone.swap(true, Ordering::AcqRel) {
            self.ch.in_changed.store(true, Ordering::Release);
            if let Some(w) = &self.ch.waker {
                w.wake();
            }
        }
    }
}

impl<T: Send> Drop for Reader<T> {
    fn drop(&mut self) {
        self.ch.close();
    }
}

/// The output end's side of a new connection: its port's name and "look" flag, and its
/// register when its samples are one word.
pub(super) struct From {
    pub(super) name: Arc<str>,
    pub(super) changed: Flag,
    pub(super) word: Option<Arc<WordCell>>,
}

/// The input end's side of a new connection: its port's name and "look" flag, the waker
/// of an event port, and whether its samples are stamped.
pub(super) struct To {
    pub(super) name: Arc<str>,
    pub(super) changed: Flag,
    pub(super) waker: Option<Arc<dyn Waker>>,
    pub(super) stamped: bool,
}

/// Makes a connection and its two ends. A data connection from a port with a register
/// reads that register; with `init` it starts with the value last written, if any. A
/// stamped buffer connection stamps each sample with the time it was written.
pub(super) fn channel<T: Clone + Send + 'static>(
    from: From,
    to: To,
    policy: ConnPolicy,
    sample: &T,
) -> (Writer<T>, Reader<T>) {
    let To {
        name: to,
        changed: in_changed,
        waker,
        stamped,
    } = to;
    let From {
        name: from,
        changed: out_changed,
        word,
    } = from;
    let mut shared = None;
    let (queues, halves) = match (policy.kind, word) {
        (ConnKind::Data, Some(cell)) => {
            let base = cell.version();
            let init = u64::from(policy.init && base > 0);
            // With `init` the version before the latest: the reader takes the latest as new.
            let seen = base - init;
            let out = LatestOut::Word {
                cell: cell.clone(),
                seen,
            };
            shared = Some(SharedWord { cell, base, init });
            (None, Some((None, out)))
        }
        (ConnKind::Data, None) => {
            let (i, o) = latest(sample);
            (None, Some((Some(i), o)))
        }
        (ConnKind::Buffer { size }, _) => (Some(Fifo::Newest(Ring::new(size, sample))), None),
        (ConnKind::CircularBuffer { size }, _) => {
            let capacity = size.max(1);
            // Room for a full queue, the sample the writer fills and the one the reader
            // empties.
            let pool = capacity + 2;
            let free = ArrayQueue::new(pool);
            for _ in 0..pool {
                let _ = free.push(Slot {
                    at: 0,
                    value: sample.clone(),
                });
            }
            let full = ArrayQueue::new(capacity);
            (Some(Fifo::Oldest(Queues { free, full })), None)
        }
    };
    let ch = Arc::new(Channel {
        id: NEXT_CONNECTION.fetch_add(1, Ordering::Relaxed),
        from,
        to,
        policy,
        queues,
        shared,
        closed: AtomicBool::new(false),
        writer_gone: AtomicBool::new(false),
        out_changed,
        in_changed,
        written: CachePadded::new(AtomicU64::new(0)),
        read: CachePadded::new(AtomicU64::new(0)),
        dropped: AtomicU64::new(0),
        waker,
        stamped,
    });
    let (input, output) = match halves {
        Some((i, o)) => (i, Some(o)),
        None => (None, None),
    };
    (
        Writer {
            ch: ch.clone(),
            latest: input,
            end: End::default(),
            tap: None,
        },
        Reader {
            ch,
            latest: output,
            end: End::default(),
        },
    )
}

/// The writing end of a tap of output `from` into `journal` as number `tap`, the journal's
/// reader named `to` (see [`super::journal`]): a stamped connection whose samples go to the
/// journal; it has no reading end (the [`Tap`](super::Tap) that holds it closes it).
pub(super) fn journal_tap<T: Send>(
    from: From,
    to: Arc<str>,
    journal: Arc<Journal>,
    tap: u32,
) -> Writer<T> {
    let policy = ConnPolicy::buffer(journal.capacity());
    let ch = Arc::new(Channel {
        id: NEXT_CONNECTION.fetch_add(1, Ordering::Relaxed),
        from: from.name,
        to,
        policy,
        queues: Some(Fifo::Journal(journal.clone())),
        shared: None,
        closed: AtomicBool::new(false),
        writer_gone: AtomicBool::new(false),
        out_changed: from.changed,
        in_changed: Arc::new(CachePadded::new(AtomicBool::new(false))),
        written: CachePadded::new(AtomicU64::new(0)),
        read: CachePadded::new(AtomicU64::new(0)),
        dropped: AtomicU64::new(0),
        waker: None,
        stamped: true,
    });
    Writer {
        ch,
        latest: None,
        end: End::default(),
        tap: Some((journal, tap)),
    }
}

/// What a [`Tap`](super::Tap) needs of its connection, whatever its sample type.
pub(super) trait TapEnd: Send + Sync {
    fn info(&self) -> ConnectionInfo;
    fn close(&self);
    /// The journal's reader took `n` of its entries: counted as written and read (the
    /// writer appends without touching the connection).
    fn taken(&self, n: u64);
    /// Keeps the connection until its writer has let go (see [`bury`]).
    fn bury(self: Arc<Self>);
}

impl<T: Send + 'static> TapEnd for Channel<T>
where
    Channel<T>: Send + Sync,
{
    fn info(&self) -> ConnectionInfo {
        Channel::info(self)
    }
    fn close(&self) {
        Channel::close(self);
    }
    fn taken(&self, n: u64) {
        self.written.fetch_add(n, Ordering::Relaxed);
        self.read.fetch_add(n, Ordering::Relaxed);
    }
    fn bury(self: Arc<Self>) {
        bury(self);
    }
}

impl<T: Clone + Send + 'static> Writer<T> {
    /// True when the connection reads its output port's register: nothing to copy.
    pub(super) fn reads_register(&self) -> bool {
        self.ch.shared.is_some()
    }

    /// True when the port must call [`push`](Self::push) at each write: the connection
    /// keeps its own copy of the value, or it wakes an event port.
    pub(super) fn needs_push(&self) -> bool {
        !self.reads_register() || self.ch.waker.is_some()
    }

    /// Writer side, after the port's own register was written. Wait-free for data,
    /// lock-free for buffers; allocation-free when `clone_from` is.
    #[inline]
    pub(super) fn push(&mut self, value: &T) {
        if let Some((journal, tap)) = &self.tap {
            // Counted by the journal's reader as it takes them (see `TapEnd::taken`).
            let at = crate::activity::stamp_now();
            if !journal.append(*tap, at, super::word::to_word(value)) {
                bump(&self.ch.dropped);
            }
            return;
        }
        if let Some(input) = &mut self.latest {
            // An unread value replaced is what a data connection is for: not a drop.
            input.publish(value);
        } else if self.ch.shared.is_some() {
            // The port's register holds it, and counts it.
            if let Some(w) = &self.ch.waker {
                w.wake();
            }
            return;
        } else if !self.push_buffered(value) {
            return;
        }
        let ch = &*self.ch;
        bump(&ch.written);
        if let Some(w) = &ch.waker {
            w.wake();
        }
    }

    /// A buffer connection's write (kept out of the data connections' path); false when
    /// the sample was dropped (counted).
    #[inline(never)]
    fn push_buffered(&mut self, value: &T) -> bool {
        let ch = &*self.ch;
        let at = if ch.stamped {
            crate::activity::stamp_now()
        } else {
            0
        };
        let q = match &ch.queues {
            // Appended in `push`, never here.
            Some(Fifo::Journal(_)) => return false,
            Some(Fifo::Newest(ring)) => {
                if !ring.push(&mut self.end, value, at) {
                    bump(&ch.dropped);
                    return false;
                }
                return true;
            }
            Some(Fifo::Oldest(q)) => q,
            None => return false,
        };
        // The pool is sized so a free sample always exists for the single writer.
        let Some(mut slot) = q.free.pop() else {
            bump(&ch.dropped);
            return false;
        };
        slot.value.clone_from(value);
        slot.at = at;
        if let Err(slot) = q.full.push(slot) {
            // Make room by dropping the oldest; only this writer pushes, so room stays.
            if let Some(old) = q.full.pop() {
                let _ = q.free.push(old);
                bump(&ch.dropped);
            }
            if let Err(slot) = q.full.push(slot) {
                let _ = q.free.push(slot);
                bump(&ch.dropped);
                return false;
            }
        }
        true
    }
}

impl<T: Clone + Send + 'static> Reader<T> {
    /// The output port's register and the version last taken, for a data connection that
    /// reads it (see [`set_seen`](Self::set_seen)).
    pub(super) fn register(&self) -> Option<(&Arc<WordCell>, u64)> {
        match &self.latest {
            Some(LatestOut::Word { cell, seen }) if self.ch.shared.is_some() => Some((cell, *seen)),
            _ => None,
        }
    }

    /// The version last taken from the register, when its port took values without this
    /// end (its direct path) and hands the end back.
    pub(super) fn set_seen(&mut self, version: u64) {
        if let Some(LatestOut::Word { seen, .. }) = &mut self.latest {
            *seen = version;
        }
    }

    /// True when its writer is gone but what it wrote is not all taken yet.
    pub(super) fn lingers(&self) -> bool {
        self.ch.writer_gone.load(Ordering::Acquire) && !self.is_done()
    }

    /// True when nothing more will come: closed, or the writer gone and all it wrote taken.
    #[inline]
    pub(super) fn is_done(&self) -> bool {
        let ch = &*self.ch;
        if ch.is_closed() {
            return true;
        }
        if !ch.writer_gone.load(Ordering::Acquire) {
            return false;
        }
        match (&self.latest, &ch.queues) {
            (Some(out), _) => !out.has_new(),
            (None, Some(Fifo::Newest(ring))) => ring.is_empty(),
            (None, Some(Fifo::Oldest(q))) => q.full.is_empty(),
            (None, Some(Fifo::Journal(_))) => true,
            (None, None) => true,
        }
    }

    /// Reader side: copies the next sample into `into`, if there is one, and the time it
    /// was written into `at` (a stamped buffer connection; else `at` is left alone).
    #[inline]
    pub(super) fn pop_into(&mut self, into: &mut T, at: &mut u64) -> bool {
        let got = match &mut self.latest {
            Some(output) => output.take(into),
            None => self.pop_buffered(into, at),
        };
        if got {
            bump(&self.ch.read);
        }
        got
    }

    /// A buffer connection's read (kept out of the data connections' path).
    #[inline(never)]
    fn pop_buffered(&mut self, into: &mut T, at: &mut u64) -> bool {
        let q = match &self.ch.queues {
            Some(Fifo::Journal(_)) => return false,
            Some(Fifo::Newest(ring)) => {
                let Some(stamp) = ring.pop(&mut self.end, into) else {
                    return false;
                };
                if self.ch.stamped {
                    *at = stamp;
                }
                return true;
            }
            Some(Fifo::Oldest(q)) => q,
            None => return false,
        };
        match q.full.pop() {
            Some(slot) => {
                into.clone_from(&slot.value);
                if self.ch.stamped {
                    *at = slot.at;
                }
                let _ = q.free.push(slot);
                true
            }
            None => false,
        }
    }
}

/// Connections whose reading end a non-real-time reader let go of: each is kept here until
/// its writer, perhaps a real-time component, has let go too, and freed by a later
/// [`bury`] — so the writer's thread never frees a connection's samples.
static GRAVEYARD: Mutex<Vec<Arc<dyn Send + Sync>>> = Mutex::new(Vec::new());

/// Keeps `ch` until its other end has let go (see [`GRAVEYARD`]), and frees those whose
/// ends have both gone. Locks: not for real-time threads.
pub(super) fn bury(ch: Arc<dyn Send + Sync>) {
    let mut g = lock(&GRAVEYARD);
    g.retain(|c| Arc::strong_count(c) > 1);
    g.push(ch);
}

/// How many connections may wait for a port's owner to take them up.
const PENDING: usize = 64;

/// Connections of one port, as seen from other threads: new ends wait in `pending` until
/// the owner's next read or write takes them; `all` lists the connections.
pub(super) struct Links<E, T> {
    pending: ArrayQueue<E>,
    /// Set when an end is put in `pending` and when one of the port's connections closes
    /// or loses an end: the owner's fast path looks at this flag only.
    pub(super) changed: Flag,
    all: Mutex<Vec<Weak<Channel<T>>>>,
}

impl<E, T> Links<E, T> {
    pub(super) fn new() -> Self {
        Links {
            pending: ArrayQueue::new(PENDING),
            changed: Arc::new(CachePadded::new(AtomicBool::new(false))),
            all: Mutex::new(Vec::new()),
        }
    }

    pub(super) fn offer(
        &self,
        port: &str,
        ch: &Arc<Channel<T>>,
        end: E,
        channel: impl Fn(&E) -> &Channel<T>,
    ) -> Result<(), ConnectError> {
        let end = match self.pending.push(end) {
            Ok(()) => None,
            Err(end) => {
                // Full of ends the owner has not taken up: let go of those already closed
                // (their other end went away), then try once more.
                for _ in 0..self.pending.len() {
                    if let Some(e) = self.pending.pop()
                        && !channel(&e).is_finished()
                    {
                        let _ = self.pending.push(e);
                    }
                }
                self.pending.push(end).err()
            }
        };
        if end.is_some() {
            return Err(ConnectError::TooManyPending {
                port: port.to_string(),
                limit: PENDING,
            });
        }
        self.changed.store(true, Ordering::Release);
        let mut all = lock(&self.all);
        all.retain(|w| w.strong_count() > 0);
        all.push(Arc::downgrade(ch));
        Ok(())
    }

    fn live(&self) -> Vec<Arc<Channel<T>>> {
        lock(&self.all)
            .iter()
            .filter_map(Weak::upgrade)
            .filter(|c| !c.is_finished())
            .collect()
    }

    pub(super) fn info(&self) -> Vec<ConnectionInfo> {
        self.live().iter().map(|c| c.info()).collect()
    }

    pub(super) fn disconnect(&self, id: Option<u64>) -> usize {
        let mut n = 0;
        for c in self.live() {
            if id.is_none_or(|id| c.id == id) {
                c.close();
                n += 1;
            }
        }
        n
    }

    /// Owner side, once its copy of [`changed`](Self::changed) was found set (the common
    /// case, nothing changed, is that one load): takes up pending ends and forgets the
    /// ends `done` says are done. An end `lingers` says will be done later (its writer
    /// gone, what it wrote not all taken yet) sets the flag again, so the owner looks once
    /// more after its next read rather than keep the end for ever.
    #[cold]
    pub(super) fn refresh_changed(
        &self,
        local: &mut Vec<E>,
        done: impl Fn(&E) -> bool,
        lingers: impl Fn(&E) -> bool,
    ) {
        // Cleared before anything is looked at (a full barrier): a change after the look
        // sets it again.
        if !self.changed.swap(false, Ordering::AcqRel) {
            return;
        }
        while let Some(end) = self.pending.pop() {
            // Capacity is reserved when the port is made; beyond it this allocates once,
            // when a connection is taken up.
            local.push(end);
        }
        local.retain(|e| !done(e));
        if local.iter().any(lingers) {
            self.changed.store(true, Ordering::Release);
        }
    }
}

/// How many connections a port holds before taking up one more allocates.
pub(super) const RESERVED_CONNECTIONS: usize = 8;
