//! I2C cards for hwgw: register-based chips on an i2c-dev bus, polled over SMBus
//! transfers (what every adapter and the kernel's i2c-stub answer).
//!
//! - [`config`]: the `[card.i2c]` section: the bus and its chips.
//! - [`smbus`]: byte and word register transfers to one chip.
//! - [`chips`]: the chip models, one file per chip (its module doc says how to add one).
//! - [`card`]: the devices over the chips' images.
//! - [`bus`]: polling each chip on its period, offline chips probed with a backoff.
//! - [`component`]: that bus side as an rtt component.
//! - [`plugin`]: the card as a driver plug-in (`driver = "i2c"`).

pub mod bus;
pub mod card;
pub mod chips;
pub mod component;
pub mod config;
pub mod plugin;
pub mod smbus;
