//! Where an output write stands after the call returned.
//!
//! Most devices apply a write within the call (a GPIO line, a simulated card). Others store
//! it and a bus activity carries it later: a Modbus unit polled on its line's cycle,
//! another gateway's output reached over Zenoh. A write that returned `Ok` there has been
//! *taken*, not yet *delivered*; whoever asked (the control socket's `set`, a northbound
//! server) must still hear when it fails on the way. Such a device keeps a
//! [`DeliveryTracker`] and answers [`AnalogOut::delivery`](crate::AnalogOut::delivery) /
//! [`DigitalOut::delivery`](crate::DigitalOut::delivery) from it.
//!
//! Each output channel numbers the writes it takes (1, 2, …). The bus side settles them in
//! order: a write is delivered, or failed with a reason, or superseded by a newer value of
//! the same output (then the newer one's fate is the one that counts: an output carries
//! only its newest value).
//!
//! # The real-time contract
//!
//! [`DeliveryTracker::take`] is one atomic increment: callable from the write path of a
//! real-time component. Settling and reading ([`DeliveryTracker::delivered`],
//! [`DeliveryTracker::failed`], [`DeliveryTracker::get`]) are for the bus and control
//! sides; a failure takes a short lock to keep its reason.

use crate::DeviceError;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

/// The delivery state of one output channel.
#[derive(Debug, Clone, Default)]
pub struct Delivery {
    /// Writes the channel has taken so far (only ever grows); the newest is number `taken`.
    pub taken: u64,
    /// The newest write whose fate is known, delivered or failed (`<= taken`).
    pub settled: u64,
    /// The newest write that reached the device (0: none yet).
    pub delivered: u64,
    /// The newest write that failed (0: none yet).
    pub failed: u64,
    /// Why write [`failed`](Self::failed) failed.
    pub error: Option<DeviceError>,
}

impl Delivery {
    /// The fate of write number `n`: `None` while it is on its way; `Some(Ok)` when it, or
    /// a newer value of the same output, reached the device; `Some(Err)` when it (and no
    /// newer value) failed.
    pub fn outcome(&self, n: u64) -> Option<Result<(), DeviceError>> {
        if self.delivered >= n {
            // It, or a newer value of the output, got there.
            return Some(Ok(()));
        }
        (self.failed >= n).then(|| {
            Err(self.error.clone().unwrap_or(DeviceError::Undelivered {
                reason: "no reason kept",
            }))
        })
    }
}

/// One channel's counters.
#[derive(Debug, Default)]
struct Counters {
    taken: AtomicU64,
    delivered: AtomicU64,
    failed: AtomicU64,
}

/// Lock-free delivery counters for `n` output channels (see the module doc).
#[derive(Debug)]
pub struct DeliveryTracker {
    channels: Box<[Counters]>,
    errors: Mutex<Box<[Option<DeviceError>]>>,
}

impl DeliveryTracker {
    /// Counters for `channels` outputs.
    pub fn new(channels: u32) -> Self {
        DeliveryTracker {
            channels: (0..channels).map(|_| Counters::default()).collect(),
            errors: Mutex::new((0..channels).map(|_| None).collect()),
        }
    }

    /// Notes a write taken on `channel`; returns its number (0 for a channel past the end).
    /// One atomic increment: real-time safe.
    pub fn take(&self, channel: u32) -> u64 {
        self.channels
            .get(channel as usize)
            .map_or(0, |c| c.taken.fetch_add(1, Ordering::AcqRel) + 1)
    }

    /// The number of the newest write `channel` took (0: none).
    pub fn taken(&self, channel: u32) -> u64 {
        self.channels
            .get(channel as usize)
            .map_or(0, |c| c.taken.load(Ordering::Acquire))
    }

    /// Writes up to number `n` of `channel` reached the device.
    pub fn delivered(&self, channel: u32, n: u64) {
        if let Some(c) = self.channels.get(channel as usize) {
            c.delivered.fetch_max(n, Ordering::AcqRel);
        }
    }

    /// Writes up to number `n` of `channel` failed, for `why`.
    pub fn failed(&self, channel: u32, n: u64, why: DeviceError) {
        let Some(c) = self.channels.get(channel as usize) else {
            return;
        };
        {
            let mut errors = self.errors.lock().unwrap_or_else(|p| p.into_inner());
            if let Some(slot) = errors.get_mut(channel as usize) {
                *slot = Some(why);
            }
        }
        c.failed.fetch_max(n, Ordering::AcqRel);
    }

    /// Every write taken so far on every channel failed, for `why` (a device that went
    /// away with writes on their way); returns how many channels had writes pending.
    pub fn fail_pending(&self, why: &DeviceError) -> usize {
        let mut n = 0;
        for ch in 0..self.channels.len() as u32 {
            let d = self.get(ch);
            if d.settled < d.taken {
                self.failed(ch, d.taken, why.clone());
                n += 1;
            }
        }
        n
    }

    /// The state of `channel` now (all zero for a channel past the end).
    pub fn get(&self, channel: u32) -> Delivery {
        let Some(c) = self.channels.get(channel as usize) else {
            return Delivery::default();
        };
        // Settled before taken: a number settled was taken, so the taken read after it is
        // at least as new.
        let failed = c.failed.load(Ordering::Acquire);
        let delivered = c.delivered.load(Ordering::Acquire);
        let taken = c.taken.load(Ordering::Acquire);
        let error = (failed > 0)
            .then(|| {
                self.errors
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .get(channel as usize)
                    .cloned()
                    .flatten()
            })
            .flatten();
        Delivery {
            taken,
            settled: delivered.max(failed),
            delivered,
            failed,
            error,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_write_is_pending_until_settled_and_a_newer_delivery_covers_it() {
        let t = DeliveryTracker::new(2);
        let n = t.take(1);
        assert_eq!(n, 1);
        assert!(t.get(1).outcome(n).is_none());
        let m = t.take(1);
        t.delivered(1, m);
        assert!(matches!(t.get(1).outcome(n), Some(Ok(()))));
        assert_eq!(t.get(0).taken, 0);
        assert_eq!(t.take(7), 0, "a channel past the end takes nothing");
    }

    #[test]
    fn a_failure_is_reported_to_every_write_it_covers_and_not_to_later_ones() {
        let t = DeliveryTracker::new(1);
        let a = t.take(0);
        let b = t.take(0);
        t.failed(0, b, DeviceError::Offline);
        assert!(matches!(
            t.get(0).outcome(a),
            Some(Err(DeviceError::Offline))
        ));
        assert!(matches!(
            t.get(0).outcome(b),
            Some(Err(DeviceError::Offline))
        ));
        let c = t.take(0);
        assert!(t.get(0).outcome(c).is_none());
        t.delivered(0, c);
        assert!(matches!(t.get(0).outcome(c), Some(Ok(()))));
        assert_eq!(t.fail_pending(&DeviceError::Offline), 0);
        let d = t.take(0);
        assert_eq!(t.fail_pending(&DeviceError::Offline), 1);
        assert!(matches!(t.get(0).outcome(d), Some(Err(_))));
    }

    #[test]
    fn a_write_delivered_stays_delivered_when_a_newer_one_fails() {
        let t = DeliveryTracker::new(1);
        let a = t.take(0);
        t.delivered(0, a);
        let b = t.take(0);
        t.failed(0, b, DeviceError::Offline);
        assert!(matches!(t.get(0).outcome(a), Some(Ok(()))));
        assert!(matches!(
            t.get(0).outcome(b),
            Some(Err(DeviceError::Offline))
        ));
        assert_eq!(t.get(0).settled, b);
    }
}
