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
    fn data_connections_of_one_word_share_the_ports_register() {
        let mut out = OutputPort::<f64>::new("out");
        out.write(&1.0);
        let mut plain = InputPort::<f64>::new("plain");
        let mut init = InputPort::<f64>::new("init");
        connect(&out, &plain, ConnPolicy::data()).unwrap();
        connect(&out, &init, ConnPolicy::data().with_init(true)).unwrap();
        let mut x = 0.0;
        assert_eq!(plain.read(&mut x), FlowStatus::NoData, "written before it");
        assert_eq!((init.read(&mut x), x), (FlowStatus::NewData, 1.0));
        for v in [2.0, 3.0] {
            out.write(&v);
        }
        assert_eq!(out.conns.len(), 2);
        assert!(!out.push, "nothing to do per write for register readers");
        for inp in [&mut plain, &mut init] {
            assert_eq!((inp.read(&mut x), x), (FlowStatus::NewData, 3.0));
            assert_eq!((inp.read(&mut x), x), (FlowStatus::OldData, 3.0));
        }
        let counts: Vec<(u64, u64)> = out
            .connections()
            .iter()
            .map(|c| (c.written, c.read))
            .collect();
        assert_eq!(
            counts,
            vec![(2, 1), (3, 2)],
            "written since connected, + init"
        );
        assert_eq!(out.last_written(), Some(3.0));
        // A buffer beside them gets every write; the register readers the latest.
        let mut buffered = InputPort::<f64>::new("buffered");
        connect(&out, &buffered, ConnPolicy::buffer(4)).unwrap();
        out.write(&4.0);
        out.write(&5.0);
        assert!(out.push);
        let mut got = Vec::new();
        while buffered.read(&mut x) == FlowStatus::NewData {
            got.push(x);
        }
        assert_eq!(got, vec![4.0, 5.0]);
        assert_eq!((plain.read(&mut x), x), (FlowStatus::NewData, 5.0));
        drop(buffered);
        out.write(&6.0);
        assert!(!out.push, "the buffer's end let go");
        assert_eq!(init.disconnect(None), 1);
        out.write(&7.0);
        assert_eq!((init.read(&mut x), x), (FlowStatus::OldData, 3.0));
        assert_eq!((plain.read(&mut x), x), (FlowStatus::NewData, 7.0));
        drop(out);
        assert_eq!(plain.read(&mut x), FlowStatus::OldData);
        assert!(plain.conns.is_empty(), "writer gone, all taken: let go");
    }

    #[test]
    fn a_reader_lets_go_once_it_took_what_a_gone_writer_left() {
        for policy in [ConnPolicy::data(), ConnPolicy::buffer(4)] {
            let (mut out, mut inp) = pair::<f64>(policy);
            out.write(&1.0);
            out.write(&2.0);
            drop(out);
            let mut x = 0.0;
            assert_eq!(inp.read(&mut x), FlowStatus::NewData, "{policy:?}");
            while inp.read(&mut x) == FlowStatus::NewData {}
            assert_eq!((inp.read(&mut x), x), (FlowStatus::OldData, 2.0));
            assert!(
                inp.conns.is_empty(),
                "{policy:?}: still holds the connection"
            );
        }
    }

    #[test]
    fn an_event_port_is_woken_by_each_write_of_a_data_connection() {
        struct Count(std::sync::atomic::AtomicU64);
        impl crate::activity::Waker for Count {
            fn wake(&self) {
                self.0.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
        }
        let count = Arc::new(Count(std::sync::atomic::AtomicU64::new(0)));
        let mut out = OutputPort::<f64>::new("out");
        let mut inp = InputPort::<f64>::new("in");
        let _ = inp.shared().waker.set(count.clone());
        connect(&out, &inp, ConnPolicy::data()).unwrap();
        for v in 0..3 {
            out.write(&f64::from(v));
        }
        assert!(out.push, "an event port's end is woken at each write");
        assert_eq!(count.0.load(std::sync::atomic::Ordering::Relaxed), 3);
        let mut x = 0.0;
        assert_eq!((inp.read(&mut x), x), (FlowStatus::NewData, 2.0));
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

    /// A data connection across two threads, for a one-word type (the word register) and
    /// for a wider one (the triple buffer): every new value read is one that was written,
    /// in order, never torn, never the same write twice; the last one arrives.
    fn data_across_threads<T: Clone + Send + Default + PartialEq + std::fmt::Debug + 'static>(
        make: fn(u64) -> T,
        key: fn(&T) -> u64,
    ) {
        let (mut out, mut inp) = pair::<T>(ConnPolicy::data());
        let n = 50_000u64;
        let writer = std::thread::spawn(move || {
            for v in 1..=n {
                out.write(&make(v));
            }
            out
        });
        let mut x = T::default();
        let mut last = 0;
        let mut news = 0u64;
        while last < n {
            if inp.read(&mut x) == FlowStatus::NewData {
                let k = key(&x);
                assert_eq!(x, make(k), "a torn sample: {x:?}");
                assert!(k > last, "{k} after {last}: not newer");
                last = k;
                news += 1;
            }
        }
        let _out = writer.join().unwrap();
        assert_eq!(
            inp.read(&mut x),
            FlowStatus::OldData,
            "nothing after the last"
        );
        assert!(news >= 1 && news <= n);
    }

    #[test]
    fn data_connections_across_two_threads_are_whole_and_in_order() {
        data_across_threads::<u64>(|v| v, |x| *x);
        data_across_threads::<f64>(|v| v as f64 * 0.5, |x| (*x * 2.0) as u64);
        data_across_threads::<[u64; 8]>(|v| [v; 8], |x| x[0]);
    }
}
