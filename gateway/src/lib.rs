//! The hwgw service: a deployment file becomes cards, a device registry, IO components,
//! user components and connections in an [`rtt`] runtime, served over a control socket.
//!
//! - [`config`]: the TOML deployment, parsed strictly, errors located by file, line,
//!   column and key path;
//! - [`deploy`]: builds and runs a deployment, and stops it with every output at its safe
//!   value;
//! - [`io`]: every device as a component (channels as ports, methods as operations);
//! - [`components`]: the component types built into the binary;
//! - [`control`]: the line-delimited JSON control protocol over a Unix socket;
//! - [`cli`]: the `hwgw` command line, reusable by a binary with its own component types;
//! - [`browse`]: `hwgw browse`, the interactive console.
//!
//! ```
//! use hwgw::{config::Deployment, deploy::Gateway};
//!
//! let text = hwgw::DEMO;
//! let d = Deployment::parse(text, "demo.toml")?;
//! let types = hwgw::components::ComponentTypes::builtin();
//! let gw = Gateway::build(&d, "demo.toml", text, &types).expect("the demo is valid");
//! assert!(gw.summary().contains("component \"follow\""));
//! # Ok::<(), hwgw::config::ConfigError>(())
//! ```

pub mod browse;
pub mod cli;
pub mod components;
pub mod config;
pub mod control;
pub mod deploy;
pub mod io;

/// The embedded default deployment (`config/demo.toml`): simulated cards, so a new user
/// sees values move with no hardware.
pub const DEMO: &str = include_str!("../../config/demo.toml");
