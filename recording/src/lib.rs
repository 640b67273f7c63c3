//! hwgw recordings: port samples and activity steps written to an MCAP file that Foxglove
//! and PlotJuggler open directly, a triggered window around an event (halscope's use), and
//! the file read back for pictures.
//!
//! - [`item`]: what is recorded — a port's sample with the time it was written, an
//!   activity's step — and the JSON messages and schemas they become;
//! - [`write`](mod@write): the MCAP file: one channel per port (`/component/port`, JSON with a JSON
//!   schema) and per activity (`/activity/<name>`), what was lost counted in its metadata;
//! - [`trigger`]: `comp.port > 3.0`, and the window of `pre` before and `post` after the
//!   moment it became true;
//! - [`file`](mod@file): files hwgw writes, opened without following links, regular files only,
//!   never another's;
//! - [`capture`]: a recording fed through a trigger window when there is one;
//! - [`read`]: a recording back as numeric series and steps.
//!
//! Times in the file are UNIX ns: the runtime's monotonic time plus the offset between the
//! two clocks taken when the recording began (kept in the metadata).

pub mod capture;
pub mod file;
pub mod item;
pub mod read;
pub mod trigger;
pub mod write;

pub use capture::Capture;
pub use item::{Item, PortSpec, Step};
pub use trigger::{Trigger, Window};
pub use write::{Closing, METADATA, Options, RecordError, Recorder, Sink};
