//! Line plots (PNG or SVG by the file's extension) of curves such as loss
//! versus iteration or error versus step, drawn with plotters. Text uses
//! the DejaVu Sans font found on the system (Debian's `fonts-dejavu-core`)
//! or the file named by `DIFFSIM_FONT`.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use plotters::prelude::*;

/// One named curve.
#[derive(Clone, Debug)]
pub struct Series {
    /// Legend entry.
    pub name: String,
    /// Points `(x, y)`.
    pub points: Vec<(f64, f64)>,
    /// Colour index in the palette (so that one variant keeps its colour
    /// across plots).
    pub color: usize,
    /// Draw the points as dots without joining them (a scatter plot).
    pub markers: bool,
}

/// Labels and scales of a plot.
#[derive(Clone, Debug)]
pub struct Axes<'a> {
    /// Title above the plot.
    pub title: &'a str,
    /// The x axis label.
    pub x: &'a str,
    /// The y axis label.
    pub y: &'a str,
    /// Logarithmic x axis.
    pub log_x: bool,
    /// Logarithmic y axis.
    pub log_y: bool,
}

/// A plot that could not be written.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// No font for the labels.
    #[error("no font for plot labels (looked for DejaVuSans.ttf in /usr/share/fonts and $DIFFSIM_FONT); install fonts-dejavu-core")]
    NoFont,
    /// The extension is neither `.png` nor `.svg`.
    #[error("{0}: plots are written as .png or .svg")]
    Extension(PathBuf),
    /// Drawing or writing failed.
    #[error("{path}: {reason}")]
    Draw {
        /// The file.
        path: PathBuf,
        /// What failed.
        reason: String,
    },
}

fn font() -> Result<(), PlotError> {
    static LOADED: OnceLock<bool> = OnceLock::new();
    let ok = *LOADED.get_or_init(|| {
        let paths = ["/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf", "/usr/share/fonts/dejavu/DejaVuSans.ttf", "/usr/share/fonts/TTF/DejaVuSans.ttf"];
        let found = std::env::var("DIFFSIM_FONT").ok().and_then(|p| std::fs::read(p).ok()).or_else(|| paths.iter().find_map(|p| std::fs::read(p).ok()));
        match found {
            Some(bytes) => {
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).is_ok()
            }
            None => false,
        }
    });
    if ok { Ok(()) } else { Err(PlotError::NoFont) }
}

/// Writes `series` as a line plot to `path` (`.png`, 800×500, or `.svg`).
/// Non-finite points and, on a log axis, non-positive ones are left out.
pub fn line_plot(path: &Path, axes: &Axes<'_>, series: &[Series]) -> Result<(), PlotError> {
    font()?;
    let draw = |reason: String| PlotError::Draw { path: path.to_path_buf(), reason };
    // The backends open the path themselves: a link planted there goes first.
    diffsim::files::remove_link(path).map_err(|e| draw(e.to_string()))?;
    match path.extension().and_then(|e| e.to_str()) {
        Some("png") => {
            let root = BitMapBackend::new(path, (800, 500)).into_drawing_area();
            draw_on(root, axes, series).map_err(draw)
        }
        Some("svg") => {
            let root = SVGBackend::new(path, (800, 500)).into_drawing_area();
            draw_on(root, axes, series).map_err(draw)
        }
        _ => Err(PlotError::Extension(path.to_path_buf())),
    }
}

/// A tick label with at most three significant digits.
/// Values below `zero` in magnitude are labelled 0 (a linear axis's tick
/// at rounding distance from zero, such as −5.6e−17).
fn tick(v: &f64, zero: f64) -> String {
    let a = v.abs();
    if a <= zero {
        "0".into()
    } else if !(1e-3..1e5).contains(&a) {
        format!("{v:.1e}")
    } else {
        let digits = (2 - a.log10().floor() as i32).max(0) as usize;
        let s = format!("{v:.digits$}");
        if s.contains('.') { s.trim_end_matches('0').trim_end_matches('.').to_string() } else { s }
    }
}

