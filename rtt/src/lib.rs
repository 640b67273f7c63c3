//! An Orocos-RTT-2.x-style component runtime: the part of hwgw that hosts drivers and
//! users' components.
//!
//! - [`runtime`]: the [`Runtime`] that holds the components, the device registry they
//!   share, the clock and ThreadScope;
//! - [`component`]: the [`Component`] hooks and the [`TaskContext`] lifecycle
//!   ([`state`]: Init, PreOperational, Stopped, Running, RunTimeError, Exception,
//!   FatalError), with every port, operation, property and attribute declared through an
//!   [`InterfaceBuilder`] and reachable by name with JSON values;
//! - [`port`]: `OutputPort<T>`/`InputPort<T>` with data, buffer and circular-buffer
//!   connections, lock-free and allocation-free;
//! - [`operation`]: ClientThread and OwnThread operations with `call`, `send` and
//!   `collect`;
//! - [`property`]: typed, documented, nested properties loaded from and saved to TOML;
//! - [`activity`]: periodic, non-periodic, file-descriptor and slave activities with
//!   timing statistics;
//! - [`service`]: services provided and required, bound at deployment, with loss and
//!   return told to the requiring component;
//! - [`scope`]: ThreadScope, each runtime thread as a bit on a digital output;
//! - [`time`]: the monotonic clock and its simulated twin;
//! - [`faults`]: one policy for missed device readings: a warning, then RunTimeError;
//! - [`error`] and [`info`]: what goes wrong, and what is listed about ports;
//! - [`typename`]: the control protocol's names of the types listed (`f64`, `string`,
//!   `[u32]`, `f64?`), never Rust paths;
//! - [`lock`](mod@lock): the one way this crate (and its users) lock plain data.
//!
//! ```
//! use device_interface::Registry;
//! use rtt::{ActivitySpec, Component, Context, HookResult, InitialState, Runtime, RuntimeOptions};
//! use rtt::port::{FlowStatus, InputPort, OutputPort};
//! use std::sync::Arc;
//!
//! struct Doubler {
//!     input: InputPort<f64>,
//!     output: OutputPort<f64>,
//! }
//!
//! impl Component for Doubler {
//!     fn update_hook(&mut self, _ctx: &mut Context<'_>) -> HookResult {
//!         let mut x = 0.0;
//!         if self.input.read(&mut x) == FlowStatus::NewData {
//!             self.output.write(&(2.0 * x));
//!         }
//!         Ok(())
//!     }
//! }
//!
//! let runtime = Runtime::new(Arc::new(Registry::new()), RuntimeOptions::default())?;
//! let task = runtime.add("doubler", ActivitySpec::Slave, InitialState::Stopped, |iface| {
//!     Ok(Doubler {
//!         input: iface.input("in", "a number")?,
//!         output: iface.output("out", "twice the number")?,
//!     })
//! })?;
//! let mut w = task.port("in")?.writer(Default::default())?;
//! let mut r = task.port("out")?.reader(Default::default())?;
//! task.start()?;
//! w.write(serde_json::json!(21.0))?;
//! task.step()?;
//! assert_eq!(r.read().1, Some(serde_json::json!(42.0)));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

pub mod activity;
pub mod bounded;
pub mod component;
pub mod error;
pub mod faults;
pub mod histogram;
pub mod info;
pub mod lock;
pub mod log;
pub mod operation;
pub mod port;
pub mod property;
pub mod runtime;
pub mod scope;
pub mod service;
mod spin;
pub mod state;
pub mod typename;

/// Monotonic time for the runtime (shared with the device interfaces).
pub mod time {
    pub use device_interface::time::{Clock, MonotonicClock, SimClock, Timestamp};
}

pub use activity::{ActivitySpec, SchedPolicy, ThreadOptions, Timing};
pub use component::{Component, Context, HookError, HookResult, InterfaceBuilder, TaskContext};
pub use error::RuntimeError;
pub use lock::lock;
pub use runtime::{Runtime, RuntimeOptions};
pub use state::{InitialState, TaskState};
