//! hwgw's pictures, PNG or SVG by the file's extension, drawn with plotters and the DejaVu
//! font built in (no browser, no system fonts):
//!
//! - [`values`]: ports' values over time from a recording;
//! - [`timing`]: each activity's steps as a logic-analyser trace (the ThreadScope view);
//! - [`lateness`]: each activity's wake-up lateness histogram from a recording's steps,
//!   with p50, p99 and max marked (the figure people compare with cyclictest's);
//! - [`live_lateness`]: the same from the runtime's live log2 histograms (`hwgw status
//!   --plot`).
//!
//! Every series is thinned to at most [`MAX_POINTS`] points, so a long recording draws in
//! bounded time and memory.

mod draw;
mod hist;

pub use draw::{Frame, PlotError, Size, Span, TIMING_SPAN_S, timing, values};
pub use hist::{LiveHistogram, lateness, live_lateness};

/// The most points drawn of one series.
pub const MAX_POINTS: usize = 20_000;
