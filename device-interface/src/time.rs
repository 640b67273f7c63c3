//! Monotonic time: the timestamps devices put on their samples, and the clocks that make them.
//!
//! A [`Timestamp`] is nanoseconds on a monotonic clock, a plain `u64` so it can be stored in
//! an atomic, compared, and sent over a network. A [`Clock`] hands out timestamps:
//! [`MonotonicClock`] reads the kernel's `CLOCK_MONOTONIC`; [`SimClock`] only moves when told
//! to, which makes tests of time-dependent behaviour (staleness, waveforms, encoder motion)
//! exact and repeatable.
//!
//! ```
//! use device_interface::time::{Clock, SimClock, Timestamp};
//! use std::time::Duration;
//!
//! let clock = SimClock::new(Timestamp::from_nanos(1_000));
//! let t0 = clock.now();
//! clock.advance(Duration::from_millis(5));
//! assert_eq!(clock.now().duration_since(t0), Duration::from_millis(5));
//! ```

use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

/// A point in time: nanoseconds on a monotonic clock.
///
/// Only timestamps from the same clock are comparable.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    PartialOrd,
    Ord,
    Hash,
    Default,
    serde::Serialize,
    serde::Deserialize,
)]
#[serde(transparent)]
pub struct Timestamp(u64);

impl Timestamp {
    /// The clock's origin.
    pub const ZERO: Timestamp = Timestamp(0);

    /// A timestamp `nanos` nanoseconds after the clock's origin.
    pub const fn from_nanos(nanos: u64) -> Self {
        Timestamp(nanos)
    }

    /// Nanoseconds since the clock's origin.
    pub const fn as_nanos(self) -> u64 {
        self.0
    }

    /// Seconds since the clock's origin, as a float (for waveforms and display).
    pub fn as_secs_f64(self) -> f64 {
        self.0 as f64 * 1e-9
    }

    /// Time from `earlier` to `self`; zero if `earlier` is later.
    pub fn duration_since(self, earlier: Timestamp) -> Duration {
        Duration::from_nanos(self.0.saturating_sub(earlier.0))
    }

    /// `self + d`, saturating at the end of time.
    pub fn saturating_add(self, d: Duration) -> Timestamp {
        let nanos = u64::try_from(d.as_nanos()).unwrap_or(u64::MAX);
        Timestamp(self.0.saturating_add(nanos))
    }
}

impl fmt::Display for Timestamp {
    /// Seconds with microsecond precision, the precision logs and exports need.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}.{:06}",
            self.0 / 1_000_000_000,
            (self.0 % 1_000_000_000) / 1_000
        )
    }
}

/// A source of monotonic timestamps.
///
/// `now()` must be callable from a real-time thread: no blocking, no allocation.
pub trait Clock: Send + Sync {
    /// The current time.
    fn now(&self) -> Timestamp;
}

/// The kernel's `CLOCK_MONOTONIC`: the time base of every real device.
///
/// Timestamps from it are comparable across processes on the same host (not across hosts).
#[derive(Debug, Clone, Copy, Default)]
pub struct MonotonicClock;

impl Clock for MonotonicClock {
    fn now(&self) -> Timestamp {
        // CLOCK_MONOTONIC always exists on Linux; the fallback only guards against an
        // impossible EINVAL without panicking.
        match nix::time::clock_gettime(nix::time::ClockId::CLOCK_MONOTONIC) {
            Ok(ts) => {
                let secs = u64::try_from(ts.tv_sec()).unwrap_or(0);
                let nanos = u64::try_from(ts.tv_nsec()).unwrap_or(0);
                Timestamp(secs.saturating_mul(1_000_000_000).saturating_add(nanos))
            }
            Err(_) => Timestamp::ZERO,
        }
    }
}

/// A clock that moves only when told to: for deterministic tests and simulations.
///
/// Shared between threads; `advance` and `set` are atomic.
#[derive(Debug, Default)]
pub struct SimClock {
    nanos: AtomicU64,
}

impl SimClock {
    /// A clock standing at `start`.
    pub fn new(start: Timestamp) -> Self {
        SimClock {
            nanos: AtomicU64::new(start.0),
        }
    }

    /// Moves the clock forward by `d` and returns the new time.
    pub fn advance(&self, d: Duration) -> Timestamp {
        let step = u64::try_from(d.as_nanos()).unwrap_or(u64::MAX);
        let prev = self.nanos.fetch_add(step, Ordering::SeqCst);
        Timestamp(prev.saturating_add(step))
    }

    /// Puts the clock at `t`. Going backwards is refused (the clock is monotonic): returns
    /// `false` and leaves the clock where it was.
    pub fn set(&self, t: Timestamp) -> bool {
        self.nanos.fetch_max(t.0, Ordering::SeqCst) <= t.0
    }
}

impl Clock for SimClock {
    fn now(&self) -> Timestamp {
        Timestamp(self.nanos.load(Ordering::SeqCst))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn monotonic_clock_moves_forward() {
        let c = MonotonicClock;
        let a = c.now();
        let b = c.now();
        assert!(a.as_nanos() > 0);
        assert!(b >= a);
    }

    #[test]
    fn sim_clock_is_monotonic() {
        let c = SimClock::new(Timestamp::from_nanos(10));
        assert!(c.set(Timestamp::from_nanos(20)));
        assert!(!c.set(Timestamp::from_nanos(15)));
        assert_eq!(c.now(), Timestamp::from_nanos(20));
        assert_eq!(
            c.advance(Duration::from_nanos(5)),
            Timestamp::from_nanos(25)
        );
    }

    #[test]
    fn display_has_microseconds() {
        assert_eq!(Timestamp::from_nanos(3_000_123_999).to_string(), "3.000123");
        assert_eq!(
            Timestamp::from_nanos(5).duration_since(Timestamp::from_nanos(9)),
            Duration::ZERO
        );
    }
}
