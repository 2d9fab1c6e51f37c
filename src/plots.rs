//! Line plots stacked in panels sharing one x axis (traces, reward curves).

use std::path::Path;

use anyhow::Context;
use plotters::prelude::*;

/// One panel: a y-axis label and named series (same length as x).
pub struct Panel {
    pub y_label: String,
    pub series: Vec<(String, Vec<f64>)>,
    /// Shaded bands (series index, low, high) in their series' colour.
    pub bands: Vec<(usize, Vec<f64>, Vec<f64>)>,
    /// This panel's own x values (else the figure's shared x).
    pub x: Option<Vec<f64>>,
    /// Horizontal reference lines (name, y): LQR, a = 0, best constant, …
    pub references: Vec<(String, f64)>,
    /// Reward curves: let the y axis ignore the few worst values (early
    /// episodes can be 1000× worse than the rest and would flatten every
    /// curve into a line); values below the axis sit on its bottom edge and
    /// the axis label says how many.
    pub clip_low_outliers: bool,
    /// Few points (one per N, say): each drawn as a dot and its band as an
    /// error bar, so that a series with a single point shows. (In every
    /// panel a NaN value is a gap in its line.)
    pub markers: bool,
}

impl Panel {
    /// A panel of series with no band, references or clipping.
    pub fn lines(y_label: impl Into<String>, series: Vec<(String, Vec<f64>)>) -> Self {
        Panel { y_label: y_label.into(), series, bands: Vec::new(), x: None, references: Vec::new(), clip_low_outliers: false, markers: false }
    }

    /// A reward-curve panel: low outliers clipped, with reference lines.
    pub fn rewards(y_label: impl Into<String>, series: Vec<(String, Vec<f64>)>, references: Vec<(String, f64)>) -> Self {
        Panel { y_label: y_label.into(), series, bands: Vec::new(), x: None, references, clip_low_outliers: true, markers: false }
    }
}

/// The bottom of a reward panel's y axis: the worst value of the second
/// half of each curve (where a run settles), less twice the spread from
/// there to the best value. Early episodes far below that sit on
/// the axis's bottom edge. None when nothing lies below it (or a curve is
/// too short to have a settled half): then the whole curve is drawn.
pub fn robust_low(series: &[&[f64]]) -> Option<f64> {
    let finite = |v: &[f64]| v.iter().copied().filter(|x| x.is_finite()).collect::<Vec<f64>>();
    let mut late_min = f64::INFINITY;
    let (mut lowest, mut highest) = (f64::INFINITY, f64::NEG_INFINITY);
    for values in series {
        let all = finite(values);
        if all.len() < 20 {
            return None;
        }
        let late = &all[all.len() / 2..];
        late_min = late.iter().copied().fold(late_min, f64::min);
        lowest = all.iter().copied().fold(lowest, f64::min);
        highest = all.iter().copied().fold(highest, f64::max);
    }
    let low = late_min - 2.0 * (highest - late_min).max(1e-9);
    (lowest < low).then_some(low)
}

/// Matplotlib's tab10 (less its grey, which reference lines use), so that
/// a study's cells and its companions' rarely share a colour.
const COLORS: [RGBColor; 9] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

/// Reference lines: black, grey, dark green, purple (dashed).
const REFERENCE_COLORS: [RGBColor; 4] = [RGBColor(0, 0, 0), RGBColor(120, 120, 120), RGBColor(0, 100, 0), RGBColor(120, 0, 120)];

/// Width of the plot and of the legend beside it, pixels: the legend
/// never covers data (the end of a reward curve, where the result is).
const PLOT_WIDTH: u32 = 820;
const LEGEND_WIDTH: u32 = 300;

/// One legend row: name, colour, and how its sample is drawn.
struct LegendRow {
    name: String,
    color: RGBColor,
    sample: Sample,
}

#[derive(Clone, Copy, PartialEq)]
enum Sample {
    Line,
    /// A reference line.
    Dashed,
    /// Clipped values' marks.
    Triangle,
}

/// Draws `panels` top to bottom against `x` into a PNG, each panel's
/// legend to its right. Integer x values (episodes) get whole-number
/// ticks; values a reward panel clips sit on its bottom edge, each marked
/// with a small triangle.
pub fn line_panels(path: &Path, title: &str, x: &[f64], x_label: &str, panels: &[Panel]) -> anyhow::Result<()> {
    let root = BitMapBackend::new(path, figure_size(panels)).into_drawing_area();
    let draw_err = |e: &dyn std::fmt::Display| anyhow::anyhow!("cannot draw {}: {e}", path.display());
    draw_panels(&root, title, x, x_label, panels).map_err(|e| draw_err(&e))?;
    root.present().map_err(|e| draw_err(&e)).with_context(|| format!("writing {}", path.display()))
}

