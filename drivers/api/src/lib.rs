//! The contract between a bus driver and the hwgw gateway.
//!
//! A driver is a function from its typed section of a deployment (`[card.<driver>]`) and a
//! [`CardContext`] to a [`BuiltCard`]: a [`Card`], one trait object that gives the gateway
//! everything it needs whatever the bus, and the card's [`BusSide`], handed over by value.
//!
//! The card gives:
//! - its devices, registered under the card's name ([`Card::devices`]);
//! - names for its channels where the bus has better ones than `ch0…` ([`Card::channel_names`]);
//! - its status and counters as one serialisable snapshot ([`Card::status`]);
//! - a one-line summary for the start-up log ([`Card::summary`]);
//! - whether its output read-back is the device's state ([`Card::read_back`]), so that an
//!   output can be put back as hwgw found it;
//! - how the safe values, once written to its outputs, reach the hardware ([`Card::settle`],
//!   told whether the bus side runs).
//!
//! The bus side is the component(s) that do the bus I/O on rtt activities: a run-once
//! value the gateway adds with the card's name and thread settings ([`BusSide::add_to`], a
//! [`BusContext`]), so it is added once by type and a driver keeps no cell to take it
//! from.
//!
//! [`channels`] finds the registry's channels with their IO components and ports, as the
//! northbound servers (MQTT, OPC UA) serve them.
//!
//! A [`Server`] is the other plug-in shape: something served beside the cards (hwgw as a
//! Modbus TCP server), built by a [`ServerBuildFn`] from its typed top-level section over
//! the device registry ([`ServerContext`]), started with the gateway and stopped first at
//! stop.
//!
//! At stop the gateway stops every other component, writes each card's safe values through
//! its [`AnalogOut`](device_interface::AnalogOut) and [`DigitalOut`](device_interface::DigitalOut)
//! devices, lets every card settle them while its bus side still runs, and only then stops
//! the bus sides: a bus component always stops last.
//!
//! A driver lives in a crate of its own (it depends on this crate, `rtt` and
//! `device-interface`, never on the gateway or on another driver) and is registered in the
//! gateway's `DriverTypes` under its name — by hwgw for the drivers it ships, by a user's
//! binary for their own; a server type likewise in `ServerTypes`.
//!
//! ```
//! use driver_api::{BuiltCard, BusSide, Card, CardContext, CardError};
//! use device_interface::CardDevices;
//!
//! /// A card with nothing on it (a real one holds its devices' image).
//! struct Empty;
//!
//! impl Card for Empty {
//!     fn devices(&self) -> CardDevices {
//!         CardDevices::default()
//!     }
//!     fn summary(&self) -> String {
//!         "nothing".into()
//!     }
//! }
//!
//! /// The driver: its section type and its build function.
//! #[derive(serde::Deserialize)]
//! #[serde(deny_unknown_fields)]
//! struct EmptyConfig {}
//!
//! fn build(_: &EmptyConfig, ctx: &mut CardContext<'_>) -> Result<BuiltCard, CardError> {
//!     // Its bus side: a cycle stepped at the card's period (a real one moves the bus
//!     // into it, polls and writes).
//!     let bus = BusSide::periodic(ctx.period(), || {});
//!     Ok(BuiltCard::new(Empty, bus))
//! }
//!
//! let types: driver_api::BuildFn<EmptyConfig> = build;
//! # let _ = types;
//! ```

mod bus;
mod card;
pub mod channels;
mod context;
mod names;
pub mod node;
mod server;

pub use bus::{BuiltCard, BusContext, BusSide, BusTasks, SocketWatch, fd_bus, periodic_bus};
pub use card::{Card, CardStatus, ReadBack, SettleError, wait_while};
pub use context::{BuildFn, CardContext, CardError};
pub use names::{ChannelDetail, ChannelDetails, ChannelNames, NamesError, is_port_name};
pub use server::{
    Control, ControlError, ControlLink, Server, ServerBuildFn, ServerContext, ServerError,
};
