//! Values over time and the timing diagram, and what every picture shares: the file
//! format, the size, the font, the time span.

use plotters::coord::CoordTranslate;
use plotters::prelude::*;
use recording::read::Recording;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Why a picture was not made.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PlotError {
    /// The output's extension is neither `.png` nor `.svg`.
    #[error("{0}: expected a .png or .svg file")]
    Format(PathBuf),
    /// The size is outside 64×64 to 8192×8192.
    #[error("{0}×{1} pixels: expected 64 to 8192 each way")]
    Size(u32, u32),
    /// There is nothing to draw.
    #[error("nothing to plot: {0}")]
    Empty(String),
    /// A port asked for is not in the recording.
    #[error("port {port:?} is not in the recording (it has: {known})")]
    UnknownPort {
        /// The port asked for.
        port: String,
        /// The recording's ports.
        known: String,
    },
    /// Drawing or writing the file failed.
    #[error("{path}: {detail}")]
    Draw {
        /// The output.
        path: PathBuf,
        /// Why.
        detail: String,
    },
    /// The file already exists.
    #[error("{0} exists: it is never overwritten; remove it or name another file")]
    Exists(PathBuf),
}

/// A picture's size in pixels.
#[derive(Debug, Clone, Copy)]
pub struct Size {
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
}

impl Default for Size {
    fn default() -> Self {
        Size {
            width: 1280,
            height: 720,
        }
    }
}

/// The part of a recording drawn: from `from_s` after its first item, `span_s` long (all
/// of it when `None`).
#[derive(Debug, Clone, Copy, Default)]
pub struct Span {
    /// Seconds after the recording's first item.
    pub from_s: f64,
    /// Seconds drawn.
    pub span_s: Option<f64>,
}

/// Where a picture goes and how large it is.
pub struct Frame<'a> {
    /// The new file (`.png` or `.svg`).
    pub path: &'a Path,
    /// Its size.
    pub size: Size,
}

pub(crate) enum Format {
    Png,
    Svg,
}

impl Frame<'_> {
    pub(crate) fn check(&self) -> Result<Format, PlotError> {
        let Size { width, height } = self.size;
        if !(64..=8192).contains(&width) || !(64..=8192).contains(&height) {
            return Err(PlotError::Size(width, height));
        }
        match std::fs::symlink_metadata(self.path) {
            Ok(m) if m.file_type().is_symlink() => {
                return Err(self.fail(recording::file::Refusal::Link));
            }
            Ok(_) => return Err(PlotError::Exists(self.path.to_path_buf())),
            Err(_) => {}
        }
        font();
        match self.path.extension().and_then(|e| e.to_str()) {
            Some(e) if e.eq_ignore_ascii_case("png") => Ok(Format::Png),
            Some(e) if e.eq_ignore_ascii_case("svg") => Ok(Format::Svg),
            _ => Err(PlotError::Format(self.path.to_path_buf())),
        }
    }

    /// Creates the file new (never through a link, never an existing name: see
    /// [`recording::file::create_new`]) and writes `bytes`.
    pub(crate) fn write(&self, bytes: &[u8]) -> Result<(), PlotError> {
        use recording::file::Refusal;
        use std::io::Write;
        let mut f = recording::file::create_new(self.path).map_err(|e| match e.why {
            Refusal::Exists => PlotError::Exists(self.path.to_path_buf()),
            why => self.fail(why),
        })?;
        f.write_all(bytes).map_err(|e| {
            // Made new above: a half-written picture is ours to remove.
            let _ = std::fs::remove_file(self.path);
            self.fail(e)
        })
    }

    pub(crate) fn fail(&self, detail: impl std::fmt::Display) -> PlotError {
        PlotError::Draw {
            path: self.path.to_path_buf(),
            detail: detail.to_string(),
        }
    }
}

