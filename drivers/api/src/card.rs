//! The [`Card`] trait: one built card, whatever its bus.

use device_interface::CardDevices;
use serde::{Deserialize, Serialize};
use std::sync::Arc;
use std::time::Instant;

use crate::names::ChannelNames;

/// A card's bus status for `hwgw status`: where it is and its counters.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CardStatus {
    /// Where the card is on its bus: an interface, an address and unit, a port.
    pub bus: String,
    /// The driver's counters and bus state, by name (a serialised snapshot struct).
    pub counters: serde_json::Map<String, serde_json::Value>,
}

impl CardStatus {
    /// A status at `bus` with the fields of `snapshot` (any struct that serialises to a
    /// map) as its counters.
    pub fn new(bus: impl Into<String>, snapshot: &impl Serialize) -> CardStatus {
        let counters = match serde_json::to_value(snapshot) {
            Ok(serde_json::Value::Object(m)) => m,
            Ok(other) => {
                let mut m = serde_json::Map::new();
                m.insert("value".into(), other);
                m
            }
            Err(e) => {
                let mut m = serde_json::Map::new();
                m.insert("error".into(), serde_json::Value::String(e.to_string()));
                m
            }
        };
        CardStatus {
            bus: bus.into(),
            counters,
        }
    }
}

/// What a card's output read-back (`AnalogOut::read_back`, `DigitalOut::check_bit`) shows:
/// the gateway notes an output's value just before hwgw first writes it, to put it back at
/// stop under the policy "initial", only when the read-back is the device's own state.
#[derive(Clone, Default)]
pub enum ReadBack {
    /// Only what hwgw wrote (before that, a placeholder): "initial" leaves such outputs as
    /// they are at stop. The default: a card that cannot tell must not claim more.
    #[default]
    Written,
    /// Always the device's state (the devices are the hardware's registers).
    Device,
    /// The device's state whenever this says so (e.g. once the outputs were polled).
    /// Called from the first write of each output, on the writer's thread: it must keep
    /// the device interfaces' real-time contract (non-blocking, allocation-free).
    DeviceWhen(Arc<dyn Fn() -> bool + Send + Sync>),
}

impl ReadBack {
    /// True when the read-back shows the device's state now.
    pub fn is_device(&self) -> bool {
        match self {
            ReadBack::Written => false,
            ReadBack::Device => true,
            ReadBack::DeviceWhen(now) => now(),
        }
    }
}

impl std::fmt::Debug for ReadBack {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            ReadBack::Written => "Written",
            ReadBack::Device => "Device",
            ReadBack::DeviceWhen(_) => "DeviceWhen(..)",
        })
    }
}

/// One built card of a deployment.
///
/// Built by its driver's [`BuildFn`](crate::BuildFn) without starting anything (so `hwgw
/// check` runs the same code as `hwgw run`), with its [`BusSide`](crate::BusSide) beside
/// it (see [`BuiltCard`](crate::BuiltCard)); the gateway then registers its devices, adds
/// the bus side once, and at stop drives its outputs to their safe values.
///
/// Real-time contract: these methods are called by the gateway at build, start, status and
/// stop time, never from a real-time path; the devices they hand out keep the device
/// interfaces' contract (non-blocking, bounded, allocation-free).
pub trait Card: Send + Sync {
    /// The card's devices, registered under the card's name (encoders as
    /// `card.<suffix>`). Called once, at build.
    fn devices(&self) -> CardDevices;

    /// Port names for channels the deployment's `[card.names]` leaves unnamed (e.g. signal
    /// names from a CAN database). Names must be unique per list, without dots or spaces;
    /// give none rather than bad ones. Default: none.
    fn channel_names(&self) -> ChannelNames {
        ChannelNames::default()
    }

    /// What the driver knows of its channels beyond their names (from a CAN database: a
    /// comment, named values), for their ports. Default: nothing.
    fn channel_details(&self) -> crate::ChannelDetails {
        crate::ChannelDetails::default()
    }

    /// One line for the start-up log: what the card talks to and what it maps.
    fn summary(&self) -> String;

    /// Its bus status and counters, now. Default: none.
    fn status(&self) -> CardStatus {
        CardStatus::default()
    }

    /// What the read-back of its outputs shows (see [`ReadBack`]). Called once, at build.
    /// Default: [`ReadBack::Written`].
    fn read_back(&self) -> ReadBack {
        ReadBack::Written
    }

    /// At stop, after the gateway wrote the safe values to the card's outputs and while its
    /// bus side still runs: waits, until `deadline` at the latest, for them to reach the
    /// hardware (sent, acknowledged). `bus_running` is false when the card's bus side (the
    /// components its [`BusSide`](crate::BusSide) added) is not running — never started,
    /// failed or stopped: nothing will carry the safe values, so do not wait for it. It is
    /// true when that bus side runs, and for a card without a bus side of its own (a card
    /// that shares another card's bus knows of that bus itself). `Err` says why the safe
    /// values may not have arrived. Default: nothing to wait for.
    fn settle(&self, deadline: Instant, bus_running: bool) -> Result<(), SettleError> {
        let _ = (deadline, bus_running);
        Ok(())
    }
}

/// Why a card's safe values may not have reached the hardware at stop
/// ([`Card::settle`]).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SettleError {
    /// The card's bus side is not running: nothing carried the safe values.
    #[error("its bus side is not running: safe values not sent")]
    BusNotRunning,
    /// The device, its link or its bus is offline (what is offline).
    #[error("{0} is offline: its outputs may not be at their safe values")]
    Offline(String),
    /// The deadline came first (what was not done by then: "safe values sent").
    #[error("{0} not in time")]
    Late(String),
    /// Some went unsent, each named with why ("MCP23017 at 0x20 (offline)").
    #[error("outputs not sent to {}", .0.join(", "))]
    Unsent(Vec<String>),
    /// The device refused them or shows others, one entry per output or pin.
    #[error("safe values not confirmed: {}", .0.join("; "))]
    Refused(Vec<String>),
}

impl SettleError {
    /// What was still pending at the deadline (`what` was not done by then, e.g. "safe
    /// values sent"): late while the bus side ran, else nothing carried it.
    pub fn pending(bus_running: bool, what: impl Into<String>) -> SettleError {
        if bus_running {
            SettleError::Late(what.into())
        } else {
            SettleError::BusNotRunning
        }
    }
}

/// Waits, `step` at a time, while `busy()` says a card's safe values are on their way
/// and `deadline` has not come; returns whether it still is. For [`Card::settle`].
pub fn wait_while(
    deadline: Instant,
    step: std::time::Duration,
    mut busy: impl FnMut() -> bool,
) -> bool {
    while busy() {
        if Instant::now() >= deadline {
            return true;
        }
        std::thread::sleep(step);
    }
    false
}
