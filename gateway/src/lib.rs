//! The hwgw service: a deployment file becomes cards, a device registry, IO components,
//! user components and connections in an [`rtt`] runtime, served over a control socket.
//!
//! - [`config`]: the TOML deployment, parsed strictly; [`problems`]: every error located
//!   by file, line, column and key path;
//! - [`types`]: what a deployment may name — [`components`] (component types),
//!   [`drivers`] (bus drivers, plug-ins of [`driver_api`]) and [`servers`] (what is
//!   served beside the cards, plug-ins too);
//! - [`deploy`]: a built gateway: started, watched, stopped with every output at its safe
//!   value (built in phases by the `build` module, changed while it runs by the `reload`
//!   module: only what changed is rebuilt);
//! - [`io`]: every device as a component (channels as ports, methods as operations);
//! - [`outputs`]: the output policy — safe values, `keep`, the output watchdog — and the
//!   guards that refuse writes once the gateway stops;
//! - [`components`]: the component types built into the binary;
//! - [`recorder`]: recording ports and activity steps to MCAP (the `recorder` type, the
//!   control socket's `record` stream behind `hwgw record`);
//! - [`protocol`]: the control protocol's typed requests and replies; [`control`]: its
//!   server on a Unix socket (requests carried out by the `requests` module), placed and
//!   guarded by [`socket`]; [`client`]: its client, with a timeout on every reply;
//! - [`cli`]: the `hwgw` command line, reusable by a binary with its own types (its manual
//!   pages and completions generated from it by the `assets` module); [`serve`]:
//!   `hwgw run` and `hwgw check`; [`table`]: what the CLI prints for people;
//! - [`browse`]: `hwgw browse`, the interactive console.
//!
//! ```
//! use hwgw::{config::Deployment, deploy::Gateway};
//!
//! let text = hwgw::DEMO;
//! let d = Deployment::parse(text, "demo.toml")?;
//! let types = hwgw::types::Types::builtin();
//! let gw = Gateway::build(&d, "demo.toml", text, &types).expect("the demo is valid");
//! assert!(gw.summary().contains("component \"follow\""));
//! # Ok::<(), hwgw::config::ConfigError>(())
//! ```

mod assets;
mod bindings;
pub mod browse;
mod build;
pub mod changes;
pub mod checks;
pub mod cli;
mod cli_changes;
pub mod client;
pub mod components;
pub mod config;
pub mod control;
pub mod deploy;
pub mod drivers;
pub mod forward;
pub mod health;
pub mod io;
pub mod logical;
pub mod outputs;
pub mod problems;
pub mod propfiles;
pub use ::protocol;
pub mod recorder;
mod reload;
pub mod remote;
pub mod remote_services;
mod requests;
pub mod scan;
pub mod serve;
pub mod servers;
pub mod socket;
pub mod table;
pub mod types;
mod watchdog;

/// The embedded default deployment (`config/demo.toml`): simulated cards, so a new user
/// sees values move with no hardware.
pub const DEMO: &str = include_str!("../../config/demo.toml");
