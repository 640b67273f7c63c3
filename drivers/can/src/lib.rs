//! SocketCAN cards for hwgw.
//!
//! This crate grows with the CAN issue. What is here: [`signal`], DBC-model signals in
//! frame payloads — Intel and Motorola bit numbering, signed values, factor and offset —
//! which the CAN card will decode received frames with and pack outgoing ones with; and
//! [`dbc`], reading messages and signals from a DBC file with errors by file, line and
//! signal.
//!
//! ```
//! use driver_can::signal::{ByteOrder, Signal};
//!
//! let speed = Signal::new(0, 16, ByteOrder::Intel, false, 0.01, 0.0, "km/h")?;
//! let mut payload = [0u8; 8];
//! speed.insert(&mut payload, 12345)?;
//! assert_eq!(speed.decode(&payload)?, 123.45);
//! # Ok::<(), driver_can::signal::SignalError>(())
//! ```

pub mod dbc;
pub mod signal;
