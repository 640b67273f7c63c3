//! Component ports across gateways: an exported output port is published, and a
//! connection from another gateway's port (`B/follow.out -> local.in`) feeds a local input
//! port.
//!
//! An export is a stamped buffer connection on the port (its writer stays lock- and
//! allocation-free; a sample that does not fit is dropped and counted there), drained
//! every publication period into one [`PortBatch`] per port. A remote connection is a
//! writer into the local input port with the deployment's connection policy — data,
//! buffer or circular buffer, as between two local ports — so what the local buffer
//! cannot hold is lost and counted by the connection as it would be locally; batches
//! missing on the way are counted by their sequence numbers, and the samples the remote
//! buffer dropped are reported by the remote gateway in every batch.

use rtt::component::{DynReader, DynWriter};
use rtt::port::FlowStatus;
use serde::{Deserialize, Serialize};
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

/// Where gateway `gw` publishes port `port` of component `component`.
pub fn port_key(gw: &str, component: &str, port: &str) -> String {
    format!("hwgw/{gw}/port/{component}/{port}")
}

/// The samples one exported port had since the last batch.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PortBatch {
    /// Counts up by one per batch of this port.
    pub seq: u64,
    /// `(time written, value)`: the monotonic time of the writing step at the publishing
    /// gateway (comparable on one host only), and the value as JSON.
    pub samples: Vec<(u64, serde_json::Value)>,
    /// Samples the export's buffer dropped so far (the port written faster than drained).
    pub dropped: u64,
}

/// An exported port.
pub struct Export {
    /// `component.port`.
    pub name: String,
    key: String,
    reader: Mutex<Box<dyn DynReader>>,
    /// Most samples drained per period (the buffer's size).
    most: usize,
    seq: AtomicU64,
}

impl Export {
    /// The export of `component.port` of gateway `gw`, read through `reader` (a stamped
    /// buffer connection of `most` samples).
    pub fn new(
        gw: &str,
        component: &str,
        port: &str,
        reader: Box<dyn DynReader>,
        most: usize,
    ) -> Self {
        Export {
            name: format!("{component}.{port}"),
            key: port_key(gw, component, port),
            reader: Mutex::new(reader),
            most,
            seq: AtomicU64::new(0),
        }
    }

    /// Its key.
    pub fn key(&self) -> &str {
        &self.key
    }

    /// What came since the last call, as a batch; `None` when nothing did.
    pub fn drain(&self) -> Option<PortBatch> {
        let mut r = self.reader.lock().unwrap_or_else(|p| p.into_inner());
        let mut samples = Vec::new();
        for _ in 0..self.most {
            match r.read_at() {
                (FlowStatus::NewData, Some(v), at) => samples.push((at, v)),
                (FlowStatus::NewData, None, _) => {}
                _ => break,
            }
        }
        if samples.is_empty() {
            return None;
        }
        Some(PortBatch {
            seq: self.seq.fetch_add(1, Ordering::Relaxed) + 1,
            samples,
            dropped: r.dropped(),
        })
    }
}

/// A connection from a port of another gateway into a local input port.
pub struct Link {
    /// `B/follow.out -> local.in`, for messages.
    pub label: String,
    /// The remote gateway.
    pub gateway: String,
    key: String,
    writer: Mutex<Box<dyn DynWriter>>,
    last_seq: AtomicU64,
    /// Samples written into the local port.
    pub received: AtomicU64,
    /// Batches missing from the sequence.
    pub lost_batches: AtomicU64,
    /// Samples the remote export's buffer dropped, as it last said.
    pub remote_dropped: AtomicU64,
    /// Samples the local port refused (not of its type), or in a batch larger than an
    /// export sends.
    pub refused: AtomicU64,
}

impl Link {
    /// The connection from `component.port` of gateway `gw` through `writer`.
    pub fn new(
        gw: &str,
        component: &str,
        port: &str,
        writer: Box<dyn DynWriter>,
        label: String,
    ) -> Self {
        Link {
            label,
            gateway: gw.to_string(),
            key: port_key(gw, component, port),
            writer: Mutex::new(writer),
            last_seq: AtomicU64::new(0),
            received: AtomicU64::new(0),
            lost_batches: AtomicU64::new(0),
            remote_dropped: AtomicU64::new(0),
            refused: AtomicU64::new(0),
        }
    }

    /// Its key.
    pub fn key(&self) -> &str {
        &self.key
    }

    /// Writes batch `b` into the local port.
    pub fn take(&self, b: PortBatch) {
        if b.samples.len() > crate::config::EXPORT_BUFFER {
            // More than an export ever sends: refused whole, not written.
            self.refused
                .fetch_add(b.samples.len() as u64, Ordering::Relaxed);
            return;
        }
        let last = self.last_seq.swap(b.seq, Ordering::AcqRel);
        if last != 0 && b.seq > last {
            let gap = b.seq.saturating_sub(last).saturating_sub(1);
            self.lost_batches.fetch_add(gap, Ordering::Relaxed);
        }
        self.remote_dropped.store(b.dropped, Ordering::Relaxed);
        let mut w = self.writer.lock().unwrap_or_else(|p| p.into_inner());
        for (_, v) in b.samples {
            match w.write(v) {
                Ok(()) => self.received.fetch_add(1, Ordering::Relaxed),
                Err(e) => {
                    if self.refused.fetch_add(1, Ordering::Relaxed) == 0 {
                        tracing::warn!("zenoh: {}: {e}", self.label);
                    }
                    0
                }
            };
        }
    }
}