/// Draws in memory on a PNG or SVG root area per the frame's format — `$body` (an
/// expression of type `Result<(), String>` using `$root`) is expanded once per backend —
/// then writes the new file (never one that exists, even if made meanwhile).
macro_rules! on_root {
    ($frame:expr, |$root:ident| $body:expr) => {{
        let frame = $frame;
        let dims = (frame.size.width, frame.size.height);
        let bytes: Result<Vec<u8>, String> = match frame.check()? {
            $crate::draw::Format::Png => {
                let mut rgb = vec![0u8; dims.0 as usize * dims.1 as usize * 3];
                let drawn = {
                    let $root = &BitMapBackend::with_buffer(&mut rgb, dims).into_drawing_area();
                    $body.and_then(|()| $root.present().map_err(|e| e.to_string()))
                };
                drawn.and_then(|()| $crate::draw::png(&rgb, dims))
            }
            $crate::draw::Format::Svg => {
                let mut svg = String::new();
                let drawn = {
                    let $root = &SVGBackend::with_string(&mut svg, dims).into_drawing_area();
                    $body.and_then(|()| $root.present().map_err(|e| e.to_string()))
                };
                drawn.map(|()| svg.into_bytes())
            }
        };
        let bytes = bytes.map_err(|e| frame.fail(e))?;
        frame.write(&bytes)
    }};
}

/// RGB pixels as a PNG file's bytes.
pub(crate) fn png(rgb: &[u8], (w, h): (u32, u32)) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, w, h);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    enc.write_header()
        .and_then(|mut w| w.write_image_data(rgb))
        .map_err(|e| e.to_string())?;
    Ok(out)
}
pub(crate) use on_root;

/// Draws a chart's legend box (its series' labels).
pub(crate) fn legend<'a, DB, CT>(chart: &mut ChartContext<'a, DB, CT>) -> Result<(), String>
where
    DB: DrawingBackend + 'a,
    CT: CoordTranslate,
{
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| e.to_string())
}

/// Registers the built-in font once.
fn font() {
    static DONE: OnceLock<()> = OnceLock::new();
    DONE.get_or_init(|| {
        for style in [FontStyle::Normal, FontStyle::Bold] {
            // DejaVu Sans is a valid font: registering it cannot fail.
            let _ = plotters::style::register_font("sans-serif", style, dejavu::sans::regular());
        }
    });
}

/// Keeps every `n`th point so at most [`MAX_POINTS`](crate::MAX_POINTS) remain.
pub(crate) fn thin<T: Copy>(points: &[T]) -> Vec<T> {
    let n = points.len().div_ceil(crate::MAX_POINTS).max(1);
    points.iter().step_by(n).copied().collect()
}

/// Nothing to draw: a recording with no messages says whether it is cut (`cut after 0
/// messages: …`) or complete and empty; one with messages, `otherwise`.
pub(crate) fn nothing(rec: &Recording, otherwise: &str) -> PlotError {
    if rec.messages == 0 {
        PlotError::Empty(rec.condition())
    } else {
        PlotError::Empty(otherwise.to_string())
    }
}

/// The recording's first time, UNIX ns.
fn origin(rec: &Recording) -> Option<u64> {
    let ports = rec
        .ports
        .iter()
        .filter_map(|s| s.points.first().map(|p| p.0));
    let steps = rec
        .activities
        .iter()
        .filter_map(|a| a.steps.first().map(|s| s.started_ns));
    ports.chain(steps).min()
}

fn in_span(span: &Span, t: f64) -> bool {
    t >= span.from_s && span.span_s.is_none_or(|s| t <= span.from_s + s)
}

