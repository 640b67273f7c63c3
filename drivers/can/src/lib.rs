//! SocketCAN cards for hwgw.
//!
//! - [`signal`]: DBC-model signals in frame payloads (Intel/Motorola, signed, 64-bit,
//!   IEEE float and double, factor, offset, limits); [`dbc`]: messages and signals from a
//!   DBC file, read by its grammar.
//! - [`section`]: a card's `[card.socketcan]` section as the TOML says it; [`map`]: that
//!   section resolved into frames and channels.
//! - [`card`]: the devices (AnalogIn/Out, DigitalIn/Out, Encoder) over those frames, with
//!   per-frame staleness, link state and bus error counters; no I/O of its own.
//! - [`bus`]: the socket side — a CAN_RAW socket with kernel filters for exactly the
//!   mapped ids, error frames, timestamps, cyclic and on-change sending, link loss and
//!   return — serviced from one file descriptor.
//! - [`j1939`]: J1939-81 address claiming for a card's node, without I/O.
//! - [`netlink`]: a real controller's error state, counters and restart delay from
//!   rtnetlink.
//! - [`component`]: that bus as an rtt component on a file-descriptor activity.
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

pub mod bus;
pub mod card;
pub mod component;
pub mod dbc;
pub mod j1939;
pub mod map;
pub mod netlink;
pub mod plugin;
pub mod section;
pub use can_socket::signal;
