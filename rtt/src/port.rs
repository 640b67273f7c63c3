//! Data-flow ports: `OutputPort<T>` writes, `InputPort<T>` reads, connections carry samples.
//!
//! As in RTT 2.x, `write()` never blocks and does not care whether anyone listens;
//! `read()` says whether it got [`NewData`](FlowStatus::NewData), the last sample again
//! ([`OldData`](FlowStatus::OldData)), or nothing yet ([`NoData`](FlowStatus::NoData)). How
//! samples travel is fixed per connection by a [`ConnPolicy`]: the last value (`data`), a
//! FIFO that drops the newest sample when full (`buffer`), or one that drops the oldest
//! (`circular_buffer`); with `init`, a new connection starts with the last value written.
//!
//! One output may feed many inputs (fan-out) and one input may be fed by many outputs
//! (fan-in: `read` takes the first connection with new data). Connections are made and
//! broken at run time, from any thread.
//!
//! # Real-time behaviour
//!
//! Every connection owns a fixed pool of pre-allocated samples (copies of the port's data
//! sample) that move between two lock-free queues; `write` copies into a free sample with
//! `clone_from` and `read` copies out the same way. So writing and reading never lock, and
//! never allocate as long as `clone_from` does not — true for plain data, and for a `Vec`
//! or `String` no longer than the data sample given with
//! [`OutputPort::with_sample`]/[`InputPort::with_sample`].
//!
//! ```
//! use rtt::port::{connect, ConnPolicy, FlowStatus, InputPort, OutputPort};
//!
//! let mut out = OutputPort::<f64>::new("setpoint");
//! let mut inp = InputPort::<f64>::new("setpoint_in");
//! connect(&out, &inp, ConnPolicy::buffer(2))?;
//!
//! let mut x = 0.0;
//! assert_eq!(inp.read(&mut x), FlowStatus::NoData);
//! for v in [1.0, 2.0, 3.0] {
//!     out.write(&v); // the third is dropped: the buffer holds two
//! }
//! assert_eq!((inp.read(&mut x), x), (FlowStatus::NewData, 1.0));
//! assert_eq!((inp.read(&mut x), x), (FlowStatus::NewData, 2.0));
//! assert_eq!((inp.read(&mut x), x), (FlowStatus::OldData, 2.0));
//! # Ok::<(), rtt::port::ConnectError>(())
//! ```

use crate::activity::Waker;
use crate::lock::lock;
use crossbeam_queue::ArrayQueue;
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, Weak};

/// What a read found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FlowStatus {
    /// Nothing was ever received.
    NoData,
    /// No new sample; the sample is the last one received, again.
    OldData,
    /// A sample not read before.
    NewData,
}

/// How a connection carries samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum ConnKind {
    /// The last value: a new sample replaces an unread one.
    Data,
    /// A FIFO of `size` samples; when full, the newest sample is dropped (and counted).
    Buffer {
        /// Capacity in samples (at least 1).
        size: usize,
    },
    /// A FIFO of `size` samples; when full, the oldest sample is dropped (and counted).
    CircularBuffer {
        /// Capacity in samples (at least 1).
        size: usize,
    },
}

/// A connection policy: the kind of connection and whether it starts with the last value.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct ConnPolicy {
    /// How samples are carried.
    pub kind: ConnKind,
    /// A new connection starts with the last value the output wrote, as new data.
    #[serde(default)]
    pub init: bool,
}

impl Default for ConnPolicy {
    fn default() -> Self {
        ConnPolicy::data()
    }
}

impl ConnPolicy {
    /// The last value.
    pub const fn data() -> Self {
        ConnPolicy {
            kind: ConnKind::Data,
            init: false,
        }
    }

    /// A FIFO of `size` samples that drops the newest when full.
    pub const fn buffer(size: usize) -> Self {
        ConnPolicy {
            kind: ConnKind::Buffer { size },
            init: false,
        }
    }

    /// A FIFO of `size` samples that drops the oldest when full.
    pub const fn circular_buffer(size: usize) -> Self {
        ConnPolicy {
            kind: ConnKind::CircularBuffer { size },
            init: false,
        }
    }

    /// The same policy, starting new connections with the last written value.
    pub const fn with_init(mut self, init: bool) -> Self {
        self.init = init;
        self
    }
}

