//! Heatmap of normalized CS3 with G marked, as the publication plots it.

use std::path::Path;

use plotters::prelude::*;
use plotters::style::FontStyle;

use crate::report::GraphReport;
use crate::GraphError;

/// Command-line check for a plot file: plots are PNG, and the drawing
/// backend picks the format from the extension, so a name without `.png`
/// would only fail after the work is done, with a backend error.
pub fn png_path(arg: &str) -> Result<std::path::PathBuf, String> {
    let path = std::path::PathBuf::from(arg);
    match path.extension().and_then(|e| e.to_str()) {
        Some(ext) if ext.eq_ignore_ascii_case("png") => Ok(path),
        _ => Err(format!("plots are PNG images: give a file name ending in .png (e.g. {arg}.png)")),
    }
}

/// Registers the embedded DejaVu Sans as plotters' "sans-serif", so plots
/// never depend on fonts installed on the machine.
pub fn register_fonts() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // Cannot fail on a valid embedded TTF; a failure would only lose text.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular());
        let _ = plotters::style::register_font("sans-serif", FontStyle::Bold, dejavu::sans::bold());
    });
}

/// Draws normalized phi (white → dark blue, value in each cell) with a
/// black dot where G = 1; action rows top to bottom as in the table. With a
/// threshold sweep, one panel per T, stacked.
pub fn heatmap(report: &GraphReport, path: &Path) -> Result<(), GraphError> {
    register_fonts();
    let (n, m) = (report.actions(), report.states());
    let cell = 64u32;
    let panels: Vec<(String, &Vec<Vec<u8>>)> = if report.sweep.is_empty() {
        vec![(format!("normalized CS3 of {} ({}); dot: G = 1", short(&report.env), report.rule_text()), &report.g)]
    } else {
        report
            .sweep
            .iter()
            .map(|e| (format!("normalized CS3 of {}; dot: G = 1 at T = {} ({} edges)", short(&report.env), e.threshold, e.edges), &e.g))
            .collect()
    };
    let panel_height = 120 + cell * n as u32;
    let size = ((170 + cell * m as u32).max(560), panel_height * panels.len() as u32);
    let plot_err = |e: &dyn std::fmt::Display| GraphError::Plot { path: path.into(), message: e.to_string() };
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(|e| plot_err(&e))?;
    for (area, (title, g)) in root.split_evenly((panels.len(), 1)).iter().zip(&panels) {
        panel(area, report, title, g).map_err(|e| plot_err(&e))?;
    }
    root.present().map_err(|e| plot_err(&e))?;
    Ok(())
}

type Area<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;

fn panel(area: &Area, report: &GraphReport, title: &str, g: &[Vec<u8>]) -> Result<(), Box<dyn std::error::Error>> {
    let (n, m) = (report.actions(), report.states());
    let mut chart = ChartBuilder::on(area)
        .caption(title, ("sans-serif", 16))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(90)
        // A segmented range a..b has b − a + 1 segments.
        .build_cartesian_2d((0..m - 1).into_segmented(), (0..n - 1).into_segmented())?;
    let centre = |v: &SegmentValue<usize>| match v {
        SegmentValue::CenterOf(k) => Some(*k),
        _ => None,
    };
    let state_label = |v: &SegmentValue<usize>| centre(v).and_then(|j| report.state_names.get(j).cloned()).unwrap_or_default();
    let action_label = |v: &SegmentValue<usize>| {
        centre(v).and_then(|y| report.action_names.get(n.checked_sub(y + 1)?).cloned()).unwrap_or_default()
    };
    chart
        .configure_mesh()
        .disable_mesh()
        .x_labels(m)
        .y_labels(n)
        .x_label_formatter(&state_label)
        .y_label_formatter(&action_label)
        .x_desc("state j")
        .y_desc("action i")
        .label_style(("sans-serif", 14))
        .draw()?;
    let cells: Vec<(usize, usize)> = (0..n).flat_map(|i| (0..m).map(move |j| (i, j))).collect();
    chart.draw_series(cells.iter().map(|&(i, j)| {
        let v = report.phi_normalized[i][j].clamp(0.0, 1.0);
        let shade = |c: u8| (255.0 - (255.0 - f64::from(c)) * v) as u8;
        let y = n - 1 - i;
        Rectangle::new(
            [(SegmentValue::Exact(j), SegmentValue::Exact(y)), (SegmentValue::Exact(j + 1), SegmentValue::Exact(y + 1))],
            RGBColor(shade(8), shade(48), shade(107)).filled(),
        )
    }))?;
    // Marks and values are placed in pixels, relative to each cell's centre;
    // backend coordinates count from the image's corner, the panel's from its own.
    let (ox, oy) = area.get_base_pixel();
    for &(i, j) in &cells {
        let y = n - 1 - i;
        let (x0, y0) = chart.backend_coord(&(SegmentValue::Exact(j), SegmentValue::Exact(y + 1)));
        let (x1, y1) = chart.backend_coord(&(SegmentValue::Exact(j + 1), SegmentValue::Exact(y)));
        let (cx, cy) = ((x0 + x1) / 2 - ox, (y0 + y1) / 2 - oy);
        let v = report.phi_normalized[i][j];
        let ink = if v > 0.5 { WHITE } else { BLACK };
        let text = format!("{v:.2}");
        area.draw(&Text::new(text, (cx - 12, cy + 8), ("sans-serif", 12).into_font().color(&ink)))?;
        if g[i][j] == 1 {
            area.draw(&Circle::new((cx, cy - 8), 6, BLACK.filled()))?;
            area.draw(&Circle::new((cx, cy - 8), 7, WHITE.stroke_width(1)))?;
        }
    }
    Ok(())
}

fn short(env: &str) -> &str {
    Path::new(env).file_name().and_then(|s| s.to_str()).unwrap_or(env)
}