/// The values of `ports` (all when empty) over time.
pub fn values(
    rec: &Recording,
    ports: &[String],
    span: Span,
    frame: &Frame<'_>,
) -> Result<(), PlotError> {
    let known = || {
        let v: Vec<&str> = rec.ports.iter().map(|s| s.port.as_str()).collect();
        v.join(", ")
    };
    for p in ports {
        if !rec.ports.iter().any(|s| &s.port == p) {
            return Err(PlotError::UnknownPort {
                port: p.clone(),
                known: known(),
            });
        }
    }
    let t0 = origin(rec).ok_or_else(|| nothing(rec, "no numeric samples"))?;
    let series: Vec<(&str, Vec<(f64, f64)>)> = rec
        .ports
        .iter()
        .filter(|s| ports.is_empty() || ports.contains(&s.port))
        .map(|s| {
            let pts: Vec<(f64, f64)> = s
                .points
                .iter()
                .map(|&(t, v)| (t.saturating_sub(t0) as f64 / 1e9, v))
                .filter(|&(t, v)| in_span(&span, t) && v.is_finite())
                .collect();
            let pts = thin(&pts);
            // A value holds until the next sample: drawn as steps (a bool's square wave
            // stays square), unless the samples are too many to tell the difference.
            let held = if pts.len() < crate::MAX_POINTS / 2 {
                let mut v = Vec::with_capacity(pts.len() * 2);
                for (i, &(t, y)) in pts.iter().enumerate() {
                    if i > 0 {
                        v.push((t, pts[i - 1].1));
                    }
                    v.push((t, y));
                }
                v
            } else {
                pts
            };
            (s.port.as_str(), held)
        })
        .collect();
    let all = series.iter().flat_map(|(_, p)| p.iter());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(t, v) in all {
        (x0, x1, y0, y1) = (x0.min(t), x1.max(t), y0.min(v), y1.max(v));
    }
    if x0 > x1 {
        return Err(PlotError::Empty("no numeric samples in the span".into()));
    }
    // Halves first: the range of values near ±f64::MAX is itself finite then.
    let pad = ((y1 / 2.0 - y0 / 2.0) * 0.1)
        .max(y0.abs().max(y1.abs()) * 1e-9)
        .max(1e-9);
    let (y0, y1) = (y0 - pad, y1 + pad);
    if !(y0.is_finite() && y1.is_finite() && (y1 - y0).is_finite()) {
        return Err(PlotError::Empty(format!(
            "values up to {:e}: too large to draw (at most ±{:e})",
            y0.abs().max(y1.abs()),
            f64::MAX / 4.0
        )));
    }
    let x1 = if x1 > x0 { x1 } else { x0 + 1e-3 };
    on_root!(frame, |root| (|| -> Result<(), String> {
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let mut chart = ChartBuilder::on(root)
            .caption("port values", ("sans-serif", 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .x_desc("time (s)")
            .y_desc("value")
            .draw()
            .map_err(|e| e.to_string())?;
        for (i, (name, pts)) in series.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            chart
                .draw_series(LineSeries::new(pts.iter().copied(), color.stroke_width(2)))
                .map_err(|e| e.to_string())?
                .label(*name)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color));
        }
        legend(&mut chart)
    })())
}

/// How long the timing diagram shows when no span is given: a logic analyser's screen.
pub const TIMING_SPAN_S: f64 = 0.1;

/// Each activity's steps as a trace: high while it steps (ThreadScope's bit); the first
/// [`TIMING_SPAN_S`] from `span.from_s` unless the span says otherwise, and at most
/// [`MAX_POINTS`](crate::MAX_POINTS)` / 4` steps of each activity.
pub fn timing(rec: &Recording, span: Span, frame: &Frame<'_>) -> Result<(), PlotError> {
    let t0 = origin(rec).ok_or_else(|| nothing(rec, "no numeric samples or steps"))?;
    let span = Span {
        span_s: Some(span.span_s.unwrap_or(TIMING_SPAN_S)),
        ..span
    };
    let rows: Vec<(&str, Vec<(f64, f64)>)> = rec
        .activities
        .iter()
        .enumerate()
        .map(|(i, a)| {
            let base = i as f64;
            let mut pts = Vec::new();
            for s in &a.steps {
                let up = s.started_ns.saturating_sub(t0) as f64 / 1e6;
                let down = s.ended_ns.saturating_sub(t0) as f64 / 1e6;
                if !in_span(&span, up / 1e3) {
                    continue;
                }
                if pts.len() >= crate::MAX_POINTS {
                    break;
                }
                pts.extend([
                    (up, base),
                    (up, base + 0.7),
                    (down, base + 0.7),
                    (down, base),
                ]);
            }
            (a.activity.as_str(), pts)
        })
        .collect();
    if rows.iter().all(|(_, p)| p.is_empty()) {
        return Err(PlotError::Empty(
            "no activity steps in the span (record with steps)".into(),
        ));
    }
    let x0 = span.from_s * 1e3;
    let x1 = (span.from_s + span.span_s.unwrap_or(TIMING_SPAN_S)) * 1e3;
    let n = rows.len();
    on_root!(frame, |root| (|| -> Result<(), String> {
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let mut chart = ChartBuilder::on(root)
            .caption("activity steps (ThreadScope)", ("sans-serif", 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(10)
            .build_cartesian_2d(x0..x1, -0.2..(n as f64))
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .x_desc("time (ms)")
            .y_labels(0)
            .disable_y_mesh()
            .draw()
            .map_err(|e| e.to_string())?;
        for (i, (name, pts)) in rows.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            chart
                .draw_series(LineSeries::new(pts.iter().copied(), color.stroke_width(2)))
                .map_err(|e| e.to_string())?;
            let label = Text::new(name.to_string(), (x0, i as f64 + 0.78), ("sans-serif", 15));
            chart
                .draw_series(std::iter::once(label))
                .map_err(|e| e.to_string())?;
        }
        Ok(())
    })())
}