fn keep(axes: &Axes<'_>, (x, y): (f64, f64)) -> bool {
    x.is_finite() && y.is_finite() && (!axes.log_x || x > 0.0) && (!axes.log_y || y > 0.0)
}

fn range(values: impl Iterator<Item = f64>, log: bool) -> std::ops::Range<f64> {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if !lo.is_finite() {
        return if log { 0.1..1.0 } else { 0.0..1.0 };
    }
    if log {
        let (lo, hi) = if hi > lo { (lo, hi) } else { (lo / 2.0, hi * 2.0) };
        lo / 1.2..hi * 1.2
    } else {
        let pad = if hi > lo { 0.05 * (hi - lo) } else { lo.abs().max(1.0) * 0.1 };
        lo - pad..hi + pad
    }
}

fn draw_on<DB: DrawingBackend>(root: DrawingArea<DB, plotters::coord::Shift>, axes: &Axes<'_>, series: &[Series]) -> Result<(), String> {
    let e = |err: &dyn std::fmt::Display| err.to_string();
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let pts = || series.iter().flat_map(|s| s.points.iter().copied()).filter(|&p| keep(axes, p));
    // plotters labels only whole decades on a log axis: one that spans
    // less than a decade is drawn linear so that it keeps its labels.
    let decade = |r: std::ops::Range<f64>| r.end >= 10.0 * r.start;
    let log_x = axes.log_x && decade(range(pts().map(|p| p.0), true));
    let log_y = axes.log_y && decade(range(pts().map(|p| p.1), true));
    let xr = range(pts().map(|p| p.0), log_x);
    let yr = range(pts().map(|p| p.1), log_y);
    let zero = |log: bool, r: &std::ops::Range<f64>| if log { 0.0 } else { 1e-9 * (r.end - r.start).abs() };
    let (zx, zy) = (zero(log_x, &xr), zero(log_y, &yr));
    let (tick_x, tick_y) = (move |v: &f64| tick(v, zx), move |v: &f64| tick(v, zy));
    let mut builder = ChartBuilder::on(&root);
    builder.caption(axes.title, ("sans-serif", 22)).margin(12).x_label_area_size(45).y_label_area_size(75);
    // Four axis kinds; the drawing is the same for each.
    macro_rules! finish {
        ($chart:expr) => {{
            let mut chart = $chart.map_err(|x| e(&x))?;
            chart
                .configure_mesh()
                .x_desc(axes.x)
                .y_desc(axes.y)
                .x_label_formatter(&tick_x)
                .y_label_formatter(&tick_y)
                .label_style(("sans-serif", 14))
                .draw()
                .map_err(|x| e(&x))?;
            for s in series {
                let color = Palette99::pick(s.color).to_rgba();
                let line = s.points.iter().copied().filter(|&p| keep(axes, p));
                // A series without a name draws without a legend entry.
                if s.markers {
                    let drawn = chart.draw_series(line.map(|p| Circle::new(p, 4, color.filled()))).map_err(|x| e(&x))?;
                    if !s.name.is_empty() {
                        drawn.label(s.name.as_str()).legend(move |(x, y)| Circle::new((x + 10, y), 4, color.filled()));
                    }
                } else {
                    let drawn = chart.draw_series(LineSeries::new(line, color.stroke_width(2))).map_err(|x| e(&x))?;
                    if !s.name.is_empty() {
                        drawn.label(s.name.as_str()).legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
                    }
                }
            }
            chart.configure_series_labels().background_style(WHITE.mix(0.85)).border_style(BLACK).label_font(("sans-serif", 14)).draw().map_err(|x| e(&x))?;
        }};
    }
    match (log_x, log_y) {
        (false, false) => finish!(builder.build_cartesian_2d(xr, yr)),
        (false, true) => finish!(builder.build_cartesian_2d(xr, yr.log_scale())),
        (true, false) => finish!(builder.build_cartesian_2d(xr.log_scale(), yr)),
        (true, true) => finish!(builder.build_cartesian_2d(xr.log_scale(), yr.log_scale())),
    }
    root.present().map_err(|x| e(&x))
}
