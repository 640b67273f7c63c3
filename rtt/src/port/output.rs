//! The writing end of a data flow: [`OutputPort`], and what other threads see of it
//! (its connections, its last value for introspection and for `init` connections).
//!
//! A one-word sample's last value is a [`WordCell`] register that the port's data
//! connections read directly; a write touches the connections' ends only when one keeps
//! its own copy (a buffer, a larger sample) or wakes an event port.

use super::ConnectionInfo;
use super::channel::{Links, RESERVED_CONNECTIONS, Writer};
use super::latest::{LatestIn, LatestOut, latest};
use super::word::{WordCell, from_word};
use crate::lock::lock;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

/// What other threads see of an output port.
pub(crate) struct OutputShared<T: Send> {
    pub(crate) name: Arc<str>,
    pub(super) links: Links<Writer<T>, T>,
    sample: Mutex<T>,
    /// Set at the first write: the last value below is real (not used with `word`, whose
    /// version says so).
    written: AtomicBool,
    /// A one-word sample's register: the port's last value, read by its data connections.
    pub(super) word: Option<Arc<WordCell>>,
    /// The reading half of the last written value, for `init` and introspection, and the
    /// last value taken from it (a sample wider than a word: a one-word sample's last value
    /// is read from `word`, and this half is unused).
    last: Mutex<(LatestOut<T>, T)>,
}

impl<T: Clone + Send + 'static> OutputShared<T> {
    /// A copy of the data sample new connections pre-allocate from.
    pub(crate) fn sample_clone(&self) -> T {
        lock(&self.sample).clone()
    }

    /// The last value written, if any. Not for real-time paths (locks, clones).
    pub(crate) fn last_written(&self) -> Option<T> {
        // A register says itself whether it was written.
        if let Some(cell) = &self.word {
            let mut value = self.sample_clone();
            from_word(cell.latest()?, &mut value);
            return Some(value);
        }
        if !self.written.load(Ordering::Acquire) {
            return None;
        }
        let mut last = lock(&self.last);
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

/// The writing end of a data flow.
pub struct OutputPort<T: Send> {
    shared: Arc<OutputShared<T>>,
    /// The port's "look at your connections" flag (a pointer away, not three).
    changed: super::channel::Flag,
    pub(super) conns: Vec<Writer<T>>,
    /// Some connection's end needs each write (see [`Writer::needs_push`]).
    pub(super) push: bool,
    last: LatestIn<T>,
    /// The first write was made and published to other threads (a one-word port's
    /// register says so itself: set from the start).
    written: bool,
    /// `push`, or the first write not made yet: the one flag a write looks at after the
    /// register.
    more: bool,
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
        let (last_in, last_out) = latest(&sample);
        let word = match &last_in {
            LatestIn::Word { cell, .. } => Some(cell.clone()),
            _ => None,
        };
        let links = Links::new();
        OutputPort {
            changed: links.changed.clone(),
            shared: Arc::new(OutputShared {
                name: Arc::from(name),
                links,
                last: Mutex::new((last_out, sample.clone())),
                sample: Mutex::new(sample),
                written: AtomicBool::new(false),
                word: word.clone(),
            }),
            conns: Vec::with_capacity(RESERVED_CONNECTIONS),
            push: false,
            last: last_in,
            written: word.is_some(),
            more: word.is_none(),
        }
    }

    /// Sends `value` to every connection. Never blocks; a full buffer drops and counts.
    #[inline(always)]
    pub fn write(&mut self, value: &T) {
        if self.changed.load(Ordering::Relaxed) {
            self.refresh();
        }
        // First: the connections reading the register see it before an event port wakes.
        self.last.publish(value);
        if self.more {
            self.write_more(value);
        }
    }

    /// What a write does beyond the register: each connection's end that needs it, and
    /// the first write's flag for other threads.
    #[inline(always)]
    fn write_more(&mut self, value: &T) {
        if self.push {
            for c in &mut self.conns {
                c.push(value);
            }
        }
        if !self.written {
            self.written = true;
            self.shared.written.store(true, Ordering::Release);
            self.more = self.push;
        }
    }

    /// Takes up new connections and forgets closed ones.
    #[cold]
    fn refresh(&mut self) {
        self.shared
            .links
            .refresh_changed(&mut self.conns, |w| w.ch.is_closed(), |_| false);
        self.push = self.conns.iter().any(Writer::needs_push);
        self.more = self.push || !self.written;
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
