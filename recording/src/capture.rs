//! A capture: a [`Recorder`] fed through a trigger [`Window`] when there is one, so the
//! recorder component and `hwgw record` share one way of deciding what is written.

use crate::item::Item;
use crate::trigger::Window;
use crate::write::{Closing, RecordError, Recorder, Sink};
use std::collections::BTreeMap;

/// A recording, triggered or not.
pub struct Capture<W: Sink = std::io::BufWriter<std::fs::File>> {
    recorder: Recorder<W>,
    window: Option<Window>,
    pass: Vec<Item>,
}

impl<W: Sink> Capture<W> {
    /// Writes everything offered to `recorder`, or only the window of `window`.
    pub fn new(recorder: Recorder<W>, window: Option<Window>) -> Self {
        Capture {
            recorder,
            window,
            pass: Vec::new(),
        }
    }

    /// Takes one batch of items, later than the batches before, its items in any order
    /// (MCAP's message indexes give readers the time order); `now_ns` is when they were
    /// taken, on the items' clock. A chunk of the file is written at least every
    /// [`CHECKPOINT_NS`](crate::write::CHECKPOINT_NS) of `now_ns` (see
    /// [`Recorder::checkpoint`]).
    pub fn offer(&mut self, mut items: Vec<Item>, now_ns: u64) -> Result<(), RecordError> {
        let Some(window) = &mut self.window else {
            for item in &items {
                self.recorder.write(item, now_ns)?;
            }
            return self.recorder.checkpoint(now_ns);
        };
        // The window decides by time: a batch is put in time order first (a batch given
        // port after port would otherwise push the ring past items of the window).
        items.sort_by_key(Item::time_ns);
        self.pass.clear();
        for item in items {
            window.offer(item, &mut self.pass);
        }
        window.advance(now_ns);
        for item in &self.pass {
            self.recorder.write(item, now_ns)?;
        }
        self.recorder.checkpoint(now_ns)
    }

    /// True when a triggered capture has its whole window.
    pub fn done(&self) -> bool {
        self.window.as_ref().is_some_and(Window::done)
    }

    /// True when a triggered capture's trigger came.
    pub fn triggered(&self) -> bool {
        self.window
            .as_ref()
            .is_some_and(|w| w.triggered_at().is_some())
    }

    /// Messages written so far.
    pub fn written(&self) -> u64 {
        self.recorder.written()
    }

    /// True once a write failed (see [`Recorder::failed`]).
    pub fn failed(&self) -> bool {
        self.recorder.failed()
    }

    /// Finishes the file, with the window's facts in the metadata.
    pub fn finish(self, mut closing: Closing) -> Result<BTreeMap<String, String>, RecordError> {
        if let Some(w) = &self.window {
            let offset = self.recorder.wall_offset_ns();
            let wall = |t: u64| (i128::from(t) + offset).to_string();
            let notes = &mut closing.notes;
            match w.bounds() {
                Some((start, end)) => {
                    notes.insert("trigger.at_ns".into(), wall(w.triggered_at().unwrap_or(0)));
                    notes.insert("trigger.window_start_ns".into(), wall(start));
                    notes.insert("trigger.window_end_ns".into(), wall(end));
                    let from = w.complete_from().unwrap_or(start);
                    notes.insert("trigger.complete_from_ns".into(), wall(from));
                }
                None => {
                    notes.insert("trigger.at_ns".into(), "never".into());
                }
            }
            notes.insert("trigger.ring_overflow".into(), w.ring_overflow.to_string());
            notes.insert("trigger.not_numbers".into(), w.not_numbers.to_string());
        }
        self.recorder.finish(&closing)
    }
}
