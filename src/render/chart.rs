//! Line charts with one-standard-deviation bands, side by side (the sim client's Figures 3
//! and 4).

use std::path::Path;

use anyhow::Context;
use plotters::prelude::*;

use super::{FONT_FAMILY, err, register_font};

/// One line: points (x, mean, std); a std of 0 draws no band.
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64, f64)>,
}

pub struct Panel {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<Series>,
}

fn color(i: usize) -> RGBColor {
    const PALETTE: [RGBColor; 6] = [
        RGBColor(31, 119, 180),
        RGBColor(214, 39, 40),
        RGBColor(44, 160, 44),
        RGBColor(255, 127, 14),
        RGBColor(148, 103, 189),
        RGBColor(140, 86, 75),
    ];
    PALETTE[i % PALETTE.len()]
}

fn range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let pad = ((hi - lo) * 0.05).max(1e-3);
    (lo - pad, hi + pad)
}

/// Draws the panels in a row into a PNG of `width` x `height`.
pub fn line_panels(
    path: &Path,
    panels: &[Panel],
    (width, height): (u32, u32),
) -> anyhow::Result<()> {
    register_font();
    let root = BitMapBackend::new(path, (width, height)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let areas = root.split_evenly((1, panels.len().max(1)));
    for (panel, area) in panels.iter().zip(areas.iter()) {
        let all = || panel.series.iter().flat_map(|s| s.points.iter());
        let (x0, x1) = range(all().map(|p| p.0));
        let (y0, y1) = range(all().flat_map(|p| [p.1 - p.2, p.1 + p.2]));
        let mut chart = ChartBuilder::on(area)
            .caption(&panel.title, (FONT_FAMILY, 20))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc(panel.x_label.as_str())
            .y_desc(panel.y_label.as_str())
            .label_style((FONT_FAMILY, 13))
            .draw()
            .map_err(err)?;
        for (i, series) in panel.series.iter().enumerate() {
            let c = color(i);
            if series.points.iter().any(|p| p.2 > 0.0) {
                let mut band: Vec<(f64, f64)> =
                    series.points.iter().map(|p| (p.0, p.1 + p.2)).collect();
                band.extend(series.points.iter().rev().map(|p| (p.0, p.1 - p.2)));
                chart
                    .draw_series(std::iter::once(Polygon::new(band, c.mix(0.2).filled())))
                    .map_err(err)?;
            }
            chart
                .draw_series(LineSeries::new(
                    series.points.iter().map(|p| (p.0, p.1)),
                    c.stroke_width(2),
                ))
                .map_err(err)?
                .label(series.name.as_str())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], c.stroke_width(2))
                });
            if series.points.len() <= 12 {
                chart
                    .draw_series(
                        series
                            .points
                            .iter()
                            .map(|p| Circle::new((p.0, p.1), 3, c.filled())),
                    )
                    .map_err(err)?;
            }
        }
        chart
            .configure_series_labels()
            .label_font((FONT_FAMILY, 13))
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(err)?;
    }
    root.present()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
