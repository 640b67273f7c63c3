//! The Modbus server's limits: how many connections, from whom, for how long, and how
//! long a write's reply waits for its delivery (see [`listener`](crate::listener)).

use std::time::Duration;

/// The server's limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Connections served at once; at this many, the one idle longest is closed to admit a
    /// new one.
    pub max_clients: usize,
    /// Connections from one IP address at once; one more from it is refused.
    pub max_clients_per_address: usize,
    /// A connection quiet this long is closed.
    pub idle_timeout: Duration,
    /// A frame must be whole this long after its first bytes arrived (the shorter of this
    /// and `idle_timeout` applies).
    pub frame_timeout: Duration,
    /// The longest a write's reply waits for a device whose bus carries the write later to
    /// deliver it; then the write is answered 0x0B (its target did not respond).
    pub write_confirm: Duration,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_clients: 16,
            max_clients_per_address: 8,
            idle_timeout: Duration::from_secs(60),
            frame_timeout: Duration::from_secs(5),
            write_confirm: DEFAULT_WRITE_CONFIRM,
        }
    }
}

/// [`Limits::write_confirm`] when not configured: a master's reply timeout is commonly
/// 1 s or more (mbpoll's and libmodbus's default is 1 s), a Modbus unit's poll cycle well
/// under that.
pub const DEFAULT_WRITE_CONFIRM: Duration = Duration::from_millis(1000);
