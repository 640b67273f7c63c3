//! hwgw northbound over OPC UA (`[server.opcua]`): how SCADA, MES and HMI software reads
//! and writes a plant's IO. Every channel of the chosen devices is a variable under
//! `Objects/hwgw/<card>/<device>/<channel>` with its type, range and unit, its status from
//! its device's health and its timestamps from the sample; outputs are written through the
//! gateway's `set` with its checks; every component is an object with its ports and its
//! operations as methods; the server's counters are under `Diagnostics`.
//!
//! The server is async-opcua (MPL-2.0, a dependency; RustCrypto, no OpenSSL): endpoints
//! None (loopback only unless allowed), Basic256Sha256 and Aes128_Sha256_RsaOaep, signed
//! or signed and encrypted; its certificate made on first start into the deployment's
//! store, never over one that is there; clients trusted by their certificates in the
//! store's `trusted/` (a refused one is put in `rejected/`); users with roles from a file. Values are read from the device
//! registry every sample period (the cards' own images: nothing on a real-time path waits
//! for a client) and what changed goes to the monitored items, whose sampling intervals,
//! deadband filters and queues async-opcua applies within the section's limits.

mod auth;
mod calls;
pub mod config;
mod nodes;
mod plan;
mod server;
mod space;
mod values;

pub use config::OpcuaConfig;
pub use server::{NAMESPACE, OpcuaServer, StartError};

use driver_api::{CardError, Server, ServerContext};

/// Builds the OPC UA server of a `[server.opcua]` section (nothing is bound or made
/// before it starts).
pub fn build(
    c: &OpcuaConfig,
    ctx: &mut ServerContext<'_>,
) -> Result<Box<dyn Server>, Vec<CardError>> {
    let settings = c.settings(ctx.base());
    let plan = plan::plan(c, ctx.registry(), ctx.runtime());
    let (settings, plan) = match (settings, plan) {
        (Ok(s), Ok(p)) => (s, p),
        (s, p) => return Err(s.err().into_iter().chain(p.err()).flatten().collect()),
    };
    Ok(Box::new(OpcuaServer::new(
        ctx.name(),
        settings,
        plan,
        ctx.registry().clone(),
        ctx.control().clone(),
    )))
}
