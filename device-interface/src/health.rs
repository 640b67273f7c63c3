//! Device health: is the device there, and how fresh are its inputs.
//!
//! Every device reports a [`Health`] so a component can tell a fresh value from a stale one
//! and an operator can see why a card is not delivering.
//!
//! ```
//! use device_interface::{Health, Status, time::Timestamp};
//! use std::time::Duration;
//!
//! let h = Health {
//!     status: Status::Online,
//!     last_good: Some(Timestamp::from_nanos(1_000_000)),
//!     checked_at: Timestamp::from_nanos(3_000_000),
//!     last_error: None,
//! };
//! assert_eq!(h.age(), Some(Duration::from_millis(2)));
//! ```

use crate::DeviceError;
use crate::time::Timestamp;
use std::fmt;
use std::time::Duration;

/// Whether a device is delivering.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Status {
    /// Answering, inputs refreshed in time.
    Online,
    /// Reachable, but its inputs have not been refreshed in time.
    Stale,
    /// Not answering: link down, unplugged, or not yet seen.
    Offline,
}

impl fmt::Display for Status {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Status::Online => "online",
            Status::Stale => "stale",
            Status::Offline => "offline",
        })
    }
}

/// A device's health at one moment.
#[derive(Debug, Clone)]
pub struct Health {
    /// Whether the device is delivering.
    pub status: Status,
    /// When the device last delivered a good sample, on its clock; `None` if never.
    pub last_good: Option<Timestamp>,
    /// When this report was made, on the same clock.
    pub checked_at: Timestamp,
    /// The last error the device's bus activity saw, if it still applies.
    pub last_error: Option<DeviceError>,
}

impl Health {
    /// Age of the last good sample when this report was made; `None` if there never was one.
    pub fn age(&self) -> Option<Duration> {
        self.last_good.map(|t| self.checked_at.duration_since(t))
    }

    /// True when the device is online.
    pub fn is_online(&self) -> bool {
        self.status == Status::Online
    }

    /// The health of a device that is online or offline as a whole: its last good sample
    /// at `last_good_nanos` on its clock (0: never), [`DeviceError::Offline`] as the last
    /// error while offline.
    pub fn online_if(online: bool, last_good_nanos: u64, checked_at: Timestamp) -> Health {
        Health {
            status: if online {
                Status::Online
            } else {
                Status::Offline
            },
            last_good: (last_good_nanos != 0).then(|| Timestamp::from_nanos(last_good_nanos)),
            checked_at,
            last_error: (!online).then_some(DeviceError::Offline),
        }
    }
}
