//! The component's side of a script's Lua state (the state's app data): who it is, its
//! ports, the registry, and what the running call asked of the error model.

use crate::ports::PortMap;
use rtt::component::SelfRef;
use std::path::PathBuf;
use std::sync::Arc;

/// What the error model's requests from a step ask for, done once the step returns.
#[derive(Default, Debug, Clone)]
pub struct Requests {
    /// `rtt.error()`: to RunTimeError.
    pub error: bool,
    /// `rtt.recover()`: back to Running.
    pub recover: bool,
    /// `rtt.warning()`.
    pub warning: bool,
    /// `rtt.recovered()`.
    pub recovered: bool,
    /// `rtt.exception(reason)`.
    pub exception: Option<String>,
}

/// The component's side of a Lua state (its app data).
pub struct Host {
    /// The component's name.
    pub name: String,
    /// The component itself, for ports and peers.
    pub me: SelfRef,
    /// Its ports.
    pub ports: PortMap,
    /// Ports may be declared (the script's top level is running).
    pub declaring: bool,
    /// What the running step asked for.
    pub requests: Requests,
    /// How long the call under way may still take (a script's `call` waits no longer).
    pub deadline: crate::sandbox::Deadline,
    /// Whether `requests` holds anything (looked at without the app data's lookup).
    pub asked: Arc<std::sync::atomic::AtomicBool>,
    /// The device registry.
    pub registry: Arc<device_interface::Registry>,
    /// The folder `io.open` may reach, if any.
    pub data_dir: Option<PathBuf>,
}

impl Requests {
    /// Adds what `other` asks to what this asks.
    pub fn merge(&mut self, other: Requests) {
        self.error |= other.error;
        self.recover |= other.recover;
        self.warning |= other.warning;
        self.recovered |= other.recovered;
        if other.exception.is_some() {
            self.exception = other.exception;
        }
    }
}

impl Host {
    /// Records a request of the error model.
    pub fn ask(&mut self, f: impl FnOnce(&mut Requests)) {
        f(&mut self.requests);
        self.asked.store(true, std::sync::atomic::Ordering::Relaxed);
    }
}
