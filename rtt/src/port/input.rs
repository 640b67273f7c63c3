//! The reading end of a data flow: [`InputPort`], and what other threads see of it (its
//! connections, the last sample its owner read, the waker of an event port).

use super::channel::{Links, RESERVED_CONNECTIONS, Reader};
use super::latest::{LatestIn, LatestOut, snapshot};
use super::{ConnectionInfo, FlowStatus};
use crate::activity::Waker;
use std::sync::atomic::{AtomicBool, Ordering};
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
            self.shared
                .links
                .refresh_changed(&mut self.conns, Reader::is_done, Reader::lingers);
        }
        for c in &mut self.conns {
            if c.pop_into(&mut self.last, at) {
                sample.clone_from(&self.last);
                self.published.publish(&self.last);
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

    /// Closes every connection, keeping each until its writer has let go too, so a writer
    /// on a real-time thread never frees the connection's samples (for readers off the
    /// real-time threads: it locks).
    pub(crate) fn bury_connections(&mut self) {
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
