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
use std::sync::{Arc, OnceLock, Weak};

/// A server type's build function: its typed section and the context to a server, or
/// every problem of the section, each at its key under the section.
pub type ServerBuildFn<C> =
    fn(&C, &mut ServerContext<'_>) -> Result<Box<dyn Server>, Vec<CardError>>;

/// Everything a server type may use to build its server: its key, the runtime with the
/// registry of the devices the cards registered, the deployment's folder, and the
/// gateway's control protocol in-process.
pub struct ServerContext<'a> {
    name: &'a str,
    runtime: &'a rtt::Runtime,
    base: &'a Path,
    control: ControlLink,
}

impl<'a> ServerContext<'a> {
    /// A context for the server under deployment key `name`, over `runtime` (its registry
    /// holds every card's devices by now); files a section names are relative to `base`;
    /// `control` reaches the gateway's control protocol once it serves.
    pub fn new(
        name: &'a str,
        runtime: &'a rtt::Runtime,
        base: &'a Path,
        control: ControlLink,
    ) -> ServerContext<'a> {
        ServerContext {
            name,
            runtime,
            base,
            control,
        }
    }

    /// The gateway's control protocol, in-process: what `hwgw status`, `hwgw get` and
    /// `hwgw set` ask, carried out by the same code with the same checks.
    pub fn control(&self) -> &ControlLink {
        &self.control
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

/// The gateway's control protocol in-process, as the gateway's control server carries it
/// out for a server: the requests and replies of the control socket, without the socket.
pub trait Control: Send + Sync {
    /// Carries out `request` (one request object of the control protocol, such as
    /// `{"cmd": "status"}`; streams, `watch` and `record`, are not served this way) and
    /// returns its reply's `ok` value, or its error.
    fn request(&self, request: serde_json::Value) -> Result<serde_json::Value, ControlError>;

    /// Carries out stream request `request` (`record`): `each` gets its acknowledgement's
    /// `ok` value, then every line of the stream (a `record` batch: `{"records": …}`),
    /// until it returns false or the gateway stops; an error when the stream could not
    /// begin. Blocks the calling thread throughout.
    fn stream(
        &self,
        request: serde_json::Value,
        each: &mut dyn FnMut(serde_json::Value) -> bool,
    ) -> Result<(), ControlError>;
}

/// A control request that was refused or failed: the protocol's error kind and message.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message} ({kind})")]
pub struct ControlError {
    /// The error kind of the control protocol (`not_found`, `failed`, `stopping`, …).
    pub kind: String,
    /// What went wrong.
    pub message: String,
}

impl ControlError {
    /// An error of `kind` saying `message`.
    pub fn new(kind: &str, message: impl Into<String>) -> ControlError {
        ControlError {
            kind: kind.to_string(),
            message: message.into(),
        }
    }
}

/// Where a server reaches the gateway's [`Control`]: given to every server when it is
/// built, joined to the control server when that starts (so a server built for
/// `hwgw check`, or before the control server, has none yet), and let go with it.
#[derive(Clone, Default)]
pub struct ControlLink(Arc<OnceLock<Weak<dyn Control>>>);

impl ControlLink {
    /// A link not joined yet.
    pub fn new() -> ControlLink {
        ControlLink::default()
    }

    /// Joins the link to `control` (held weakly: the link keeps nothing alive); a link
    /// already joined keeps its first (returns false).
    pub fn join(&self, control: Weak<dyn Control>) -> bool {
        self.0.set(control).is_ok()
    }

    /// Carries out `request` through the joined control; `unavailable` when there is none
    /// (not joined yet, or gone).
    pub fn request(&self, request: serde_json::Value) -> Result<serde_json::Value, ControlError> {
        self.joined()?.request(request)
    }

    /// [`Control::stream`] through the joined control; `unavailable` when there is none.
    /// The link holds the control only while the stream runs.
    pub fn stream(
        &self,
        request: serde_json::Value,
        each: &mut dyn FnMut(serde_json::Value) -> bool,
    ) -> Result<(), ControlError> {
        self.joined()?.stream(request, each)
    }

    fn joined(&self) -> Result<Arc<dyn Control>, ControlError> {
        self.0.get().and_then(Weak::upgrade).ok_or_else(|| {
            ControlError::new("unavailable", "the gateway's control server is not serving")
        })
    }
}

impl std::fmt::Debug for ControlLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let joined = self.0.get().is_some_and(|w| w.strong_count() > 0);
        f.debug_struct("ControlLink")
            .field("joined", &joined)
            .finish()
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
