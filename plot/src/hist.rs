//! Lateness histograms: from a recording's steps (linear bins, exact quantiles) or from
//! the runtime's live log2 buckets, one panel per activity with p50, p99 and max marked.

use crate::draw::{Frame, PlotError, legend, on_root};
use plotters::coord::Shift;
use plotters::prelude::*;
use recording::read::Recording;

/// One activity's live histogram: bucket `i` counts wake-ups `2^i..2^(i+1)` ns late.
#[derive(Debug, Clone)]
pub struct LiveHistogram {
    /// The activity (component) name.
    pub name: String,
    /// The buckets.
    pub buckets: Vec<u64>,
    /// The largest lateness seen, ns.
    pub max_ns: u64,
    /// The bucket bound below which half the wake-ups fell, ns (as the runtime's
    /// `ActivityStats::lateness_quantile(0.5)` gives it).
    pub p50_ns: u64,
    /// Likewise for 99 % of them.
    pub p99_ns: u64,
}

/// One panel: bars `(from_us, to_us, count)` and marks `(label, at_us)`.
struct Panel {
    title: String,
    bars: Vec<(f64, f64, u64)>,
    marks: Vec<(String, f64)>,
    log_x: bool,
}

/// Bins for the recording's histograms.
const BINS: usize = 100;

/// The `q` quantile of sorted `v`.
fn quantile(v: &[u64], q: f64) -> u64 {
    let i = ((v.len() as f64 - 1.0) * q).round() as usize;
    v.get(i.min(v.len().saturating_sub(1)))
        .copied()
        .unwrap_or(0)
}

/// Each activity's wake-up lateness in the recording.
pub fn lateness(rec: &Recording, frame: &Frame<'_>) -> Result<(), PlotError> {
    let mut panels = Vec::new();
    for a in &rec.activities {
        let mut late: Vec<u64> = a
            .steps
            .iter()
            .map(|s| s.started_ns.saturating_sub(s.scheduled_ns))
            .collect();
        if late.is_empty() {
            continue;
        }
        late.sort_unstable();
        let max = *late.last().unwrap_or(&0);
        let width = (max as f64 / 1e3 / BINS as f64).max(0.01);
        let mut counts = vec![0u64; BINS + 1];
        for &l in &late {
            let i = ((l as f64 / 1e3) / width) as usize;
            counts[i.min(BINS)] += 1;
        }
        let bars = counts
            .iter()
            .enumerate()
            .filter(|(_, c)| **c > 0)
            .map(|(i, c)| (i as f64 * width, (i + 1) as f64 * width, *c))
            .collect();
        let us = |ns: u64| ns as f64 / 1e3;
        let (p50, p99) = (quantile(&late, 0.5), quantile(&late, 0.99));
        panels.push(Panel {
            title: format!("{}: {} wake-ups", a.activity, late.len()),
            bars,
            marks: vec![
                (format!("p50 {:.1} µs", us(p50)), us(p50)),
                (format!("p99 {:.1} µs", us(p99)), us(p99)),
                (format!("max {:.1} µs", us(max)), us(max)),
            ],
            log_x: false,
        });
    }
    if panels.is_empty() {
        return Err(crate::draw::nothing(rec, NO_WAKE_UPS));
    }
    draw_panels(panels, frame)
}

const NO_WAKE_UPS: &str = "no activity has wake-ups to show (record with steps)";

/// The live histograms (log2 buckets; the marks are bucket bounds, as `hwgw status` says).
pub fn live_lateness(live: &[LiveHistogram], frame: &Frame<'_>) -> Result<(), PlotError> {
    let panels = live
        .iter()
        .filter(|h| h.buckets.iter().any(|&c| c > 0))
        .map(|h| {
            let bars = h
                .buckets
                .iter()
                .enumerate()
                .filter(|(_, c)| **c > 0)
                .map(|(i, c)| {
                    let lo = (1u64 << i.min(62)) as f64 / 1e3;
                    (lo, lo * 2.0, *c)
                })
                .collect();
            let (p50, p99) = (h.p50_ns as f64 / 1e3, h.p99_ns as f64 / 1e3);
            let max = h.max_ns as f64 / 1e3;
            Panel {
                title: format!("{}: {} wake-ups", h.name, h.buckets.iter().sum::<u64>()),
                bars,
                marks: vec![
                    (format!("p50 ≤ {p50:.1} µs"), p50),
                    (format!("p99 ≤ {p99:.1} µs"), p99),
                    (format!("max {max:.1} µs"), max),
                ],
                log_x: true,
            }
        })
        .collect();
    draw_panels(panels, frame)
}

fn draw_panels(panels: Vec<Panel>, frame: &Frame<'_>) -> Result<(), PlotError> {
    if panels.is_empty() {
        return Err(PlotError::Empty(NO_WAKE_UPS.into()));
    }
    on_root!(frame, |root| (|| -> Result<(), String> {
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let cols = if panels.len() > 2 { 2 } else { 1 };
        let areas = root.split_evenly((panels.len().div_ceil(cols), cols));
        for (i, (panel, area)) in panels.iter().zip(areas.iter()).enumerate() {
            draw_panel(panel, area, Palette99::pick(i).to_rgba())?;
        }
        Ok(())
    })())
}

fn draw_panel<DB: DrawingBackend>(
    p: &Panel,
    area: &DrawingArea<DB, Shift>,
    color: RGBAColor,
) -> Result<(), String> {
    let top = p.bars.iter().map(|b| b.2).max().unwrap_or(1) as f64 * 2.0;
    let x_hi = p
        .bars
        .iter()
        .map(|b| b.1)
        .chain(p.marks.iter().map(|m| m.1))
        .fold(0.0, f64::max)
        * 1.1;
    let x_lo = p.bars.iter().map(|b| b.0).fold(f64::MAX, f64::min);
    let mut chart = ChartBuilder::on(area);
    chart
        .caption(&p.title, ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(60);
    macro_rules! body {
        ($chart:expr) => {{
            let mut chart = $chart.map_err(|e| e.to_string())?;
            chart
                .configure_mesh()
                .x_desc("lateness (µs)")
                .light_line_style(TRANSPARENT)
                .y_desc("wake-ups")
                .draw()
                .map_err(|e| e.to_string())?;
            chart
                .draw_series(
                    p.bars.iter().map(|&(a, b, n)| {
                        Rectangle::new([(a, 0.8), (b, n as f64)], color.filled())
                    }),
                )
                .map_err(|e| e.to_string())?;
            for (k, (label, at)) in p.marks.iter().enumerate() {
                let mark = [RED, MAGENTA, BLACK][k % 3];
                chart
                    .draw_series(std::iter::once(PathElement::new(
                        vec![(*at, 0.8), (*at, top)],
                        mark.stroke_width(2),
                    )))
                    .map_err(|e| e.to_string())?
                    .label(label.clone())
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], mark));
            }
            legend(&mut chart)
        }};
    }
    if p.log_x {
        body!(chart.build_cartesian_2d(
            (x_lo.max(1e-3) / 1.5..x_hi.max(x_lo * 2.0)).log_scale(),
            (0.8..top).log_scale()
        ))
    } else {
        body!(chart.build_cartesian_2d(0.0..x_hi.max(0.1), (0.8..top).log_scale()))
    }
}
