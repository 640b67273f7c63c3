//! Modbus TCP and RTU cards for hwgw.
//!
//! This crate grows with the Modbus issue. What is here:
//! - [`codec`]: values in registers — u16/i16/u32/i32/u64/i64/f32/f64 with word and byte
//!   order;
//! - [`plan`]: coalescing a register map into as few reads as the protocol allows;
//! - [`map`]: the register map, and which device channel each point is;
//! - [`holes`]: the unmapped addresses a unit refuses, found by reading parts of a refused read;
//! - [`card`]: a unit's devices — images fed by replies, outputs turned into writes;
//! - [`line`](mod@line): the poller of one connection and the units on it;
//! - [`client`]: the poller's Modbus TCP and RTU framing, RTU over TCP too (silences,
//!   broadcast, stale replies);
//! - [`value`]: an analog point's value in the card's image (floats exact);
//! - [`config`]: a card's section of a deployment;
//! - [`server`]: hwgw as a Modbus server over chosen registry devices: its table;
//! - [`pdu`]: requests checked before anything acts on them, replies encoded;
//! - [`framing`]: how the server cuts requests from a stream (MBAP or RTU) and frames
//!   replies;
//! - [`conn`]: one stream served, its requests routed by unit id;
//! - [`shared`]: what a server's streams share (table, limits, units, counters);
//! - [`listener`]: the server's TCP loops, its limits and counters;
//! - [`slave`]: the server as an RTU slave on a serial port (RS-485 mode);
//! - [`gateway`]: gateway mode, other units' requests forwarded to a card's line.
//!
//! ```
//! use driver_modbus::codec::{Layout, Number, ValueType};
//!
//! let l = Layout { ty: ValueType::I32, ..Layout::default() };
//! assert_eq!(l.decode(&[0xFFFF, 0xFFFE])?, Number::Int(-2));
//! # Ok::<(), driver_modbus::codec::CodecError>(())
//! ```

pub mod card;
pub mod client;
pub mod codec;
pub mod component;
pub mod config;
pub mod conn;
pub mod framing;
pub mod gateway;
pub mod holes;
mod limits;
pub mod line;
pub mod listener;
pub mod map;
pub mod pdu;
pub mod plan;
pub mod plugin;
mod point;
pub mod served;
pub mod server;
pub mod shared;
pub mod slave;
#[cfg(feature = "test-server")]
pub mod testing;
pub mod transport;
pub mod value;