/// The figure's size in pixels: one 260-pixel row per panel under the title.
fn figure_size(panels: &[Panel]) -> (u32, u32) {
    (PLOT_WIDTH + LEGEND_WIDTH, 60 + 260 * panels.len() as u32)
}

/// [`line_panels`] on any drawing backend (a file, or memory in the tests).
fn draw_panels<DB: DrawingBackend>(root: &DrawingArea<DB, plotters::coord::Shift>, title: &str, x: &[f64], x_label: &str, panels: &[Panel]) -> anyhow::Result<()>
where
    DB::ErrorType: 'static,
{
    lcrl_graph_builder::plot::register_fonts();
    let draw_err = |e: &dyn std::fmt::Display| anyhow::anyhow!("{e}");
    root.fill(&WHITE).map_err(|e| draw_err(&e))?;
    let root = root.titled(title, ("sans-serif", 20)).map_err(|e| draw_err(&e))?;
    let areas = root.split_evenly((panels.len(), 1));
    for (whole, panel) in areas.iter().zip(panels) {
        let (area, legend_area) = whole.split_horizontally(PLOT_WIDTH);
        let mut legend: Vec<LegendRow> = Vec::new();
        let x = panel.x.as_deref().unwrap_or(x);
        let whole_numbers = x.iter().all(|v| v.fract() == 0.0);
        let (x0, x1) = range(x.iter().copied());
        let (y0, y1, below) = y_range(panel);
        let y_label = if below > 0 { format!("{} ({below} values below the axis)", panel.y_label) } else { panel.y_label.clone() };
        let mut chart = ChartBuilder::on(&area)
            .margin(12)
            .x_label_area_size(35)
            .y_label_area_size(70)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(|e| draw_err(&e))?;
        let whole_ticks = |v: &f64| format!("{v:.0}");
        let mut mesh = chart.configure_mesh();
        mesh.x_desc(x_label).y_desc(y_label.as_str()).label_style(("sans-serif", 13));
        if whole_numbers {
            mesh.x_label_formatter(&whole_ticks);
        }
        mesh.draw().map_err(|e| draw_err(&e))?;
        // With markers, series at the same x stand a little apart, so that
        // their error bars do not hide each other.
        let dodge = |k: usize| if panel.markers { (k as f64 - (panel.series.len() as f64 - 1.0) / 2.0) * 0.012 * (x1 - x0) } else { 0.0 };
        for (k, lo, hi) in &panel.bands {
            let color = COLORS[k % COLORS.len()];
            if panel.markers {
                let bars = x.iter().zip(lo.iter().zip(hi)).filter(|(_, (l, h))| l.is_finite() && h.is_finite());
                let bars = bars.map(|(x, (l, h))| PathElement::new(vec![(x + dodge(*k), l.clamp(y0, y1)), (x + dodge(*k), h.clamp(y0, y1))], color.stroke_width(2)));
                chart.draw_series(bars).map_err(|e| draw_err(&e))?;
            } else {
                let clamp = |v: &[f64]| -> Vec<(f64, f64)> { x.iter().copied().zip(v.iter().map(|y| y.clamp(y0, y1))).collect() };
                let polygon: Vec<(f64, f64)> = clamp(hi).into_iter().chain(clamp(lo).into_iter().rev()).collect();
                chart.draw_series(std::iter::once(Polygon::new(polygon, color.mix(0.18).filled()))).map_err(|e| draw_err(&e))?;
            }
        }
        for (k, (name, values)) in panel.series.iter().enumerate() {
            let color = COLORS[k % COLORS.len()];
            let stretches = stretches(x, values, dodge(k), y0);
            // Segment by segment: plotters joins a wide polyline's segments
            // with unlimited miters, and a sharp zigzag (noisy returns)
            // turns them into spikes that leave the frame.
            for stretch in &stretches {
                let segments = stretch.windows(2).map(|pair| PathElement::new(pair.to_vec(), color.stroke_width(2)));
                chart.draw_series(segments).map_err(|e| draw_err(&e))?;
            }
            if panel.markers {
                let dots = stretches.iter().flatten().map(|p| Circle::new(*p, 4, color.filled()));
                chart.draw_series(dots).map_err(|e| draw_err(&e))?;
            }
            // Clipped values: a triangle standing on the bottom edge for each.
            let clipped = x.iter().zip(values).filter(|(_, y)| **y < y0);
            let clipped = clipped.map(|(x, _)| EmptyElement::at((*x, y0)) + TriangleMarker::new((0, -4), 4, color.filled()));
            chart.draw_series(clipped).map_err(|e| draw_err(&e))?;
            legend.push(LegendRow { name: name.clone(), color, sample: Sample::Line });
        }
        for (k, (name, y)) in panel.references.iter().enumerate() {
            let color = REFERENCE_COLORS[k % REFERENCE_COLORS.len()];
            chart.draw_series(DashedLineSeries::new(vec![(x0, *y), (x1, *y)], 8, 5, color.stroke_width(2))).map_err(|e| draw_err(&e))?;
            legend.push(LegendRow { name: format!("{name} ({y:.3})"), color, sample: Sample::Dashed });
        }
        if below > 0 {
            legend.push(LegendRow { name: format!("{below} values below the axis"), color: COLORS[0], sample: Sample::Triangle });
        }
        draw_legend(&legend_area, &legend).map_err(|e| draw_err(&e))?;
    }
    Ok(())
}