/// Why two ports could not be connected.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ConnectError {
    /// The ports carry different types.
    #[error(
        "cannot connect {output:?} ({output_type}) to {input:?} ({input_type}): the types differ"
    )]
    TypeMismatch {
        /// Output port name.
        output: String,
        /// Its data type.
        output_type: String,
        /// Input port name.
        input: String,
        /// Its data type.
        input_type: String,
    },
    /// Both ports are outputs, or both inputs.
    #[error(
        "cannot connect {from:?} to {to:?}: a connection goes from an output port to an input port"
    )]
    Direction {
        /// The port given as the source.
        from: String,
        /// The port given as the destination.
        to: String,
    },
    /// A port had too many connections waiting for its owner to take them up.
    #[error(
        "port {port:?} has {limit} connections waiting for its component to take them up; is the component running?"
    )]
    TooManyPending {
        /// The port.
        port: String,
        /// The limit.
        limit: usize,
    },
    /// A buffer policy with a size of zero.
    #[error("a buffer connection needs a size of at least 1")]
    ZeroSize,
    /// A buffer policy larger than a connection may pre-allocate.
    #[error("a buffer connection of {size} samples is too large (at most {max})")]
    TooLarge {
        /// The size asked for.
        size: usize,
        /// The most a connection takes.
        max: usize,
    },
}

/// The most samples a buffer connection holds: each is allocated when it is made.
pub const MAX_BUFFER: usize = 1 << 20;

/// Counters of one connection.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ConnectionInfo {
    /// Unique id of the connection within the process.
    pub id: u64,
    /// The output port.
    pub from: String,
    /// The input port.
    pub to: String,
    /// Its policy.
    pub policy: ConnPolicy,
    /// Samples written into it.
    pub written: u64,
    /// Samples taken out by the reader.
    pub read: u64,
    /// Samples lost because a buffer was full.
    pub dropped: u64,
}

static NEXT_CONNECTION: AtomicU64 = AtomicU64::new(1);

/// Adds one to a counter only one thread writes: a plain load and store, no atomic
/// read-modify-write on the hot path.
fn bump(counter: &AtomicU64) {
    counter.store(
        counter.load(Ordering::Relaxed).wrapping_add(1),
        Ordering::Relaxed,
    );
}

/// What both ends of one connection share: its identity, state and counters. `written`
/// and `dropped` are only written by the writer, `read` only by the reader.
pub(crate) struct Channel<T> {
    id: u64,
    from: Arc<str>,
    to: Arc<str>,
    policy: ConnPolicy,
    /// The sample pool of a buffer connection; `None` for a data connection, whose triple
    /// buffer halves live in the two ends.
    queues: Option<Queues<T>>,
    /// Closed for good: disconnected, or its reader went away. Neither end uses it again.
    closed: AtomicBool,
    /// Its writer went away: the reader still takes what was written, then lets go.
    writer_gone: AtomicBool,
    written: AtomicU64,
    read: AtomicU64,
    dropped: AtomicU64,
    waker: Option<Arc<dyn Waker>>,
}

/// A buffer connection's samples, cycling between `free` and `full`.
struct Queues<T> {
    free: ArrayQueue<T>,
    full: ArrayQueue<T>,
}

impl<T> Channel<T> {
    fn is_closed(&self) -> bool {
        self.closed.load(Ordering::Acquire)
    }

    /// True when the connection carries nothing any more: closed, or its writer gone.
    fn is_finished(&self) -> bool {
        self.is_closed() || self.writer_gone.load(Ordering::Acquire)
    }

    fn info(&self) -> ConnectionInfo {
        ConnectionInfo {
            id: self.id,
            from: self.from.to_string(),
            to: self.to.to_string(),
            policy: self.policy,
            written: self.written.load(Ordering::Relaxed),
            read: self.read.load(Ordering::Relaxed),
            dropped: self.dropped.load(Ordering::Relaxed),
        }
    }
}

/// The writing end of one connection, owned by its output port.
pub(crate) struct Writer<T: Send> {
    ch: Arc<Channel<T>>,
    latest: Option<triple_buffer::Input<T>>,
}

/// The reading end of one connection, owned by its input port.
pub(crate) struct Reader<T: Send> {
    ch: Arc<Channel<T>>,
    latest: Option<triple_buffer::Output<T>>,
}

