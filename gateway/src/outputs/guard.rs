//! The guards every card output is registered through: they note which outputs hwgw wrote,
//! when last, and each one's value just before hwgw first wrote it, and refuse every write
//! once the gateway holds its outputs for the stop.
//!
//! Real-time contract: a guarded write adds, to the card's own write, an uncontended
//! read lock (a compare-and-swap; contended only while [`Hold::hold`] waits for writes under
//! way), two atomic stores, and on an output's first write one read-back and, for a card
//! with [`ReadBack::DeviceWhen`], its check. Nothing allocates.

use device_interface::{AnalogOut, Delivery, Device, DeviceError, DigitalOut, Health, Scale};
use driver_api::ReadBack;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, OnceLock, PoisonError, RwLock, RwLockReadGuard};

/// Why guarded outputs refuse writes during a stop.
const STOPPING: &str = "the gateway is stopping: outputs go to their safe values";

/// The gateway's stop flag and the gate every guarded write passes: a write checks the
/// flag and goes to the card under the gate's read side, so once [`hold`](Hold::hold)
/// returns no write that passed the check is still under way — the safe values that
/// follow are the last word.
#[derive(Debug, Default)]
pub struct Hold {
    held: AtomicBool,
    /// Held for good: its card was taken down by a reload (and a new one may stand under
    /// its name). A writer still holding its devices is refused as by a device gone
    /// (offline), not as by a stop, so the writer shows the fault.
    retired: AtomicBool,
    gate: RwLock<()>,
}

impl Hold {
    /// From now on every guarded write is refused ([`DeviceError::Held`]); returns once the
    /// writes under way have finished. Idempotent.
    pub fn hold(&self) {
        let _closed = self.gate.write().unwrap_or_else(PoisonError::into_inner);
        self.held.store(true, Ordering::Release);
    }

    /// [`hold`](Hold::hold), for a card a reload takes down: from now on a write is refused
    /// as by a device that is gone ([`DeviceError::Offline`]).
    pub fn retire(&self) {
        let _closed = self.gate.write().unwrap_or_else(PoisonError::into_inner);
        self.retired.store(true, Ordering::Release);
        self.held.store(true, Ordering::Release);
    }

    /// True once [`hold`](Hold::hold) was called.
    pub fn is_held(&self) -> bool {
        self.held.load(Ordering::Acquire)
    }

    /// Admits one write (the guard is held while it goes to the card), or refuses it.
    fn enter(&self) -> Result<RwLockReadGuard<'_, ()>, DeviceError> {
        let open = self.gate.read().unwrap_or_else(PoisonError::into_inner);
        if self.is_held() {
            if self.retired.load(Ordering::Acquire) {
                return Err(DeviceError::Offline);
            }
            return Err(DeviceError::Held { reason: STOPPING });
        }
        Ok(open)
    }
}

/// Per output: written at all, when last (ns on the monotonic clock), and its value just
/// before the first write (`None` inside: the card's read-back could not tell it).
pub(crate) struct Track {
    written: Box<[AtomicBool]>,
    last_ns: Box<[AtomicU64]>,
    initial: Box<[OnceLock<Option<f64>>]>,
    read_back: ReadBack,
}

impl Track {
    fn new(n: u32, read_back: ReadBack) -> Track {
        Track {
            written: (0..n).map(|_| AtomicBool::new(false)).collect(),
            last_ns: (0..n).map(|_| AtomicU64::new(0)).collect(),
            initial: (0..n).map(|_| OnceLock::new()).collect(),
            read_back,
        }
    }

    /// Before output `i` is written: the first time, notes its value as `read` gives it,
    /// when the card's read-back is the device's state.
    fn before(&self, i: u32, read: impl FnOnce() -> Result<f64, DeviceError>) {
        if let Some(cell) = self.initial.get(i as usize) {
            cell.get_or_init(|| {
                if self.read_back.is_device() {
                    read().ok()
                } else {
                    None
                }
            });
        }
    }

    fn mark(&self, i: u32) {
        use rtt::time::{Clock, MonotonicClock};
        if let (Some(w), Some(t)) = (self.written.get(i as usize), self.last_ns.get(i as usize)) {
            t.store(MonotonicClock.now().as_nanos(), Ordering::Release);
            w.store(true, Ordering::Release);
        }
    }

    /// True once hwgw wrote output `i`.
    pub(crate) fn written(&self, i: u32) -> bool {
        self.written
            .get(i as usize)
            .is_some_and(|w| w.load(Ordering::Acquire))
    }

    /// When hwgw last wrote output `i` (0: never).
    pub(crate) fn last(&self, i: u32) -> u64 {
        self.last_ns
            .get(i as usize)
            .map_or(0, |t| t.load(Ordering::Acquire))
    }

