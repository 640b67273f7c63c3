//! hwgw's `script` component type: behaviour without a compiler. A Lua 5.4 script (Lua
//! built from source by `mlua`'s `vendored` feature: nothing to install) runs as an RTT
//! component — its hooks, programs (coroutines resumed once a step, manual L2159–2228)
//! and a state machine (manual L3323–4052) — reaching ports, peers, properties,
//! operations, devices and a logger through the by-name layer, and nothing else (see
//! [`sandbox`]). Road map L64: "a real-time language binding to Lua".
//!
//! Real-time contract: a step allocates in Lua (the collector is stopped while Lua runs
//! and stepped between steps by the component, `gc_step_kb`); memory is bounded
//! (`memory_kb`, an error when exceeded); a call into the script that runs past
//! `max_step_us` is stopped by an instruction-count hook, counted in the `overruns`
//! attribute and is the component's Exception. Run scripts on SCHED_OTHER unless the
//! benchmark (`cargo bench -p script`) shows the step fits the period with room.

mod api;
mod component;
mod devices;
pub mod error;
mod files;
mod host;
pub mod load;
mod operations;
mod peers;
mod ports;
pub mod sandbox;

pub use component::Script;
pub use error::ScriptError;
pub use files::open_regular;
pub use ports::TYPES as PORT_TYPES;

/// The component type's name in a deployment (`type = "script"`).
pub const TYPE: &str = "script";

/// Builds script component `name` (the constructor the gateway registers).
pub fn add(
    runtime: &rtt::Runtime,
    name: &str,
    spec: rtt::ActivitySpec,
) -> Result<rtt::TaskContext, rtt::RuntimeError> {
    runtime.add(name, spec, rtt::InitialState::PreOperational, Script::new)
}