/// A panel's y axis (y0, y1): its series, bands and reference lines,
/// without the low outliers when the panel clips them; and how many values
/// of its first series lie below the axis.
fn y_range(panel: &Panel) -> (f64, f64, usize) {
    let values: Vec<f64> = panel.series.iter().flat_map(|(_, v)| v.iter().copied()).collect();
    let band = panel.bands.iter().flat_map(|(_, lo, hi)| lo.iter().chain(hi).copied());
    let references = panel.references.iter().map(|(_, y)| *y);
    let curves: Vec<&[f64]> = panel.series.iter().map(|(_, v)| v.as_slice()).collect();
    let floor = if panel.clip_low_outliers && !curves.is_empty() { robust_low(&curves) } else { None };
    let kept = values.iter().copied().filter(|v| floor.is_none_or(|f| *v >= f));
    let (y0, y1) = range(kept.chain(band).chain(references).chain(floor));
    let below = floor.map_or(0, |f| panel.series.first().map_or(0, |(_, v)| v.iter().filter(|x| **x < f).count()));
    (y0, y1, below)
}

/// A series' points as the stretches its line is drawn in: a NaN value is
/// a gap (the line stops there and starts again after it); values below
/// the axis bottom `y0` sit on it (they are marked as clipped); x moves by
/// `dodge`.
fn stretches(x: &[f64], values: &[f64], dodge: f64, y0: f64) -> Vec<Vec<(f64, f64)>> {
    let points: Vec<Option<(f64, f64)>> = x.iter().zip(values).map(|(x, y)| (!y.is_nan()).then(|| (x + dodge, y.max(y0)))).collect();
    points
        .split(Option::is_none)
        .map(|stretch| stretch.iter().flatten().copied().filter(|(_, y)| y.is_finite()).collect::<Vec<_>>())
        .filter(|stretch| !stretch.is_empty())
        .collect()
}

/// The legend rows top down, a line sample (dashed for references) and the
/// name, beside the plot.
fn draw_legend<DB: DrawingBackend>(area: &DrawingArea<DB, plotters::coord::Shift>, rows: &[LegendRow]) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    for (k, row) in rows.iter().enumerate() {
        let y = 24 + 20 * k as i32;
        let style = row.color.stroke_width(2);
        match row.sample {
            Sample::Line => area.draw(&PathElement::new(vec![(4, y), (22, y)], style))?,
            Sample::Dashed => {
                for start in [4, 13] {
                    area.draw(&PathElement::new(vec![(start, y), (start + 6, y)], style))?;
                }
            }
            Sample::Triangle => area.draw(&TriangleMarker::new((13, y), 4, row.color.filled()))?,
        }
        area.draw(&Text::new(row.name.as_str(), (28, y - 7), ("sans-serif", 13).into_font().color(&BLACK)))?;
    }
    Ok(())
}

/// A padded [min, max] range that is never empty.
fn range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values.filter(|v| v.is_finite()).fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let pad = ((hi - lo) * 0.05).max(1e-9);
    (lo - pad, hi + pad)
}

#[cfg(test)]
mod tests {
    use plotters::prelude::*;

    use super::{draw_panels, figure_size, robust_low, stretches, Panel, COLORS, PLOT_WIDTH};

    /// NaN splits a line (a companion that did not run at some N), a
    /// single point is a stretch of its own, and −∞ sits on the bottom.
    #[test]
    fn a_gap_splits_the_line_into_stretches() {
        let x = [4.0, 8.0, 16.0, 32.0, 64.0];
        let drawn = stretches(&x, &[1.0, f64::NAN, 2.0, 3.0, f64::NAN], 0.5, -1.0);
        assert_eq!(drawn, vec![vec![(4.5, 1.0)], vec![(16.5, 2.0), (32.5, 3.0)]]);
        assert_eq!(stretches(&x, &[f64::NAN; 5], 0.0, -1.0), Vec::<Vec<(f64, f64)>>::new());
        assert_eq!(stretches(&x[..2], &[f64::NEG_INFINITY, 0.0], 0.0, -1.0), vec![vec![(4.0, -1.0), (8.0, 0.0)]]);
    }

