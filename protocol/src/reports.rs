//! The reports of cards and servers `status` carries: the gateway fills them, the
//! protocol defines them.

use driver_api::CardStatus;
use serde::{Deserialize, Serialize};

/// One card in `hwgw status`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CardReport {
    /// The card.
    pub name: String,
    /// Its driver.
    pub driver: String,
    /// Its bus and counters.
    #[serde(flatten)]
    pub status: CardStatus,
    /// Its outputs: how many hwgw wrote, watchdog trips.
    pub outputs: OutputReport,
}

/// Counters of a card's outputs, for `hwgw status`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct OutputReport {
    /// Outputs hwgw wrote since it started.
    pub written: u64,
    /// Watchdog trips (an output driven to its safe value while running).
    pub watchdog_trips: u64,
}

/// A server's state, for `status`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ServerReport {
    /// Its deployment key (`modbus_server`).
    pub name: String,
    /// Where it listens, and its counters.
    #[serde(flatten)]
    pub status: CardStatus,
}
