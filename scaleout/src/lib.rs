//! hwgw across hosts on Zenoh: one name space of devices over many gateways.
//!
//! - Every device a card of this gateway registered is published under
//!   `hwgw/<gateway>/dev/<interface>/<device>` with its health and the time it was read
//!   ([`wire`]), off the real-time threads.
//! - A device of another gateway is registered here as `<gateway>/<device>`, an
//!   `Arc<dyn DigitalOut>` (…) that a component looks up as a local one ([`remote`]):
//!   reads answer from the latest sample with its age, writes are sent and acknowledged,
//!   health turns stale and offline when samples stop.
//! - Other gateways' writes to this one's outputs, and their control requests, are
//!   answered by queryables ([`node`]); the gateway's own output policy and watchdog apply
//!   to what they drive.
//!
//! The [`Node`] is built with the deployment from its `[zenoh]` section ([`config`]) and
//! is a [`driver_api::Server`] of the gateway: started with it, stopped first at stop.
//! A deployment without `[zenoh]` has no node and opens no socket.

pub mod config;
pub mod local;
pub mod node;
pub mod outbox;
pub mod ports;
pub mod remote;
pub mod session;
pub mod wire;

pub use config::ZenohConfig;
pub use node::{ControlHandler, Node, NodeError, NodeReport};

use std::sync::Arc;

/// A [`Node`] as one of the gateway's servers.
pub struct NodeServer(pub Arc<Node>);

impl driver_api::Server for NodeServer {
    fn name(&self) -> &str {
        "zenoh"
    }

    fn start(&self) -> Result<String, driver_api::ServerError> {
        self.0.start().map_err(driver_api::ServerError::failed)
    }

    fn stop(&self) {
        self.0.stop();
    }

    fn address(&self) -> Option<String> {
        self.0.address()
    }

    fn status(&self) -> Option<driver_api::CardStatus> {
        let r = self.0.report();
        let sum = |f: fn(&node::ImportReport) -> u64| r.imports.iter().map(f).sum::<u64>();
        let summary = node::StatusSummary {
            peers: r.peers.clone(),
            counts: r.counts,
            imported_received: sum(|i| i.received),
            imported_lost: sum(|i| i.lost),
            imported_refused: sum(|i| i.refused),
            writes_sent: sum(|i| i.writes_sent),
            writes_acked: sum(|i| i.writes_acked),
            writes_failed: sum(|i| i.writes_failed),
            writes_retried: sum(|i| i.writes_retried),
            writes_pending: sum(|i| i.writes_pending),
            links: r
                .links
                .iter()
                .map(|k| {
                    format!(
                        "{}: {} received, {} batches lost, {} dropped there, {} refused",
                        k.connection, k.received, k.lost_batches, k.remote_dropped, k.refused
                    )
                })
                .collect(),
            problems: r
                .twin
                .iter()
                .cloned()
                .chain(r.imports.iter().filter_map(|i| {
                    Some(format!(
                        "{} ({}): {}",
                        i.name,
                        wire::interface_key(i.interface),
                        i.problem.as_ref()?
                    ))
                }))
                .collect(),
        };
        let at = self.0.address().unwrap_or_else(|| "not started".into());
        Some(driver_api::CardStatus::new(at, &summary))
    }

    fn health(&self) -> Result<(), driver_api::ServerError> {
        match self.0.address() {
            Some(_) => Ok(()),
            None => Err(driver_api::ServerError::NotStarted(format!(
                "zenoh: {}",
                self.0.name()
            ))),
        }
    }
}
