//! comedi cards for hwgw: a data-acquisition board's analog, digital and counter
//! subdevices through comedilib (bindings generated with bindgen, crate `comedi-sys`).
//!
//! - [`board`]: the safe wrapper over comedilib (the crate's only `unsafe`).
//! - [`config`]: the `[card.comedi]` section: the board and its channel groups.
//! - [`layout`]: the section resolved against the board's description (ranges → scales).
//! - [`card`]: the devices; inputs from the last poll, outputs written at once.
//! - [`bus`]: opening the board, setting its outputs up, polling its inputs.
//! - [`plugin`]: the card as a driver plug-in (`driver = "comedi"`).

pub mod board;
pub mod bus;
pub mod card;
pub mod config;
pub mod layout;
pub mod plugin;

#[cfg(test)]
mod fake;
#[cfg(test)]
mod tests;