    #[test]
    fn early_disasters_do_not_set_the_axis() {
        // 40 terrible early episodes of 150, then a run settling near −2.
        let returns: Vec<f64> = (0..150).map(|k| if k < 40 { -3000.0 + k as f64 } else { -2.0 - 10.0 / (k as f64) }).collect();
        let low = robust_low(&[&returns]).unwrap();
        assert!(low > -10.0 && low < -2.0, "{low}");
        // A run with nothing far below its settled half: no clipping.
        let calm: Vec<f64> = (0..150).map(|k| -5.0 + k as f64 * 0.01).collect();
        assert_eq!(robust_low(&[&calm]), None);
        assert_eq!(robust_low(&[&returns[..10]]), None);
    }

    /// The longest run of black pixels along rows (`horizontal`) or
    /// columns of the plot area: (the line's index, its first, its last).
    fn longest_black_run(pixels: &[u8], (width, height): (u32, u32), horizontal: bool) -> (usize, usize, usize) {
        let black = |x: usize, y: usize| pixels[3 * (y * width as usize + x)..][..3] == [0, 0, 0];
        let (lines, along) = if horizontal { (height as usize, PLOT_WIDTH as usize) } else { (PLOT_WIDTH as usize, height as usize) };
        let mut best = (0, 0, 0);
        for line in 0..lines {
            let mut start = None;
            for k in 0..=along {
                let on = k < along && if horizontal { black(k, line) } else { black(line, k) };
                match (on, start) {
                    (true, None) => start = Some(k),
                    (false, Some(s)) => {
                        if k - s > best.2 - best.1 + 1 || best == (0, 0, 0) {
                            best = (line, s, k - 1);
                        }
                        start = None;
                    }
                    _ => {}
                }
            }
        }
        best
    }

    /// A noisy reward curve (sharp dips, early disasters below the axis)
    /// is drawn inside the frame the axes make: no pixel of its colour lies
    /// left of the y axis, below the x axis or above the y axis's top.
    /// (Drawn as one wide polyline, its sharp corners became spikes far
    /// outside it: 680 pixels of this curve.)
    #[test]
    fn a_noisy_curve_stays_inside_its_frame() {
        // Noisy returns over 1,000 episodes (a fixed LCG): every few a
        // sharp dip, and the first 100 far below the rest.
        let mut state = 12345u64;
        let mut noise = || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let returns: Vec<f64> = (0..1000).map(|k| if k < 100 { -600.0 * noise() } else { -1.0 - 3.0 * noise() - if noise() < 0.1 { 30.0 * noise() } else { 0.0 } }).collect();
        let x: Vec<f64> = (1..=returns.len()).map(|e| e as f64).collect();
        let panels = [Panel::rewards("return", vec![("return".into(), returns)], Vec::new())];
        let size = figure_size(&panels);
        let mut pixels = vec![0u8; 3 * (size.0 * size.1) as usize];
        {
            let root = BitMapBackend::with_buffer(&mut pixels, size).into_drawing_area();
            draw_panels(&root, "noisy", &x, "episode", &panels).unwrap();
            root.present().unwrap();
        }
        let (axis_row, _, _) = longest_black_run(&pixels, size, true);
        let (axis_column, top, _) = longest_black_run(&pixels, size, false);
        let color = COLORS[0];
        let drawn: Vec<(usize, usize)> = (0..size.1 as usize)
            .flat_map(|y| (0..PLOT_WIDTH as usize).map(move |x| (x, y)))
            .filter(|&(x, y)| pixels[3 * (y * size.0 as usize + x)..][..3] == [color.0, color.1, color.2])
            .collect();
        assert!(drawn.len() > 1000, "the curve is drawn ({} pixels)", drawn.len());
        // The line is 2 pixels wide: it may lie on an axis, not beyond it.
        let outside: Vec<&(usize, usize)> = drawn.iter().filter(|&&(x, y)| y > axis_row + 1 || y + 1 < top || x + 1 < axis_column).collect();
        assert!(outside.is_empty(), "{} pixels outside the frame (rows {top}..={axis_row}, from column {axis_column}), e.g. {:?}", outside.len(), &outside[..outside.len().min(5)]);
    }
}
