//! The reading end of a data flow: [`InputPort`], and what other threads see of it (its
//! connections, the last sample its owner read, the waker of an event port).

use super::channel::{Channel, Links, RESERVED_CONNECTIONS, Reader};
use super::latest::{LatestIn, LatestOut, snapshot};
use super::word::{Found, WordCell, from_word};
use super::{ConnectionInfo, FlowStatus};
use crate::activity::Waker;
use crossbeam_utils::CachePadded;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};

/// What other threads see of an input port.
pub(crate) struct InputShared<T: Send> {
    pub(crate) name: Arc<str>,
    pub(super) links: Links<Reader<T>, T>,
    /// Set when the port is an event port of a component: new data wakes its activity.
    pub(crate) waker: OnceLock<Arc<dyn Waker>>,
    /// Set at the first new sample read: the last read value below is real.
    received: AtomicBool,
    /// The reading half of the last sample the owner read, for introspection, and the last
    /// value taken from it.
    last: Mutex<(LatestOut<T>, T)>,
}

impl<T: Clone + Send + 'static> InputShared<T> {
    /// The last new sample the port's owner read, if any. Not for real-time paths (locks,
    /// clones).
    pub(crate) fn last_read(&self) -> Option<T> {
        if !self.received.load(Ordering::Acquire) {
            return None;
        }
        let mut last = crate::lock::lock(&self.last);
        let (out, value) = &mut *last;
        out.take(value);
        Some(value.clone())
    }

    pub(crate) fn connections(&self) -> Vec<ConnectionInfo> {
        self.links.info()
    }

    pub(crate) fn disconnect(&self, id: Option<u64>) -> usize {
        self.links.disconnect(id)
    }
}

/// The port's only connection when it reads its output port's one-word register: what a
/// read needs of it, one pointer away, so a read is the register's protocol and a few
/// stores — no walk of the connections, no match on how each carries its samples. Its
/// version last taken is handed back to the connection's end whenever the port's
/// connections change (before anything looks at that end).
pub(super) struct Direct<T> {
    cell: Arc<WordCell>,
    /// The register's version last taken.
    seen: u64,
    /// The connection, for its read counter.
    ch: Arc<Channel<T>>,
    /// The port's last read value for introspection (its [`LatestIn::Plain`] word).
    published: Arc<CachePadded<AtomicU64>>,
}

/// The reading end of a data flow.
pub struct InputPort<T: Send> {
    shared: Arc<InputShared<T>>,
    /// The port's "look at your connections" flag (a pointer away, not three).
    changed: super::channel::Flag,
    pub(super) conns: Vec<Reader<T>>,
    last: T,
    has_last: bool,
    /// Publishes each new sample for [`InputShared::last_read`].
    published: LatestIn<T>,
    /// Set while the port's only connection reads a one-word register.
    pub(super) direct: Option<Direct<T>>,
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
        let (published, last) = snapshot(&sample);
        let links = Links::new();
        InputPort {
            changed: links.changed.clone(),
            shared: Arc::new(InputShared {
                name: Arc::from(name),
                links,
                waker: OnceLock::new(),
                received: AtomicBool::new(false),
                last: Mutex::new((last, sample.clone())),
            }),
            conns: Vec::with_capacity(RESERVED_CONNECTIONS),
            last: sample,
            has_last: false,
            published,
            direct: None,
        }
    }

    /// Reads the next sample into `sample`: from the first connection that has new data
    /// ([`NewData`](FlowStatus::NewData)), else the last sample read again
    /// ([`OldData`](FlowStatus::OldData)), else [`NoData`](FlowStatus::NoData) and `sample`
    /// is left alone. Never blocks.
    #[inline(always)]
    pub fn read(&mut self, sample: &mut T) -> FlowStatus {
        self.read_at(sample, &mut 0)
    }

    /// [`read`](Self::read), and for new data from a stamped connection (see
    /// [`connect_stamped`](super::connect_stamped)) the time it was written, in ns on the
    /// monotonic clock, into `at` (left alone otherwise).
    #[inline(always)]
    pub fn read_at(&mut self, sample: &mut T, at: &mut u64) -> FlowStatus {
        if self.changed.load(Ordering::Relaxed) {
            self.refresh();
        }
        if let Some(d) = &mut self.direct {
            // A data connection is never stamped: `at` stays as it is.
            if let Found::New { version, value } = d.cell.read(d.seen) {
                d.seen = version;
                d.published.store(value, Ordering::Relaxed);
                d.ch.count_read();
                from_word(value, &mut self.last);
                return self.new_data(sample);
            }
        } else {
            for c in &mut self.conns {
                if c.pop_into(&mut self.last, at) {
                    self.published.publish(&self.last);
                    return self.new_data(sample);
                }
            }
        }
        if self.has_last {
            sample.clone_from(&self.last);
            FlowStatus::OldData
        } else {
            FlowStatus::NoData
        }
    }

    /// Hands the new sample in `last` to the caller.
    #[inline(always)]
    fn new_data(&mut self, sample: &mut T) -> FlowStatus {
        sample.clone_from(&self.last);
        if !self.has_last {
            self.has_last = true;
            self.shared.received.store(true, Ordering::Release);
        }
        FlowStatus::NewData
    }

    /// Takes up new connections and forgets closed ones; reads directly from a register
    /// when that is the only connection left.
    #[cold]
    fn refresh(&mut self) {
        self.undirect();
        self.shared
            .links
            .refresh_changed(&mut self.conns, Reader::is_done, Reader::lingers);
        let LatestIn::Plain(published) = &self.published else {
            return;
        };
        if let [only] = self.conns.as_slice()
            && let Some((cell, seen)) = only.register()
        {
            self.direct = Some(Direct {
                cell: cell.clone(),
                seen,
                ch: only.ch.clone(),
                published: published.clone(),
            });
        }
    }

    /// Hands the direct path's version back to its connection's end.
    fn undirect(&mut self) {
        if let Some(d) = self.direct.take()
            && let Some(c) = self.conns.iter_mut().find(|c| Arc::ptr_eq(&c.ch, &d.ch))
        {
            c.set_seen(d.seen);
        }
    }

    /// Closes every connection, keeping each until its writer has let go too, so a writer
    /// on a real-time thread never frees the connection's samples (for readers off the
    /// real-time threads: it locks).
    pub(crate) fn bury_connections(&mut self) {
        self.undirect();
        // Ends not taken up yet are taken now, so none is freed by its writer either.
        self.shared
            .links
            .refresh_changed(&mut self.conns, |_| false, |_| false);
        for c in self.conns.drain(..) {
            super::channel::bury(c.ch.clone());
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
