//! A J1939 card's side: received parameter groups matched by PGN (a frame that pins the
//! source address before one that does not), and the node's address claiming as the bus
//! side reports it, which decides whether the card's J1939 groups can be sent: while the
//! node holds no address, writes to their outputs are refused with the reason.

use super::status::bump;
use super::{CanCard, Received};
use crate::j1939::{ClaimCounts, State};
use can_socket::j1939::{Name, Pgn};
use device_interface::DeviceError;
use device_interface::time::Timestamp;
use std::sync::Arc;

/// A J1939 card's node as `hwgw status` shows it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct J1939Report {
    /// Its NAME, hex.
    pub name: String,
    /// Where its claiming stands.
    pub claim: State,
    /// What the claiming did.
    #[serde(flatten)]
    pub counts: ClaimCounts,
}

/// Why a J1939 group cannot be sent.
#[derive(Debug, thiserror::Error)]
#[error(
    "J1939: NAME {0} holds no source address (it lost its claim to a lower NAME and cannot claim another)"
)]
struct NoAddress(Name);

impl CanCard {
    /// Decodes a received J1939 parameter group into the channels of the rx frame it
    /// matches, and its signals' physical values into `values` (as
    /// [`receive_with_values`](Self::receive_with_values)).
    pub fn receive_j1939(
        &self,
        pgn: Pgn,
        source: u8,
        priority: u8,
        data: &[u8],
        at: Timestamp,
        values: &mut Vec<f64>,
    ) -> Received {
        values.clear();
        let matching = |pinned: bool| {
            self.map.rx().iter().position(|f| {
                f.j1939.is_some_and(|j| {
                    j.pgn == pgn
                        && j.source.is_some() == pinned
                        && j.source.is_none_or(|s| s == source)
                        && j.priority.is_none_or(|p| p == priority)
                })
            })
        };
        let Some(f) = matching(true).or_else(|| matching(false)) else {
            bump(&self.counters.rx_unknown_id);
            return Received::UnknownId;
        };
        self.decode(f, data, at, Some(values))
    }

    /// Takes the node's claiming as the bus side reports it.
    pub fn set_claim(&self, name: Name, claim: State, counts: ClaimCounts) {
        let lost = claim == State::CannotClaim;
        if lost != self.no_address.load().is_some() {
            self.no_address
                .store(lost.then(|| Arc::new(DeviceError::bus(NoAddress(name)))));
        }
        self.claim.store(Some(Arc::new(J1939Report {
            name: name.to_string(),
            claim,
            counts,
        })));
    }

    /// The node's claiming (J1939 cards with a NAME, once the bus side has started).
    pub fn claim(&self) -> Option<J1939Report> {
        self.claim.load().as_deref().cloned()
    }

    /// Why the card's J1939 groups cannot be sent now (its node holds no address), if it
    /// has any and they cannot.
    pub fn unsendable(&self) -> Option<DeviceError> {
        let e = self.no_address.load_full()?;
        self.map
            .tx()
            .iter()
            .any(|f| f.j1939.is_some())
            .then(|| (*e).clone())
    }

    /// `Ok` unless tx frame `tx` is a J1939 group and the node holds no address.
    pub(super) fn check_sendable(&self, tx: u32) -> Result<(), DeviceError> {
        let j1939 = self
            .map
            .tx()
            .get(tx as usize)
            .is_some_and(|f| f.j1939.is_some());
        match self.no_address.load_full() {
            Some(e) if j1939 => Err((*e).clone()),
            _ => Ok(()),
        }
    }

    /// `Ok` unless some digital output sits in a J1939 group and the node holds no
    /// address (the digital outputs are written as one image).
    pub(super) fn check_digital_sendable(&self) -> Result<(), DeviceError> {
        if self.no_address.load().is_none() {
            return Ok(());
        }
        self.do_frame
            .iter()
            .try_for_each(|&f| self.check_sendable(f))
    }
}