// An end that goes away ends its connection, so the other end lets go of it (a flag: no
// allocation, no lock on either side). A reader that goes away closes it: the writer lets
// go at its next write. A writer that goes away leaves what it wrote to be read: the reader
// lets go once it has taken it; the writer wakes an event port's component so that happens
// at once rather than at its next wake-up.
impl<T: Send> Drop for Writer<T> {
    fn drop(&mut self) {
        if !self.ch.writer_gone.swap(true, Ordering::AcqRel)
            && let Some(w) = &self.ch.waker
        {
            w.wake();
        }
    }
}

impl<T: Send> Drop for Reader<T> {
    fn drop(&mut self) {
        self.ch.closed.store(true, Ordering::Release);
    }
}

/// Makes a connection and its two ends.
fn channel<T: Clone + Send>(
    from: Arc<str>,
    to: Arc<str>,
    policy: ConnPolicy,
    sample: &T,
    waker: Option<Arc<dyn Waker>>,
) -> (Writer<T>, Reader<T>) {
    let (queues, halves) = match policy.kind {
        ConnKind::Data => (None, Some(triple_buffer::triple_buffer(sample))),
        ConnKind::Buffer { size } | ConnKind::CircularBuffer { size } => {
            let capacity = size.max(1);
            // Room for a full queue, the sample the writer fills and the one the reader
            // empties.
            let pool = capacity + 2;
            let free = ArrayQueue::new(pool);
            for _ in 0..pool {
                let _ = free.push(sample.clone());
            }
            let full = ArrayQueue::new(capacity);
            (Some(Queues { free, full }), None)
        }
    };
    let ch = Arc::new(Channel {
        id: NEXT_CONNECTION.fetch_add(1, Ordering::Relaxed),
        from,
        to,
        policy,
        queues,
        closed: AtomicBool::new(false),
        writer_gone: AtomicBool::new(false),
        written: AtomicU64::new(0),
        read: AtomicU64::new(0),
        dropped: AtomicU64::new(0),
        waker,
    });
    let (input, output) = match halves {
        Some((i, o)) => (Some(i), Some(o)),
        None => (None, None),
    };
    (
        Writer {
            ch: ch.clone(),
            latest: input,
        },
        Reader { ch, latest: output },
    )
}

impl<T: Clone + Send> Writer<T> {
    /// Writer side. Wait-free for data, lock-free for buffers; allocation-free when
    /// `clone_from` is.
    fn push(&mut self, value: &T) {
        let ch = &*self.ch;
        if let Some(input) = &mut self.latest {
            input.input_buffer_mut().clone_from(value);
            // An unread value replaced is what a data connection is for: not a drop.
            input.publish();
        } else if let Some(q) = &ch.queues {
            let drop_newest = matches!(ch.policy.kind, ConnKind::Buffer { .. });
            if drop_newest && q.full.is_full() {
                bump(&ch.dropped);
                return;
            }
            // The pool is sized so a free sample always exists for the single writer.
            let Some(mut slot) = q.free.pop() else {
                bump(&ch.dropped);
                return;
            };
            slot.clone_from(value);
            if let Err(slot) = q.full.push(slot) {
                if drop_newest {
                    let _ = q.free.push(slot);
                    bump(&ch.dropped);
                    return;
                }
                // Make room by dropping the oldest; only this writer pushes, so room stays.
                if let Some(old) = q.full.pop() {
                    let _ = q.free.push(old);
                    bump(&ch.dropped);
                }
                if let Err(slot) = q.full.push(slot) {
                    let _ = q.free.push(slot);
                    bump(&ch.dropped);
                    return;
                }
            }
        }
        bump(&ch.written);
        if let Some(w) = &ch.waker {
            w.wake();
        }
    }
}

impl<T: Clone + Send> Reader<T> {
    /// True when nothing more will come: closed, or the writer gone and all it wrote taken.
    fn is_done(&self) -> bool {
        let ch = &*self.ch;
        if ch.is_closed() {
            return true;
        }
        if !ch.writer_gone.load(Ordering::Acquire) {
            return false;
        }
        match (&self.latest, &ch.queues) {
            (Some(out), _) => !out.updated(),
            (None, Some(q)) => q.full.is_empty(),
            (None, None) => true,
        }
    }

    /// Reader side: copies the next sample into `into`, if there is one.
    fn pop_into(&mut self, into: &mut T) -> bool {
        let ch = &*self.ch;
        let got = if let Some(output) = &mut self.latest {
            if output.update() {
                into.clone_from(output.output_buffer());
                true
            } else {
                false
            }
        } else if let Some(q) = &ch.queues {
            match q.full.pop() {
                Some(slot) => {
                    into.clone_from(&slot);
                    let _ = q.free.push(slot);
                    true
                }
                None => false,
            }
        } else {
            false
        };
        if got {
            bump(&ch.read);
        }
        got
    }
}

