//! Recording to MCAP: the `recorder` component type, the control socket's `record` stream
//! and `hwgw record`, over the same [`taps`] on the runtime and the same
//! [`recording::Capture`].

pub mod cli;
pub mod component;
pub mod stream;
pub mod taps;
