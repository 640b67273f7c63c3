//! What the streams of one Modbus server share: the table, the limits, the unit ids it
//! answers as its own, and the counters its tasks keep (the TCP connections'
//! [`conn`](crate::conn), the serial port's [`slave`](crate::slave)), which
//! [`listener`](crate::listener) reports.

use crate::limits::Limits;
use crate::server::RegisterTable;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::time::Duration;

/// The unit ids a server answers as its own.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum Units {
    /// Every unit id (but 0 on RTU, the broadcast).
    #[default]
    Any,
    /// These.
    Only(Vec<u8>),
}

impl Units {
    pub(crate) fn own(&self, unit: u8, rtu: bool) -> bool {
        match self {
            Units::Any => !(rtu && unit == 0),
            Units::Only(v) => v.contains(&unit),
        }
    }
}

/// The server's counters, as its tasks count them.
#[derive(Debug, Default)]
pub(crate) struct Stats {
    pub(crate) running: AtomicBool,
    /// When `accept` started failing (ns since `epoch`, plus 1), 0 while it succeeds.
    pub(crate) failing_since: AtomicU64,
    pub(crate) clients: AtomicUsize,
    pub(crate) connections: AtomicU64,
    pub(crate) evicted: AtomicU64,
    pub(crate) refused_per_address: AtomicU64,
    pub(crate) requests: AtomicU64,
    pub(crate) exceptions: AtomicU64,
    pub(crate) malformed: AtomicU64,
    pub(crate) idle_closed: AtomicU64,
    pub(crate) frame_timeouts: AtomicU64,
    pub(crate) accept_errors: AtomicU64,
    pub(crate) panics: AtomicU64,
    pub(crate) writes_confirmed: AtomicU64,
    pub(crate) writes_failed: AtomicU64,
    pub(crate) writes_unconfirmed: AtomicU64,
    pub(crate) crc_errors: AtomicU64,
    pub(crate) broadcasts: AtomicU64,
    pub(crate) other_units: AtomicU64,
    pub(crate) unreachable: AtomicU64,
    pub(crate) forwarded: AtomicU64,
    pub(crate) gateway_no_response: AtomicU64,
    pub(crate) gateway_unavailable: AtomicU64,
    pub(crate) port: PortState,
}

/// The serial port's state, for counters and health.
#[derive(Debug, Default)]
pub(crate) struct PortState {
    /// Times the port was opened.
    pub(crate) opens: AtomicU64,
    /// Failures to open or set up the port, and errors that closed it.
    pub(crate) errors: AtomicU64,
    /// When the port stopped serving (ns since the server's epoch, plus 1), 0 before a
    /// failure.
    failing_since: AtomicU64,
    /// When the port was opened (ns since the server's epoch, plus 1), 0 while closed.
    open_since: AtomicU64,
    /// Why, last.
    last_error: std::sync::Mutex<String>,
}

/// How long a port must stay open to count as serving again: one that opens and fails at
/// once (a USB adapter returning EIO) is still failing.
pub(crate) const PORT_UP: Duration = Duration::from_secs(5);

impl PortState {
    /// The port opened.
    pub(crate) fn opened(&self, epoch: std::time::Instant) {
        self.opens.fetch_add(1, Ordering::Relaxed);
        self.open_since
            .store(epoch.elapsed().as_nanos() as u64 + 1, Ordering::Release);
    }

    /// How long the port has been open, if it is.
    pub(crate) fn up(&self, epoch: std::time::Instant) -> Option<Duration> {
        let since = self.open_since.load(Ordering::Acquire);
        (since != 0).then(|| {
            Duration::from_nanos((epoch.elapsed().as_nanos() as u64).saturating_sub(since - 1))
        })
    }

    /// How long the port has not served and why, if it does not: not while it has been
    /// open for [`PORT_UP`].
    pub(crate) fn failing(&self, epoch: std::time::Instant) -> Option<(Duration, String)> {
        if self.up(epoch).is_some_and(|u| u >= PORT_UP) {
            return None;
        }
        let since = self.failing_since.load(Ordering::Acquire);
        (since != 0).then(|| {
            let now = epoch.elapsed().as_nanos() as u64;
            (
                Duration::from_nanos(now.saturating_sub(since - 1)),
                rtt::lock(&self.last_error).clone(),
            )
        })
    }

    /// Counts a failure; true for the first of every hundred (to log).
    pub(crate) fn failed(&self, epoch: std::time::Instant, why: String) -> bool {
        let first = first_of_hundred(&self.errors);
        let now = epoch.elapsed().as_nanos() as u64 + 1;
        // A port that served for a while fails anew from now; one that failed at once
        // goes on failing since it first did.
        if self.up(epoch).is_some_and(|u| u >= PORT_UP) {
            self.failing_since.store(now, Ordering::Release);
        } else {
            let _ =
                self.failing_since
                    .compare_exchange(0, now, Ordering::AcqRel, Ordering::Relaxed);
        }
        self.open_since.store(0, Ordering::Release);
        *rtt::lock(&self.last_error) = why;
        first
    }
}

/// What every stream of one server shares.
pub(crate) struct Shared {
    pub(crate) table: RegisterTable,
    pub(crate) stats: Arc<Stats>,
    pub(crate) limits: Limits,
    pub(crate) units: Units,
    /// Where requests for other units go (gateway mode).
    pub(crate) routes: Vec<crate::gateway::Route>,
    pub(crate) epoch: std::time::Instant,
}

pub(crate) fn bump(c: &AtomicU64) {
    c.fetch_add(1, Ordering::Relaxed);
}

/// Counts one more on `counter`; true for the first of every hundred (what is logged, so a
/// flood is counted in full but said only now and then).
pub(crate) fn first_of_hundred(counter: &AtomicU64) -> bool {
    counter.fetch_add(1, Ordering::Relaxed).is_multiple_of(100)
}