/// How many connections may wait for a port's owner to take them up.
const PENDING: usize = 64;

/// Connections of one port, as seen from other threads: new ends wait in `pending` until
/// the owner's next read or write takes them; `all` lists the connections.
struct Links<E, T> {
    pending: ArrayQueue<E>,
    all: Mutex<Vec<Weak<Channel<T>>>>,
}

impl<E, T> Links<E, T> {
    fn new() -> Self {
        Links {
            pending: ArrayQueue::new(PENDING),
            all: Mutex::new(Vec::new()),
        }
    }

    fn offer(
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

    fn info(&self) -> Vec<ConnectionInfo> {
        self.live().iter().map(|c| c.info()).collect()
    }

    fn disconnect(&self, id: Option<u64>) -> usize {
        let mut n = 0;
        for c in self.live() {
            if id.is_none_or(|id| c.id == id) {
                c.closed.store(true, Ordering::Release);
                n += 1;
            }
        }
        n
    }

    /// Owner side: takes up pending ends and forgets the ends `done` says are done.
    fn refresh(&self, local: &mut Vec<E>, done: impl Fn(&E) -> bool) {
        if !self.pending.is_empty() {
            while let Some(end) = self.pending.pop() {
                // Capacity is reserved when the port is made; beyond it this allocates
                // once, when a connection is taken up.
                local.push(end);
            }
        }
        local.retain(|e| !done(e));
    }
}

/// How many connections a port holds before taking up one more allocates.
const RESERVED_CONNECTIONS: usize = 8;

pub(crate) struct OutputShared<T: Send> {
    pub(crate) name: Arc<str>,
    links: Links<Writer<T>, T>,
    sample: Mutex<T>,
    /// Set at the first write: the last value below is real.
    written: AtomicBool,
    /// The reading half of the last written value, for `init` and introspection.
    last: Mutex<triple_buffer::Output<T>>,
}

impl<T: Clone + Send> OutputShared<T> {
    /// A copy of the data sample new connections pre-allocate from.
    pub(crate) fn sample_clone(&self) -> T {
        lock(&self.sample).clone()
    }

    /// The last value written, if any. Not for real-time paths (locks, clones).
    pub(crate) fn last_written(&self) -> Option<T> {
        if !self.written.load(Ordering::Acquire) {
            return None;
        }
        let mut last = lock(&self.last);
        last.update();
        Some(last.output_buffer().clone())
    }

    pub(crate) fn connections(&self) -> Vec<ConnectionInfo> {
        self.links.info()
    }

    pub(crate) fn disconnect(&self, id: Option<u64>) -> usize {
        self.links.disconnect(id)
    }
}

/// The writing end of a data flow.
pub struct OutputPort<T: Send> {
    shared: Arc<OutputShared<T>>,
    conns: Vec<Writer<T>>,
    last: triple_buffer::Input<T>,
    written: bool,
}

impl<T: Clone + Send + 'static> OutputPort<T> {
    /// An output port named `name`, with `T::default()` as its data sample.
    pub fn new(name: &str) -> Self
    where
        T: Default,
    {
        Self::with_sample(name, T::default())
    }

    /// An output port named `name` whose connections pre-allocate copies of `sample`: size a
    /// `Vec` sample to the longest value written and writing never allocates.
    pub fn with_sample(name: &str, sample: T) -> Self {
        let (last_in, last_out) = triple_buffer::triple_buffer(&sample);
        OutputPort {
            shared: Arc::new(OutputShared {
                name: Arc::from(name),
                links: Links::new(),
                sample: Mutex::new(sample),
                written: AtomicBool::new(false),
                last: Mutex::new(last_out),
            }),
            conns: Vec::with_capacity(RESERVED_CONNECTIONS),
            last: last_in,
            written: false,
        }
    }

    /// Sends `value` to every connection. Never blocks; a full buffer drops and counts.
    pub fn write(&mut self, value: &T) {
        self.shared
            .links
            .refresh(&mut self.conns, |w| w.ch.is_closed());
        for c in &mut self.conns {
            c.push(value);
        }
        self.last.input_buffer_mut().clone_from(value);
        self.last.publish();
        if !self.written {
            self.written = true;
            self.shared.written.store(true, Ordering::Release);
        }
    }

