//! What a CAN card reports of its bus: the controller's error state, what error frames
//! said, and the counters of frames, errors and staleness (`hwgw status`).

use super::CanCard;
use crate::netlink::{Controller, ControllerState};
use device_interface::time::Timestamp;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

/// The controller's error state, as error frames report it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum BusState {
    /// Normal operation (also the state before any error frame).
    ErrorActive,
    /// An error counter passed 96.
    ErrorWarning,
    /// An error counter passed 127: the controller no longer sends active error flags.
    ErrorPassive,
    /// The transmit error counter passed 255: the controller is off the bus.
    BusOff,
}

impl BusState {
    pub(super) fn from_u8(v: u8) -> BusState {
        match v {
            1 => BusState::ErrorWarning,
            2 => BusState::ErrorPassive,
            3 => BusState::BusOff,
            _ => BusState::ErrorActive,
        }
    }
}

/// What an error frame reported, decoded by the bus side.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ErrorReport {
    /// The controller went bus-off.
    pub bus_off: bool,
    /// The controller was restarted (back to error-active).
    pub restarted: bool,
    /// Controller reached error-warning.
    pub warning: bool,
    /// Controller reached error-passive.
    pub passive: bool,
    /// Controller is back to error-active.
    pub active: bool,
    /// RX or TX buffer overflow in the controller.
    pub overflow: bool,
    /// No acknowledgement of a sent frame.
    pub no_ack: bool,
    /// Arbitration lost.
    pub lost_arbitration: bool,
    /// A protocol violation (bit, form, stuff, CRC …).
    pub protocol: bool,
    /// A transceiver (wiring) fault.
    pub transceiver: bool,
    /// The driver timed out sending.
    pub tx_timeout: bool,
}

/// A snapshot of a card's counters.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct CanCounters {
    /// Mapped frames received and decoded.
    pub rx_frames: u64,
    /// Frames with an id the card does not map (the kernel filters should drop these).
    pub rx_unknown_id: u64,
    /// Mapped frames with the wrong payload length (not decoded).
    pub rx_bad_length: u64,
    /// Mapped frames of the wrong kind (classic for FD or the reverse, remote frames).
    pub rx_bad_kind: u64,
    /// Received signal values outside their declared [min|max] (decoded anyway).
    pub rx_out_of_range: u64,
    /// Frames the kernel dropped because the socket's queue was full.
    pub rx_dropped: u64,
    /// Frames sent.
    pub tx_frames: u64,
    /// Sends that failed (buffer full, link down, controller off).
    pub tx_errors: u64,
    /// Cycles of cyclic frames left out because the bus thread woke too late for them
    /// (the schedule keeps its phase instead of sending a burst).
    pub tx_skipped_cycles: u64,
    /// Times a received frame went stale.
    pub stale_events: u64,
    /// Times the link went down.
    pub link_down_events: u64,
    /// Error frames.
    pub error_frames: u64,
    /// Bus-off events.
    pub bus_off: u64,
    /// Error-passive events.
    pub error_passive: u64,
    /// Error-warning events.
    pub error_warning: u64,
    /// Controller restarts.
    pub restarted: u64,
    /// Controller buffer overflows.
    pub controller_overflow: u64,
    /// Missing acknowledgements.
    pub no_ack: u64,
    /// Lost arbitrations.
    pub lost_arbitration: u64,
    /// Protocol violations.
    pub protocol_violations: u64,
    /// Transceiver faults.
    pub transceiver_faults: u64,
    /// Driver transmit timeouts.
    pub tx_timeouts: u64,
    /// The controller state now.
    pub bus_state: Option<BusState>,
    /// The link is up.
    pub link_up: bool,
    /// A real controller's state from netlink (none on vcan).
    pub controller: Option<Controller>,
    /// A J1939 card's node: its NAME, its address claiming and what it did.
    pub j1939: Option<super::J1939Report>,
    /// Each received message: how many came, how long ago the last, whether it is stale
    /// (its own channels then read as stale; the others not).
    pub messages: Vec<MessageState>,
}

/// One received message's state.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct MessageState {
    /// Its name (the DBC message's, or the id in hex).
    pub name: String,
    /// Its CAN id.
    pub id: u32,
    /// Frames of it received.
    pub received: u64,
    /// Since the last one, ms (none: never received).
    pub age_ms: Option<f64>,
    /// Not received within its timeout (or never).
    pub stale: bool,
    /// The ports of its signals (each multiplexed one stale on its own too).
    pub channels: Vec<String>,
}

