//! Line plots stacked in panels sharing one x axis (traces, reward curves).

use std::path::Path;

use anyhow::Context;
use plotters::prelude::*;

/// One panel: a y-axis label and named series (same length as x).
pub struct Panel {
    pub y_label: String,
    pub series: Vec<(String, Vec<f64>)>,
    /// Optional shaded band (low, high) drawn under the first series.
    pub band: Option<(Vec<f64>, Vec<f64>)>,
}

const COLORS: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];

/// Draws `panels` top to bottom against `x` into a PNG.
pub fn line_panels(path: &Path, title: &str, x: &[f64], x_label: &str, panels: &[Panel]) -> anyhow::Result<()> {
    lcrl_graph_builder::plot::register_fonts();
    let height = 60 + 260 * panels.len() as u32;
    let root = BitMapBackend::new(path, (900, height)).into_drawing_area();
    let draw_err = |e: &dyn std::fmt::Display| anyhow::anyhow!("cannot draw {}: {e}", path.display());
    root.fill(&WHITE).map_err(|e| draw_err(&e))?;
    let root = root.titled(title, ("sans-serif", 20)).map_err(|e| draw_err(&e))?;
    let areas = root.split_evenly((panels.len(), 1));
    let (x0, x1) = range(x.iter().copied());
    for (area, panel) in areas.iter().zip(panels) {
        let all = panel.series.iter().flat_map(|(_, v)| v.iter().copied());
        let band = panel.band.iter().flat_map(|(lo, hi)| lo.iter().chain(hi).copied());
        let (y0, y1) = range(all.chain(band));
        let mut chart = ChartBuilder::on(area)
            .margin(12)
            .x_label_area_size(35)
            .y_label_area_size(70)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(|e| draw_err(&e))?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(panel.y_label.as_str())
            .label_style(("sans-serif", 13))
            .draw()
            .map_err(|e| draw_err(&e))?;
        if let Some((lo, hi)) = &panel.band {
            let polygon: Vec<(f64, f64)> =
                x.iter().copied().zip(hi.iter().copied()).chain(x.iter().copied().zip(lo.iter().copied()).rev()).collect();
            chart.draw_series(std::iter::once(Polygon::new(polygon, COLORS[0].mix(0.2).filled()))).map_err(|e| draw_err(&e))?;
        }
        for (k, (name, values)) in panel.series.iter().enumerate() {
            let color = COLORS[k % COLORS.len()];
            let points = x.iter().copied().zip(values.iter().copied()).filter(|(_, y)| y.is_finite());
            chart
                .draw_series(LineSeries::new(points, color.stroke_width(2)))
                .map_err(|e| draw_err(&e))?
                .label(name.as_str())
                .legend(move |(lx, ly)| PathElement::new(vec![(lx, ly), (lx + 18, ly)], color.stroke_width(2)));
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 13))
            .draw()
            .map_err(|e| draw_err(&e))?;
    }
    root.present().map_err(|e| draw_err(&e)).with_context(|| format!("writing {}", path.display()))
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