    /// Replaces the data sample future connections pre-allocate from.
    pub fn set_data_sample(&self, sample: T) {
        *lock(&self.shared.sample) = sample;
    }

    /// The last value written, if any. Not for real-time paths (locks, clones).
    pub fn last_written(&self) -> Option<T> {
        self.shared.last_written()
    }

    /// The port's name.
    pub fn name(&self) -> &str {
        &self.shared.name
    }

    /// Live connections with their counters.
    pub fn connections(&self) -> Vec<ConnectionInfo> {
        self.shared.connections()
    }

    /// Closes connection `id` (or every connection with `None`); returns how many closed.
    pub fn disconnect(&self, id: Option<u64>) -> usize {
        self.shared.disconnect(id)
    }

    pub(crate) fn shared(&self) -> &Arc<OutputShared<T>> {
        &self.shared
    }
}

pub(crate) struct InputShared<T: Send> {
    pub(crate) name: Arc<str>,
    links: Links<Reader<T>, T>,
    /// Set when the port is an event port of a component: new data wakes its activity.
    pub(crate) waker: OnceLock<Arc<dyn Waker>>,
    /// Set at the first new sample read: the last read value below is real.
    received: AtomicBool,
    /// The reading half of the last sample the owner read, for introspection.
    last: Mutex<triple_buffer::Output<T>>,
}

impl<T: Clone + Send> InputShared<T> {
    /// The last new sample the port's owner read, if any. Not for real-time paths (locks,
    /// clones).
    pub(crate) fn last_read(&self) -> Option<T> {
        if !self.received.load(Ordering::Acquire) {
            return None;
        }
        let mut last = lock(&self.last);
        last.update();
        Some(last.output_buffer().clone())
    }

    pub(crate) fn connections(&self) -> Vec<ConnectionInfo> {
        self.links.info()
    }

    pub(crate) fn disconnect(&self, id: Option<u64>) -> usize {
        self.links.disconnect(id)
    }
}

/// The reading end of a data flow.
pub struct InputPort<T: Send> {
    shared: Arc<InputShared<T>>,
    conns: Vec<Reader<T>>,
    last: T,
    has_last: bool,
    /// Publishes each new sample for [`InputShared::last_read`].
    published: triple_buffer::Input<T>,
}

impl<T: Clone + Send + 'static> InputPort<T> {
    /// An input port named `name`, with `T::default()` as its sample.
    pub fn new(name: &str) -> Self
    where
        T: Default,
    {
        Self::with_sample(name, T::default())
    }

    /// An input port named `name` keeping its last sample in a copy of `sample`: size a `Vec`
    /// sample to the longest value read and reading never allocates.
    pub fn with_sample(name: &str, sample: T) -> Self {
        let (published, last) = triple_buffer::triple_buffer(&sample);
        InputPort {
            shared: Arc::new(InputShared {
                name: Arc::from(name),
                links: Links::new(),
                waker: OnceLock::new(),
                received: AtomicBool::new(false),
                last: Mutex::new(last),
            }),
            conns: Vec::with_capacity(RESERVED_CONNECTIONS),
            last: sample,
            has_last: false,
            published,
        }
    }

    /// Reads the next sample into `sample`: from the first connection that has new data
    /// ([`NewData`](FlowStatus::NewData)), else the last sample read again
    /// ([`OldData`](FlowStatus::OldData)), else [`NoData`](FlowStatus::NoData) and `sample`
    /// is left alone. Never blocks.
    pub fn read(&mut self, sample: &mut T) -> FlowStatus {
        self.shared.links.refresh(&mut self.conns, Reader::is_done);
        for c in &mut self.conns {
            if c.pop_into(&mut self.last) {
                sample.clone_from(&self.last);
                self.published.input_buffer_mut().clone_from(&self.last);
                self.published.publish();
                if !self.has_last {
                    self.has_last = true;
                    self.shared.received.store(true, Ordering::Release);
                }
                return FlowStatus::NewData;
            }
        }
        if self.has_last {
            sample.clone_from(&self.last);
            FlowStatus::OldData
        } else {
            FlowStatus::NoData
        }
    }

    /// The port's name.
    pub fn name(&self) -> &str {
        &self.shared.name
    }

    /// Live connections with their counters.
    pub fn connections(&self) -> Vec<ConnectionInfo> {
        self.shared.connections()
    }

    /// Closes connection `id` (or every connection with `None`); returns how many closed.
    /// The last sample read stays readable as old data.
    pub fn disconnect(&self, id: Option<u64>) -> usize {
        self.shared.disconnect(id)
    }

    pub(crate) fn shared(&self) -> &Arc<InputShared<T>> {
        &self.shared
    }
}

