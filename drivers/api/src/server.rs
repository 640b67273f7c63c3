//! The [`Server`] trait: something the gateway serves beside its cards (hwgw as a Modbus
//! TCP server over chosen devices), built over the registry with the deployment, started
//! with the gateway, stopped first at stop so no client write races the safe values.
//!
//! A server type is registered in the gateway's `ServerTypes` under the top-level key of
//! its section (`[modbus_server]`), with a [`ServerBuildFn`] over its typed section: the
//! gateway names no server.

use crate::context::CardError;
use device_interface::Registry;
use std::path::Path;
use std::sync::Arc;

/// A server type's build function: its typed section and the context to a server, or
/// every problem of the section, each at its key under the section.
pub type ServerBuildFn<C> =
    fn(&C, &mut ServerContext<'_>) -> Result<Box<dyn Server>, Vec<CardError>>;

/// Everything a server type may use to build its server: its key, the runtime with the
/// registry of the devices the cards registered, the deployment's folder.
pub struct ServerContext<'a> {
    name: &'a str,
    runtime: &'a rtt::Runtime,
    base: &'a Path,
}

impl<'a> ServerContext<'a> {
    /// A context for the server under deployment key `name`, over `runtime` (its registry
    /// holds every card's devices by now); files a section names are relative to `base`.
    pub fn new(name: &'a str, runtime: &'a rtt::Runtime, base: &'a Path) -> ServerContext<'a> {
        ServerContext {
            name,
            runtime,
            base,
        }
    }

    /// Its deployment key (`modbus_server`): what [`Server::name`] returns.
    pub fn name(&self) -> &'a str {
        self.name
    }

    /// The device registry: every card's devices, aliases, imported devices.
    pub fn registry(&self) -> &'a Arc<Registry> {
        self.runtime.registry()
    }

    /// The runtime of the deployment's components (built, not started).
    pub fn runtime(&self) -> &'a rtt::Runtime {
        self.runtime
    }

    /// The folder of the deployment file: files a section names are relative to it.
    pub fn base(&self) -> &'a Path {
        self.base
    }
}

/// Why a server did not start, or does not serve as it should.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// It could not take its address or what it serves with (a socket, a thread).
    #[error("cannot serve on {address}: {source}")]
    Listen {
        /// Where it was to listen.
        address: String,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// It is not running: never started, or stopped by itself (what is not running).
    #[error("{0} is not started")]
    NotStarted(String),
    /// Its own kind of failure, from its library (a Zenoh session refused, accept failing).
    #[error(transparent)]
    Failed(Box<dyn std::error::Error + Send + Sync>),
}

impl ServerError {
    /// A failure of the server's own kind.
    pub fn failed(e: impl std::error::Error + Send + Sync + 'static) -> ServerError {
        ServerError::Failed(Box::new(e))
    }
}

/// A server of a deployment.
pub trait Server: Send + Sync {
    /// Its deployment key, e.g. `modbus_server` ([`ServerContext::name`]).
    fn name(&self) -> &str;

    /// Starts serving; returns where it listens.
    fn start(&self) -> Result<String, ServerError>;

    /// Stops serving (closing its clients' connections) and waits for that; idempotent.
    fn stop(&self);

    /// Where it listens while running.
    fn address(&self) -> Option<String>;

    /// Its state and counters for `hwgw status` (as a card's: where, and a snapshot).
    /// Default: none.
    fn status(&self) -> Option<crate::CardStatus> {
        None
    }

    /// `Ok` while it serves as it should (part of the gateway's health, which feeds the
    /// systemd watchdog); else what is wrong. Default: `Ok`.
    fn health(&self) -> Result<(), ServerError> {
        Ok(())
    }
}
