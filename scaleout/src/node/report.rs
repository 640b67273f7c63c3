//! What the node tells `hwgw status`: its counters, each import's and each remote
//! connection's.

use device_interface::Interface;
use serde::Serialize;

/// The node's state and counters, for `hwgw status`.
#[derive(Debug, Clone, Serialize)]
pub struct NodeReport {
    /// This gateway's name.
    pub name: String,
    /// Its Zenoh id, once started.
    pub zid: Option<String>,
    /// The peers (or routers) it is connected to now.
    pub peers: Vec<String>,
    /// Its own counters.
    #[serde(flatten)]
    pub counts: NodeCounts,
    /// Every imported interface.
    pub imports: Vec<ImportReport>,
    /// Every connection from another gateway's port.
    pub links: Vec<LinkReport>,
    /// Another gateway answering to this one's name, if one was seen.
    pub twin: Option<String>,
}

/// The node's own counters (not an import's or a connection's).
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct NodeCounts {
    /// Samples published.
    pub published: u64,
    /// Publications that failed.
    pub publish_failed: u64,
    /// Writes of other gateways carried out.
    pub writes_served: u64,
    /// Writes of other gateways refused (some value, or the whole write).
    pub writes_refused: u64,
    /// Writes of other gateways sent again (or superseded): acknowledged, not written again.
    pub writes_repeated: u64,
    /// Control requests of other gateways answered.
    pub controls_served: u64,
    /// Messages that did not parse.
    pub bad_messages: u64,
}

/// A connection from another gateway's port, for `hwgw status`.
#[derive(Debug, Clone, Serialize)]
pub struct LinkReport {
    /// `B/follow.out -> local.in`.
    pub connection: String,
    /// Samples written into the local port.
    pub received: u64,
    /// Batches lost on the way.
    pub lost_batches: u64,
    /// Samples the remote export dropped.
    pub remote_dropped: u64,
    /// Samples the local port refused.
    pub refused: u64,
}

/// One imported interface, for `hwgw status`.
#[derive(Debug, Clone, Serialize)]
pub struct ImportReport {
    /// Its name here (`B/sim0`).
    pub name: String,
    /// Its interface.
    pub interface: Interface,
    /// Samples received, lost on the way, refused.
    pub received: u64,
    /// Samples missing from the sequence.
    pub lost: u64,
    /// Samples refused.
    pub refused: u64,
    /// Writes sent, acknowledged, refused.
    pub writes_sent: u64,
    /// Writes acknowledged.
    pub writes_acked: u64,
    /// Writes refused.
    pub writes_refused: u64,
    /// Writes without an acknowledgement within `request_timeout_ms` (one a channel).
    pub writes_failed: u64,
    /// Messages sent again while waiting for an acknowledgement.
    pub writes_retried: u64,
    /// Outputs with a write on its way now (neither acknowledged nor failed yet).
    pub writes_pending: u64,
    /// Its last problem.
    pub problem: Option<String>,
}

/// The node's counters as `hwgw status` shows them: the imports summed, their problems
/// listed (each import's own counters are in [`NodeReport`]).
#[derive(Debug, Clone, Serialize)]
pub struct StatusSummary {
    /// Peers and routers connected now (their Zenoh ids).
    pub peers: Vec<String>,
    /// The node's own counters.
    #[serde(flatten)]
    pub counts: NodeCounts,
    /// Samples of imported devices taken.
    pub imported_received: u64,
    /// ... missing from their sequence.
    pub imported_lost: u64,
    /// ... refused (shape unknown or not matching).
    pub imported_refused: u64,
    /// Writes sent to other gateways.
    pub writes_sent: u64,
    /// ... that they acknowledged.
    pub writes_acked: u64,
    /// ... that got no acknowledgement within `request_timeout_ms` (one a channel).
    pub writes_failed: u64,
    /// ... sent again while waiting for an acknowledgement.
    pub writes_retried: u64,
    /// Outputs with a write on its way now.
    pub writes_pending: u64,
    /// Each import's problem.
    pub problems: Vec<String>,
    /// Each connection from another gateway's port and its counters.
    pub links: Vec<String>,
}