/// Connects `output` to `input` with `policy`. Callable from any thread, at any time; the
/// ports take the connection up at their next write or read.
pub fn connect<T: Clone + Send + 'static>(
    output: &OutputPort<T>,
    input: &InputPort<T>,
    policy: ConnPolicy,
) -> Result<ConnectionInfo, ConnectError> {
    connect_shared(output.shared(), input.shared(), policy)
}

pub(crate) fn connect_shared<T: Clone + Send + 'static>(
    out: &Arc<OutputShared<T>>,
    inp: &Arc<InputShared<T>>,
    policy: ConnPolicy,
) -> Result<ConnectionInfo, ConnectError> {
    if let ConnKind::Buffer { size } | ConnKind::CircularBuffer { size } = policy.kind {
        if size == 0 {
            return Err(ConnectError::ZeroSize);
        }
        if size > MAX_BUFFER {
            return Err(ConnectError::TooLarge {
                size,
                max: MAX_BUFFER,
            });
        }
    }
    let sample = out.sample_clone();
    let (mut writer, reader) = channel(
        out.name.clone(),
        inp.name.clone(),
        policy,
        &sample,
        inp.waker.get().cloned(),
    );
    let ch = writer.ch.clone();
    if policy.init
        && let Some(v) = out.last_written()
    {
        // Before either end is handed over, so this thread is the only writer.
        writer.push(&v);
    }
    inp.links.offer(&inp.name, &ch, reader, |r| &r.ch)?;
    if let Err(e) = out.links.offer(&out.name, &ch, writer, |w| &w.ch) {
        ch.closed.store(true, Ordering::Release);
        return Err(e);
    }
    Ok(ch.info())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pair<T: Clone + Send + Default + 'static>(
        policy: ConnPolicy,
    ) -> (OutputPort<T>, InputPort<T>) {
        let out = OutputPort::new("out");
        let inp = InputPort::new("in");
        connect(&out, &inp, policy).unwrap();
        (out, inp)
    }

    fn drain(inp: &mut InputPort<i32>) -> Vec<i32> {
        let mut v = Vec::new();
        let mut x = 0;
        while inp.read(&mut x) == FlowStatus::NewData {
            v.push(x);
        }
        v
    }

    #[test]
    fn data_keeps_the_last_value() {
        let (mut out, mut inp) = pair::<i32>(ConnPolicy::data());
        let mut x = -1;
        assert_eq!(inp.read(&mut x), FlowStatus::NoData);
        assert_eq!(x, -1, "NoData leaves the sample alone");
        for v in 1..=5 {
            out.write(&v);
        }
        assert_eq!((inp.read(&mut x), x), (FlowStatus::NewData, 5));
        assert_eq!((inp.read(&mut x), x), (FlowStatus::OldData, 5));
        assert_eq!(
            out.connections()[0].dropped,
            0,
            "data connections overwrite, they do not drop"
        );
    }

    #[test]
    fn buffer_drops_newest_and_counts() {
        let (mut out, mut inp) = pair::<i32>(ConnPolicy::buffer(3));
        for v in 1..=5 {
            out.write(&v);
        }
        assert_eq!(drain(&mut inp), vec![1, 2, 3]);
        let info = &inp.connections()[0];
        assert_eq!((info.written, info.read, info.dropped), (3, 3, 2));
    }

    #[test]
    fn circular_buffer_drops_oldest_and_counts() {
        let (mut out, mut inp) = pair::<i32>(ConnPolicy::circular_buffer(3));
        for v in 1..=5 {
            out.write(&v);
        }
        assert_eq!(drain(&mut inp), vec![3, 4, 5]);
        assert_eq!(out.connections()[0].dropped, 2);
        out.write(&6);
        assert_eq!(drain(&mut inp), vec![6]);
    }

    #[test]
    fn init_hands_a_new_reader_the_last_value() {
        let mut out = OutputPort::<i32>::new("out");
        out.write(&41);
        out.write(&42);
        let mut late = InputPort::new("late");
        connect(&out, &late, ConnPolicy::data().with_init(true)).unwrap();
        let mut x = 0;
        assert_eq!((late.read(&mut x), x), (FlowStatus::NewData, 42));
        let mut plain = InputPort::new("plain");
        connect(&out, &plain, ConnPolicy::buffer(4)).unwrap();
        assert_eq!(
            plain.read(&mut x),
            FlowStatus::NoData,
            "without init a new reader has nothing"
        );
        let mut buffered = InputPort::new("buffered");
        connect(&out, &buffered, ConnPolicy::buffer(4).with_init(true)).unwrap();
        assert_eq!(drain(&mut buffered), vec![42]);
    }

    #[test]
    fn fan_out_and_fan_in() {
        let (mut a, mut b) = (OutputPort::<i32>::new("a"), OutputPort::<i32>::new("b"));
        let (mut i1, mut i2) = (InputPort::<i32>::new("i1"), InputPort::<i32>::new("i2"));
        connect(&a, &i1, ConnPolicy::buffer(8)).unwrap();
        connect(&a, &i2, ConnPolicy::buffer(8)).unwrap();
        connect(&b, &i1, ConnPolicy::buffer(8)).unwrap();
        a.write(&1);
        b.write(&10);
        a.write(&2);
        let mut got = drain(&mut i1);
        got.sort();
        assert_eq!(got, vec![1, 2, 10]);
        assert_eq!(drain(&mut i2), vec![1, 2]);
    }

    #[test]
    fn an_end_that_goes_away_closes_its_connection() {
        let mut out = OutputPort::<i32>::new("out");
        let readers: Vec<InputPort<i32>> = (0..50)
            .map(|i| {
                let inp = InputPort::new(&format!("in{i}"));
                connect(&out, &inp, ConnPolicy::buffer(4)).unwrap();
                inp
            })
            .collect();
        out.write(&1);
        assert_eq!(out.connections().len(), 50);
        drop(readers);
        assert!(
            out.connections().is_empty(),
            "closed connections are not listed"
        );
        out.write(&2);
        assert!(
            out.conns.is_empty(),
            "the writer let go of every closed connection"
        );

        let mut inp = InputPort::<i32>::new("in");
        for _ in 0..10 {
            let w = OutputPort::<i32>::new("w");
            connect(&w, &inp, ConnPolicy::data()).unwrap();
            drop(w);
        }
        let mut x = 0;
        assert_eq!(inp.read(&mut x), FlowStatus::NoData);
        assert!(
            inp.conns.is_empty(),
            "the reader let go of every closed connection"
        );
    }

    #[test]
    fn disconnect_at_run_time() {
        let (mut out, mut inp) = pair::<i32>(ConnPolicy::buffer(4));
        out.write(&1);
        assert_eq!(out.disconnect(None), 1);
        out.write(&2);
        let mut x = 0;
        assert_eq!(
            inp.read(&mut x),
            FlowStatus::NoData,
            "a closed connection delivers nothing"
        );
        assert!(inp.connections().is_empty());
        connect(&out, &inp, ConnPolicy::data()).unwrap();
        out.write(&3);
        assert_eq!((inp.read(&mut x), x), (FlowStatus::NewData, 3));
    }

    #[test]
    fn zero_size_buffers_are_refused() {
        let out = OutputPort::<i32>::new("o");
        let inp = InputPort::<i32>::new("i");
        assert_eq!(
            connect(&out, &inp, ConnPolicy::buffer(0)).unwrap_err(),
            ConnectError::ZeroSize
        );
    }

    #[test]
    fn writer_and_reader_on_two_threads_lose_nothing_in_order() {
        let (mut out, mut inp) = pair::<u64>(ConnPolicy::buffer(64));
        let n = 50_000u64;
        let writer = std::thread::spawn(move || {
            let mut v = 0;
            while v < n {
                // Only write when there is room, to test order, not dropping.
                if out.connections()[0].written - out.connections()[0].read < 60 {
                    out.write(&v);
                    v += 1;
                } else {
                    std::thread::yield_now();
                }
            }
            out
        });
        let mut expect = 0;
        let mut x = 0;
        while expect < n {
            if inp.read(&mut x) == FlowStatus::NewData {
                assert_eq!(x, expect);
                expect += 1;
            }
        }
        let out = writer.join().unwrap();
        assert_eq!(out.connections()[0].dropped, 0);
    }
}
