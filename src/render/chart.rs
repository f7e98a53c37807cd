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

/// Twelve distinct colours (matplotlib's tab10, then black and a dark magenta), so that a
/// Figure 4 with three seeds of four settings repeats none.
pub(crate) fn color(i: usize) -> RGBColor {
    const PALETTE: [RGBColor; 12] = [
        RGBColor(31, 119, 180),
        RGBColor(214, 39, 40),
        RGBColor(44, 160, 44),
        RGBColor(255, 127, 14),
        RGBColor(148, 103, 189),
        RGBColor(140, 86, 75),
        RGBColor(227, 119, 194),
        RGBColor(127, 127, 127),
        RGBColor(188, 189, 34),
        RGBColor(23, 190, 207),
        RGBColor(0, 0, 0),
        RGBColor(153, 0, 76),
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

/// A short tick label: 150000 -> "150k", 2500000 -> "2.5M", 0.0100 -> "0.01", so that the
/// labels of a training-steps axis do not run into each other.
fn tick_label(v: &f64) -> String {
    let (scaled, suffix) = match v.abs() {
        m if m >= 1e6 => (v / 1e6, "M"),
        m if m >= 1e3 => (v / 1e3, "k"),
        _ => (*v, ""),
    };
    // Six places, trimmed: enough for small fractions (eps coefficients) and for the ticks of a
    // narrow axis around a larger value (1.0002), while round ticks stay short.
    let places = 6;
    let text = format!("{scaled:.places$}");
    let trimmed = text.trim_end_matches('0').trim_end_matches('.');
    // A tick a rounding error below zero prints as "-0".
    let trimmed = if trimmed == "-0" { "0" } else { trimmed };
    format!("{trimmed}{suffix}")
}

/// Where the legend covers the least of the lines: the candidate spots are the corners and
/// the edges' middles, each a box of 30% of both axes; each line is sampled along its
/// segments, so a line with few points still counts where it runs.
fn emptiest_spot(
    series: &[Series],
    (x0, x1): (f64, f64),
    (y0, y1): (f64, f64),
) -> SeriesLabelPosition {
    use SeriesLabelPosition::*;
    const LOW: (f64, f64) = (0.0, 0.3);
    const MID: (f64, f64) = (0.35, 0.65);
    const HIGH: (f64, f64) = (0.7, 1.0);
    let spots = [
        (UpperRight, HIGH, HIGH),
        (LowerRight, HIGH, LOW),
        (UpperLeft, LOW, HIGH),
        (LowerLeft, LOW, LOW),
        (MiddleRight, HIGH, MID),
        (MiddleLeft, LOW, MID),
        (UpperMiddle, MID, HIGH),
        (LowerMiddle, MID, LOW),
    ];
    const SAMPLES_PER_SEGMENT: usize = 16;
    let samples: Vec<(f64, f64)> = series
        .iter()
        .flat_map(|line| {
            line.points.windows(2).flat_map(|w| {
                let ((ax, ay, _), (bx, by, _)) = (w[0], w[1]);
                (0..SAMPLES_PER_SEGMENT).map(move |k| {
                    let f = k as f64 / SAMPLES_PER_SEGMENT as f64;
                    (ax + f * (bx - ax), ay + f * (by - ay))
                })
            })
        })
        .chain(
            series
                .iter()
                .filter_map(|line| line.points.last().map(|p| (p.0, p.1))),
        )
        .map(|(x, y)| ((x - x0) / (x1 - x0), (y - y0) / (y1 - y0)))
        .collect();
    let inside = |t: f64, (lo, hi): (f64, f64)| t >= lo && t <= hi;
    spots
        .into_iter()
        .min_by_key(|&(_, xs, ys)| {
            samples
                .iter()
                .filter(|&&(tx, ty)| inside(tx, xs) && inside(ty, ys))
                .count()
        })
        .map(|(spot, _, _)| spot)
        .unwrap_or(UpperRight)
}

/// Draws the panels in a row into a PNG of `width` x `height`.
pub fn line_panels(
    path: &Path,
    panels: &[Panel],
    (width, height): (u32, u32),
) -> anyhow::Result<()> {
    register_font();
    super::check_folder(path)?;
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
            .x_label_formatter(&tick_label)
            .y_label_formatter(&tick_label)
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
            .position(emptiest_spot(&panel.series, (x0, x1), (y0, y1)))
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

#[cfg(test)]
mod tests {
    use super::{Series, SeriesLabelPosition, color, emptiest_spot, tick_label};
    use plotters::prelude::Color;

    #[test]
    fn three_seeds_of_four_settings_get_twelve_colours() {
        let colours: Vec<_> = (0..12).map(|i| color(i).rgb()).collect();
        for (i, a) in colours.iter().enumerate() {
            assert!(!colours[..i].contains(a), "colour {i} repeats");
        }
    }

    #[test]
    fn tick_labels_are_short() {
        assert_eq!(tick_label(&150000.0), "150k");
        assert_eq!(tick_label(&2_500_000.0), "2.5M");
        assert_eq!(tick_label(&-250.0), "-250");
        assert_eq!(tick_label(&0.0), "0");
        assert_eq!(tick_label(&0.01), "0.01");
        assert_eq!(tick_label(&0.0005), "0.0005");
        assert_eq!(tick_label(&12.5), "12.5");
        assert_eq!(tick_label(&0.9999999), "1");
        assert_eq!(tick_label(&-1e-17), "0");
        assert_eq!(tick_label(&1.0002), "1.0002");
        assert_eq!(tick_label(&0.30000000000000004), "0.3");
    }

    /// A line through the given (x, y) points, with no band.
    fn line(points: &[(f64, f64)]) -> Series {
        Series {
            name: String::new(),
            points: points.iter().map(|&(x, y)| (x, y, 0.0)).collect(),
        }
    }

    #[test]
    fn the_legend_goes_where_no_line_runs() {
        let range = (0.0, 100.0);
        // Two points a line apart still count along the segment between them.
        let rising = line(&[(0.0, 0.0), (100.0, 100.0)]);
        let flat_low = line(&[(0.0, 2.0), (100.0, 2.0)]);
        let spot = emptiest_spot(&[rising, flat_low], range, range);
        assert!(matches!(spot, SeriesLabelPosition::UpperLeft), "{spot:?}");
        // Lines along the top and the bottom leave only the middles free; a falling one takes
        // the middle right.
        let top = line(&[(0.0, 98.0), (100.0, 98.0)]);
        let bottom = line(&[(0.0, 2.0), (100.0, 2.0)]);
        let falling = line(&[(0.0, 100.0), (50.0, 100.0), (100.0, 50.0)]);
        let spot = emptiest_spot(&[top, bottom, falling], range, range);
        assert!(matches!(spot, SeriesLabelPosition::MiddleLeft), "{spot:?}");
    }
}
