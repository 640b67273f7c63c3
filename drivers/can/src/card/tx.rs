//! A card's sending side: the payloads of its tx frames composed from the output images,
//! the marks of frames waiting to be sent (an on-change write, a flush at stop, a send
//! that failed), and the send counters.

use super::CanCard;
use super::status::bump;
use crate::map::SignalRole;
use std::sync::atomic::Ordering;

impl CanCard {
    /// Writes tx frame `tx`'s payload into `buf` (at least the frame's length) and clears
    /// its on-change mark. Returns the payload length.
    pub fn compose(&self, tx: usize, buf: &mut [u8]) -> usize {
        let Some(frame) = self.map.tx().get(tx) else {
            return 0;
        };
        self.tx_dirty[tx].store(false, Ordering::Release);
        let payload = &mut buf[..frame.length];
        payload.fill(0);
        for s in &frame.signals {
            let raw = match s.role {
                SignalRole::Analog => self.ao[s.channel as usize].load(Ordering::Acquire),
                SignalRole::Digital => (0..s.width()).fold(0i64, |v, k| {
                    v | i64::from(self.dout.get(s.channel + k).unwrap_or(false)) << k
                }),
                SignalRole::Encoder => continue,
            };
            // Values were range-checked when written.
            let _ = s.signal.insert(payload, raw);
        }
        frame.length
    }

    /// True while some tx frame waits to be sent (after an on-change write or a flush)
    /// that can be: a J1939 group waits for nothing while its node holds no address
    /// ([`unsendable`](Self::unsendable) says so).
    pub fn sends_pending(&self) -> bool {
        let no_address = self.no_address.load().is_some();
        self.tx_dirty
            .iter()
            .zip(self.map.tx())
            .any(|(d, f)| d.load(Ordering::Acquire) && !(no_address && f.j1939.is_some()))
    }

    /// Marks tx frame `tx` to be sent again (its send failed).
    pub(crate) fn resend(&self, tx: usize) {
        if let Some(d) = self.tx_dirty.get(tx) {
            d.store(true, Ordering::Release);
        }
    }

    /// True when tx frame `tx` waits to be sent because an output of it changed.
    pub fn is_dirty(&self, tx: usize) -> bool {
        self.tx_dirty
            .get(tx)
            .is_some_and(|d| d.load(Ordering::Acquire))
    }

    /// Counts a frame sent, or a send that failed.
    pub fn sent(&self, ok: bool) {
        bump(if ok {
            &self.counters.tx_frames
        } else {
            &self.counters.tx_errors
        });
    }

    /// Counts cyclic sends left out after a late wake-up.
    pub fn skipped(&self, cycles: u64) {
        self.counters
            .tx_skipped_cycles
            .fetch_add(cycles, Ordering::Relaxed);
    }

    /// An output of tx frame `tx` changed: an on-change frame is marked and the bus woken
    /// (a cyclic-only frame just carries the new value at its next cycle).
    pub(super) fn output(&self, tx: u32) {
        if self.map.tx().get(tx as usize).is_some_and(|f| f.on_change) {
            self.tx_dirty[tx as usize].store(true, Ordering::Release);
            self.wake();
        }
    }

    /// Wakes the bus side: ends its wait (a changed output, a flush, any wake-up of its
    /// activity).
    pub fn wake(&self) {
        if let Some(w) = self.waker.load().as_deref() {
            w();
        }
    }

    /// Asks the bus side to send every tx frame now (at shutdown, after the safe values).
    pub fn flush(&self) {
        for d in self.tx_dirty.iter() {
            d.store(true, Ordering::Release);
        }
        self.wake();
    }
}
