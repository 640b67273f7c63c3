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
//! Every buffer connection owns a fixed pool of pre-allocated samples (copies of the
//! port's data sample): a `buffer` keeps them in a single-writer single-reader ring, a
//! `circular_buffer` moves them between two lock-free queues (its writer takes the oldest
//! back when full); `write` copies into a sample with `clone_from` and `read` copies out
//! the same way. So writing and reading never lock, and
//! never allocate as long as `clone_from` does not — true for plain data, and for a `Vec`
//! or `String` no longer than the data sample given with
//! [`OutputPort::with_sample`]/[`InputPort::with_sample`]. A recording taps one-word
//! ports into a [`journal`] instead: one pre-allocated ring per component that a write
//! appends an entry to.
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

mod channel;
mod input;
pub mod journal;
mod latest;
mod output;
mod ring;
pub mod word;

pub use input::InputPort;
pub(crate) use input::InputShared;
pub use output::OutputPort;
pub(crate) use output::OutputShared;

use channel::channel;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

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
    /// A stamped connection asked with a data policy.
    #[error("a stamped connection needs a buffer or circular_buffer policy, not data")]
    NotBuffered,
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
    /// A journal tap asked of a port whose samples are not one word.
    #[error(
        "port {port:?} carries {type_name}: only one-word samples (numbers, bool, char) go into a journal"
    )]
    NotOneWord {
        /// The port.
        port: String,
        /// Its type.
        type_name: String,
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

/// Connects `output` to `input` with `policy`. Callable from any thread, at any time; the
/// ports take the connection up at their next write or read.
pub fn connect<T: Clone + Send + 'static>(
    output: &OutputPort<T>,
    input: &InputPort<T>,
    policy: ConnPolicy,
) -> Result<ConnectionInfo, ConnectError> {
    connect_shared(output.shared(), input.shared(), policy)
}

/// Connects `output` to `input` with a buffer `policy` whose samples carry the time they
/// were written, [`InputPort::read_at`] gives it back: the start of the activity step that
/// wrote it, or the monotonic clock's time of the write when no step was under way (see
/// [`crate::activity::stamp_now`]). A data policy is refused
/// ([`ConnectError::NotBuffered`]): a stamp belongs to a sample kept for the reader.
pub fn connect_stamped<T: Clone + Send + 'static>(
    output: &OutputPort<T>,
    input: &InputPort<T>,
    policy: ConnPolicy,
) -> Result<ConnectionInfo, ConnectError> {
    connect_with(output.shared(), input.shared(), policy, true)
}

pub(crate) fn connect_shared<T: Clone + Send + 'static>(
    out: &Arc<OutputShared<T>>,
    inp: &Arc<InputShared<T>>,
    policy: ConnPolicy,
) -> Result<ConnectionInfo, ConnectError> {
    connect_with(out, inp, policy, false)
}

pub(crate) fn connect_with<T: Clone + Send + 'static>(
    out: &Arc<OutputShared<T>>,
    inp: &Arc<InputShared<T>>,
    policy: ConnPolicy,
    stamped: bool,
) -> Result<ConnectionInfo, ConnectError> {
    if stamped && policy.kind == ConnKind::Data {
        return Err(ConnectError::NotBuffered);
    }
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
    let from = channel::From {
        name: out.name.clone(),
        changed: out.links.changed.clone(),
        word: out.word.clone(),
    };
    let to = channel::To {
        name: inp.name.clone(),
        changed: inp.links.changed.clone(),
        waker: inp.waker.get().cloned(),
        stamped,
    };
    let (mut writer, reader) = channel(from, to, policy, &sample);
    let ch = writer.ch.clone();
    if policy.init
        && !writer.reads_register()
        && let Some(v) = out.last_written()
    {
        // Before either end is handed over, so this thread is the only writer.
        writer.push(&v);
    }
    inp.links.offer(&inp.name, &ch, reader, |r| &r.ch)?;
    if let Err(e) = out.links.offer(&out.name, &ch, writer, |w| &w.ch) {
        ch.close();
        return Err(e);
    }
    Ok(ch.info())
}

#[cfg(test)]
mod tests;
