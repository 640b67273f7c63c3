//! GPIO cards for hwgw, over the Linux GPIO character device (uAPI v2, `gpiocdev`).
//!
//! - [`config`]: the `[card.gpio]` section: lines by chip and offset or by name, with
//!   bias, polarity, debounce, edges, drive and initial values.
//! - [`chips`]: finding chips (path, name, label) and lines (offset, name).
//! - [`card`]: the devices — DigitalIn, DigitalOut, software quadrature Encoders — over
//!   the requested lines.
//! - [`quad`]: the quadrature decoder.
//! - [`request`]: requesting one chip's lines.
//! - [`bus`]: requesting the lines, reading their edge events without blocking, and
//!   finding a chip again that went away.
//! - [`component`]: that bus side as an rtt component on a file-descriptor activity,
//!   publishing every input edge on its `edges` port.
//! - [`plugin`]: the card as a driver plug-in (`driver = "gpio"`).

pub mod bus;
pub mod card;
pub mod chips;
pub mod component;
pub mod config;
pub mod plugin;
pub mod quad;
pub mod request;
