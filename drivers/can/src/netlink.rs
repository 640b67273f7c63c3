//! A real CAN controller's state as the kernel reports it over rtnetlink (socketcan's
//! netlink feature): error state, bus-error counters, automatic restart delay, bit rate.
//!
//! Virtual interfaces (vcan, vxcan) have none of these: [`query`] answers `None` for them,
//! and the bus side stops asking.

use serde::{Deserialize, Serialize};
use socketcan::nl::{CanInterface, CanState};

/// A controller's state as the kernel names it (`ip -details link show`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ControllerState {
    /// Both error counters below 96.
    ErrorActive,
    /// An error counter at 96 or more.
    ErrorWarning,
    /// An error counter at 128 or more: no active error flags sent.
    ErrorPassive,
    /// The transmit error counter passed 255: off the bus until restarted.
    BusOff,
    /// The interface is down (the controller is not on the bus).
    #[default]
    Stopped,
    /// The controller sleeps.
    Sleeping,
}

/// What the kernel says of a real CAN controller, and what hwgw saw of its restarts.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Controller {
    /// The error state.
    pub state: ControllerState,
    /// The transmit error counter (0–255; bus-off beyond).
    pub tx_errors: u16,
    /// The receive error counter.
    pub rx_errors: u16,
    /// The delay of the kernel's automatic restart after bus-off, ms (0: restarts only by
    /// hand, `ip link set … type can restart`).
    pub restart_ms: u32,
    /// The nominal bit rate, bit/s (0 when the kernel does not say).
    pub bitrate: u32,
    /// Restarts hwgw saw (each restart's error frame), since it opened the interface.
    pub restarts: u64,
}

/// The state of the controller behind interface `ifindex`: `Ok(None)` for an interface that
/// is not a CAN controller (vcan). One netlink round trip on a socket of its own.
pub fn query(ifindex: u32) -> Result<Option<Controller>, socketcan::Error> {
    let params = CanInterface::open_iface(ifindex).can_params()?;
    let Some(state) = params.state else {
        return Ok(None);
    };
    let berr = params.berr_counter;
    Ok(Some(Controller {
        state: match state {
            CanState::ErrorActive => ControllerState::ErrorActive,
            CanState::ErrorWarning => ControllerState::ErrorWarning,
            CanState::ErrorPassive => ControllerState::ErrorPassive,
            CanState::BusOff => ControllerState::BusOff,
            CanState::Stopped => ControllerState::Stopped,
            CanState::Sleeping => ControllerState::Sleeping,
        },
        tx_errors: berr.map_or(0, |b| b.txerr),
        rx_errors: berr.map_or(0, |b| b.rxerr),
        restart_ms: params.restart_ms.unwrap_or(0),
        bitrate: params.bit_timing.map_or(0, |t| t.bitrate),
        restarts: 0,
    }))
}
