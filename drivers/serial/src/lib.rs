//! Serial IO boards for hwgw: an Arduino (or any board) running Firmata — StandardFirmata
//! and its kin — as a card: digital in and out, analog in, PWM and servo out, encoders.
//!
//! - [`protocol`]: the Firmata protocol, decoded and encoded by hwgw itself.
//! - [`board`]: what a board says it has (versions, pin capabilities, analog mapping).
//! - [`config`]: the `[card.firmata]` section, checked alone and against the board.
//! - [`card`]: the devices; inputs from the board's reports, outputs marked to be sent.
//! - [`bus`]: the serial line (tokio-serial's builder, mio-serial's non-blocking port), the
//!   hand-shake, the set-up, reconnection.
//! - [`mod@line`]: the serial port (tokio-serial's builder, mio-serial's non-blocking port).
//! - [`component`]: the bus side on a file-descriptor activity.
//! - [`plugin`]: the card as a driver plug-in (`driver = "firmata"`).

pub mod board;
pub mod bus;
pub mod card;
pub mod component;
pub mod config;
pub mod line;
pub mod plugin;
pub mod protocol;

#[cfg(test)]
mod tests;