#[derive(Default)]
pub(super) struct Counters {
    pub(super) rx_frames: AtomicU64,
    pub(super) rx_unknown_id: AtomicU64,
    pub(super) rx_bad_length: AtomicU64,
    pub(super) rx_bad_kind: AtomicU64,
    pub(super) rx_out_of_range: AtomicU64,
    pub(super) rx_dropped: AtomicU64,
    pub(super) tx_frames: AtomicU64,
    pub(super) tx_errors: AtomicU64,
    pub(super) tx_skipped_cycles: AtomicU64,
    pub(super) stale_events: AtomicU64,
    pub(super) link_down_events: AtomicU64,
    pub(super) error_frames: AtomicU64,
    pub(super) bus_off: AtomicU64,
    pub(super) error_passive: AtomicU64,
    pub(super) error_warning: AtomicU64,
    pub(super) restarted: AtomicU64,
    pub(super) controller_overflow: AtomicU64,
    pub(super) no_ack: AtomicU64,
    pub(super) lost_arbitration: AtomicU64,
    pub(super) protocol_violations: AtomicU64,
    pub(super) transceiver_faults: AtomicU64,
    pub(super) tx_timeouts: AtomicU64,
}

pub(super) fn bump(c: &AtomicU64) {
    c.fetch_add(1, Ordering::Relaxed);
}

/// A bus state as a device error cause.
#[derive(Debug, thiserror::Error)]
#[error("CAN controller is {0:?}")]
pub(super) struct BusStateError(pub(super) BusState);

impl CanCard {
    /// Takes what netlink said of the controller (the bus side asks at each link check);
    /// its error state becomes the card's bus state.
    pub fn set_controller(&self, c: Option<Controller>) {
        if let Some(c) = &c {
            let s = match c.state {
                ControllerState::ErrorActive => Some(BusState::ErrorActive),
                ControllerState::ErrorWarning => Some(BusState::ErrorWarning),
                ControllerState::ErrorPassive => Some(BusState::ErrorPassive),
                ControllerState::BusOff => Some(BusState::BusOff),
                // Down or asleep: the link state says so.
                ControllerState::Stopped | ControllerState::Sleeping => None,
            };
            if let Some(s) = s {
                self.follow_state(s);
            }
        }
        let old = self.controller.load();
        if old.as_deref() != c.as_ref() {
            self.controller.store(c.map(Arc::new));
        }
    }

    /// A real controller's state (as netlink last said, with the restarts seen); none for
    /// a virtual interface or before the first link check.
    pub fn controller(&self) -> Option<Controller> {
        self.controller.load().as_deref().map(|c| Controller {
            restarts: self.counters.restarted.load(Ordering::Relaxed),
            ..*c
        })
    }

    /// The counters now.
    pub fn counters(&self) -> CanCounters {
        let c = &self.counters;
        let l = |a: &AtomicU64| a.load(Ordering::Relaxed);
        CanCounters {
            rx_frames: l(&c.rx_frames),
            rx_unknown_id: l(&c.rx_unknown_id),
            rx_bad_length: l(&c.rx_bad_length),
            rx_bad_kind: l(&c.rx_bad_kind),
            rx_out_of_range: l(&c.rx_out_of_range),
            rx_dropped: l(&c.rx_dropped),
            tx_frames: l(&c.tx_frames),
            tx_errors: l(&c.tx_errors),
            tx_skipped_cycles: l(&c.tx_skipped_cycles),
            stale_events: l(&c.stale_events),
            link_down_events: l(&c.link_down_events),
            error_frames: l(&c.error_frames),
            bus_off: l(&c.bus_off),
            error_passive: l(&c.error_passive),
            error_warning: l(&c.error_warning),
            restarted: l(&c.restarted),
            controller_overflow: l(&c.controller_overflow),
            no_ack: l(&c.no_ack),
            lost_arbitration: l(&c.lost_arbitration),
            protocol_violations: l(&c.protocol_violations),
            transceiver_faults: l(&c.transceiver_faults),
            tx_timeouts: l(&c.tx_timeouts),
            bus_state: Some(self.bus_state()),
            controller: self.controller(),
            link_up: self.link_up(),
            j1939: self.claim(),
            messages: self.message_states(),
        }
    }

    /// Each received message's state now.
    fn message_states(&self) -> Vec<MessageState> {
        let now = self.clock.now();
        self.map
            .rx()
            .iter()
            .enumerate()
            .map(|(f, frame)| {
                let last = self.rx[f].last.load(Ordering::Acquire);
                MessageState {
                    name: frame.name.clone(),
                    id: frame.id,
                    received: self.rx[f].count.load(Ordering::Relaxed),
                    age_ms: (last != 0).then(|| {
                        now.duration_since(Timestamp::from_nanos(last - 1))
                            .as_secs_f64()
                            * 1000.0
                    }),
                    stale: self.frame_age_error(f, frame, now).is_some(),
                    channels: frame.signals.iter().map(|s| s.port.clone()).collect(),
                }
            })
            .collect()
    }
}
