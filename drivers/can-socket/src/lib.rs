//! The SocketCAN layer hwgw's CAN drivers share — the DBC cards (`driver-can`) and the
//! CANopen manager (`driver-canopen`) — without knowing each other:
//!
//! - [`socket`]: a non-blocking CAN_RAW socket with kernel filters, receive timestamps and
//!   drop counts, and the checks that an interface can carry a driver's frames;
//! - [`isotp`]: ISO-TP exchanges through the kernel's `CAN_ISOTP` sockets;
//! - [`j1939`]: SAE J1939 parameter groups through the kernel's `CAN_J1939` sockets;
//! - [`link`]: an interface's presence, state and identity from sysfs;
//! - [`signal`]: values in frame payloads as DBC files and CANopen PDOs lay them out
//!   (Intel/Motorola bit order, signed, 64-bit, IEEE float and double, factor, offset);
//! - [`wakeups`]: the timer and wake-up a bus side waits on beside its socket;
//! - [`blocking`]: waiting in the socket itself, interrupted by a signal.
//!
//! ```
//! use can_socket::signal::{ByteOrder, Signal};
//!
//! // A CANopen PDO's second object: 16 bits, little endian, at bit 8.
//! let ai = Signal::new(8, 16, ByteOrder::Intel, true, 1.0, 0.0, "")?;
//! assert_eq!(ai.extract(&[0xFF, 0x18, 0xFC])?, -1000);
//! # Ok::<(), can_socket::signal::SignalError>(())
//! ```

pub mod batch;
pub mod blocking;
pub mod isotp;
pub mod j1939;
pub mod link;
pub mod signal;
pub mod socket;
pub mod wakeups;