    /// Output `i`'s value just before hwgw first wrote it, if the card could tell.
    pub(crate) fn initial(&self, i: u32) -> Option<f64> {
        self.initial
            .get(i as usize)
            .and_then(|c| c.get().copied().flatten())
    }

    /// How many outputs hwgw wrote.
    pub(crate) fn count_written(&self) -> u64 {
        self.written
            .iter()
            .filter(|w| w.load(Ordering::Relaxed))
            .count() as u64
    }
}

/// A card's analog outputs as the registry hands them out: writes go through to the card,
/// are noted, and are refused once the gateway holds its outputs.
pub struct GuardedAnalogOut {
    pub(crate) inner: Arc<dyn AnalogOut>,
    hold: Arc<Hold>,
    pub(crate) track: Track,
}

impl GuardedAnalogOut {
    pub(crate) fn new(inner: Arc<dyn AnalogOut>, hold: &Arc<Hold>, rb: ReadBack) -> Self {
        let track = Track::new(inner.channel_count(), rb);
        GuardedAnalogOut {
            inner,
            hold: hold.clone(),
            track,
        }
    }

    fn guarded(
        &self,
        channel: u32,
        write: impl FnOnce(&dyn AnalogOut) -> Result<(), DeviceError>,
    ) -> Result<(), DeviceError> {
        let _open = self.hold.enter()?;
        self.track.before(channel, || self.inner.read_back(channel));
        write(&*self.inner)?;
        self.track.mark(channel);
        Ok(())
    }
}

impl Device for GuardedAnalogOut {
    fn health(&self) -> Health {
        self.inner.health()
    }
}

impl AnalogOut for GuardedAnalogOut {
    fn channel_count(&self) -> u32 {
        self.inner.channel_count()
    }
    fn scale(&self, channel: u32) -> Result<Scale, DeviceError> {
        self.inner.scale(channel)
    }
    fn write_raw(&self, channel: u32, raw: i64) -> Result<(), DeviceError> {
        self.guarded(channel, |d| d.write_raw(channel, raw))
    }
    fn write(&self, channel: u32, value: f64) -> Result<(), DeviceError> {
        self.guarded(channel, |d| d.write(channel, value))
    }
    fn read_back_raw(&self, channel: u32) -> Result<i64, DeviceError> {
        self.inner.read_back_raw(channel)
    }
    fn read_back(&self, channel: u32) -> Result<f64, DeviceError> {
        self.inner.read_back(channel)
    }
    fn delivery(&self, channel: u32) -> Option<Delivery> {
        self.inner.delivery(channel)
    }
}

/// A card's digital outputs as the registry hands them out (see [`GuardedAnalogOut`]).
pub struct GuardedDigitalOut {
    pub(crate) inner: Arc<dyn DigitalOut>,
    hold: Arc<Hold>,
    pub(crate) track: Track,
}

impl GuardedDigitalOut {
    pub(crate) fn new(inner: Arc<dyn DigitalOut>, hold: &Arc<Hold>, rb: ReadBack) -> Self {
        let track = Track::new(inner.output_count(), rb);
        GuardedDigitalOut {
            inner,
            hold: hold.clone(),
            track,
        }
    }

    /// Notes bits `start..=stop` before their first write (0.0 / 1.0).
    fn before(&self, start: u32, stop: u32) {
        for b in start..=stop {
            self.track.before(b, || {
                self.inner.check_bit(b).map(|on| f64::from(u8::from(on)))
            });
        }
    }
}

impl Device for GuardedDigitalOut {
    fn health(&self) -> Health {
        self.inner.health()
    }
}

impl DigitalOut for GuardedDigitalOut {
    fn output_count(&self) -> u32 {
        self.inner.output_count()
    }
    fn set_bit(&self, bit: u32, value: bool) -> Result<(), DeviceError> {
        let _open = self.hold.enter()?;
        self.before(bit, bit);
        self.inner.set_bit(bit, value)?;
        self.track.mark(bit);
        Ok(())
    }
    fn check_bit(&self, bit: u32) -> Result<bool, DeviceError> {
        self.inner.check_bit(bit)
    }
    fn set_sequence(&self, start: u32, stop: u32, value: u64) -> Result<(), DeviceError> {
        let _open = self.hold.enter()?;
        // A span the card would refuse is refused before anything is noted.
        if start > stop || stop >= self.inner.output_count() {
            return self.inner.set_sequence(start, stop, value);
        }
        self.before(start, stop);
        self.inner.set_sequence(start, stop, value)?;
        for b in start..=stop {
            self.track.mark(b);
        }
        Ok(())
    }
    fn check_sequence(&self, start: u32, stop: u32) -> Result<u64, DeviceError> {
        self.inner.check_sequence(start, stop)
    }
    fn delivery(&self, bit: u32) -> Option<Delivery> {
        self.inner.delivery(bit)
    }
}
