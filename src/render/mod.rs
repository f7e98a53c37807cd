//! Pictures with plotters: a domain's scene with an imagined plan overlaid (`prac render`, the
//! paper's Figure 2), and line charts for the sim client's figures. Text uses DejaVu Sans,
//! embedded, so nothing depends on the machine's fonts.

use std::path::Path;
use std::sync::Once;

use anyhow::Context;
use plotters::prelude::*;
use plotters::style::FontStyle;

use crate::domains::{Part, Scene, Shape};

pub mod chart;

const FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");
pub(crate) const FONT_FAMILY: &str = "sans-serif";

/// Registers the embedded font with plotters (once per process).
pub(crate) fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The font is a valid TrueType file compiled into the binary.
        let _ = plotters::style::register_font(FONT_FAMILY, FontStyle::Normal, FONT);
    });
}

fn err<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow::anyhow!("drawing failed: {e:?}")
}

/// Refuses a picture path whose folder does not exist, before drawing (the PNG encoder's own
/// error is a nested debug dump).
pub(crate) fn check_folder(path: &Path) -> anyhow::Result<()> {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() && !dir.is_dir() => anyhow::bail!(
            "cannot write {}: the folder {} does not exist",
            path.display(),
            dir.display()
        ),
        _ => Ok(()),
    }
}

const SKY: RGBColor = RGBColor(250, 250, 252);
const BODY: RGBColor = RGBColor(80, 90, 160);
const LEFT: RGBColor = RGBColor(30, 140, 120);
const RIGHT: RGBColor = RGBColor(200, 120, 30);
const GROUND: RGBColor = RGBColor(90, 90, 90);
const DETAIL: RGBColor = RGBColor(200, 170, 40);
const PLAN: RGBColor = RGBColor(220, 60, 40);
const TITLE_BAND: i32 = 34;

/// What the policy has committed to at the drawn state: drawn over the scene (where the model
/// imagines the robot) and in a panel under it (the actions, step by step).
pub struct Forecast<'a> {
    /// Where the model imagines the robot after each committed action, in scene coordinates.
    pub trace: &'a [(f64, f64)],
    /// The committed actions, one row per coming step, in the domain's units.
    pub actions: &'a [Vec<f32>],
    /// The step at which each action was decided.
    pub decided_at: &'a [u64],
    /// The episode step of the first action (executed now).
    pub step: u64,
    /// The actions' bounds, for the panel's axis.
    pub action_range: (f32, f32),
}

/// Draws `scene` into a `width` x `height` PNG at `path` under `title`: with a forecast, the
/// imagined states over the scene (dots fading into the future) and the committed actions in a
/// panel below it; a legend says what is drawn and a bar gives the scale.
pub fn render_scene(
    scene: &Scene,
    forecast: Option<&Forecast<'_>>,
    title: &str,
    path: &Path,
    (width, height): (u32, u32),
) -> anyhow::Result<()> {
    check_folder(path)?;
    register_font();
    let root = BitMapBackend::new(path, (width, height)).into_drawing_area();
    root.fill(&SKY).map_err(err)?;
    let band = TITLE_BAND.min(height as i32 / 6);
    let (title_area, rest) = root.split_vertically(band);
    let (scene_area, panel_area) = match forecast {
        Some(_) => {
            let rest_height = height as i32 - band;
            let (upper, lower) = rest.split_vertically(rest_height * 62 / 100);
            (upper, Some(lower))
        }
        None => (rest, None),
    };
    draw_scene(&scene_area, scene, forecast.map(|f| f.trace))?;
    if let (Some(area), Some(forecast)) = (panel_area, forecast) {
        draw_forecast(&area, forecast)?;
    }
    let size = (band as f64 * 0.55).round().max(8.0) as u32;
    title_area
        .draw(&Text::new(
            title.to_string(),
            (10, (band - size as i32) / 2),
            (FONT_FAMILY, size).into_font().color(&BLACK),
        ))
        .map_err(err)?;
    root.present()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

fn draw_scene(
    area: &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
    scene: &Scene,
    trace: Option<&[(f64, f64)]>,
) -> anyhow::Result<()> {
    let (width, height) = area.dim_in_pixel();
    let scale = (f64::from(width) / scene.width).min(f64::from(height) / scene.height);
    let (cx, cy) = scene.center;
    let to_px = |(x, y): (f64, f64)| -> (i32, i32) {
        (
            (f64::from(width) / 2.0 + (x - cx) * scale).round() as i32,
            (f64::from(height) / 2.0 - (y - cy) * scale).round() as i32,
        )
    };
    // Ground first, then the robot in the order the scene gives (far side first), then markers.
    let robot = |part: Part| matches!(part, Part::Body | Part::Left | Part::Right);
    let layers: [&dyn Fn(Part) -> bool; 3] =
        [&|p| p == Part::Ground, &robot, &|p| p == Part::Detail];
    let mut sides = [false; 2];
    for in_layer in layers {
        for (part, shape) in scene.shapes.iter().filter(|(p, _)| in_layer(*p)) {
            let color = match part {
                Part::Body => BODY,
                Part::Left => {
                    sides[0] = true;
                    LEFT
                }
                Part::Right => {
                    sides[1] = true;
                    RIGHT
                }
                Part::Ground => GROUND,
                Part::Detail => DETAIL,
            };
            draw_shape(area, shape, color, scale, &to_px)?;
        }
    }
    let mut legend: Vec<(RGBColor, String)> = Vec::new();
    if let Some(trace) = trace.filter(|t| !t.is_empty()) {
        let px: Vec<(i32, i32)> = trace.iter().map(|&p| to_px(p)).collect();
        area.draw(&PathElement::new(px.clone(), PLAN.mix(0.5).stroke_width(2)))
            .map_err(err)?;
        for (i, p) in px.iter().enumerate() {
            let fade = 1.0 - 0.7 * i as f64 / px.len() as f64;
            area.draw(&Circle::new(*p, 4, PLAN.mix(fade).filled()))
                .map_err(err)?;
        }
        legend.push((
            PLAN,
            format!(
                "where the model imagines the robot over the {} committed steps (fading)",
                trace.len()
            ),
        ));
    }
    if sides[0] {
        legend.push((LEFT, "left limbs".to_string()));
    }
    if sides[1] {
        legend.push((RIGHT, "right limbs".to_string()));
    }
    let font = (FONT_FAMILY, 13).into_font().color(&BLACK);
    for (k, (color, text)) in legend.iter().enumerate() {
        let y = 8 + 18 * k as i32;
        area.draw(&Circle::new((14, y + 6), 5, color.filled()))
            .map_err(err)?;
        area.draw(&Text::new(text.clone(), (24, y), font.clone()))
            .map_err(err)?;
    }
    draw_scale_bar(area, scale)
}

fn draw_shape(
    area: &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
    shape: &Shape,
    color: RGBColor,
    scale: f64,
    to_px: &dyn Fn((f64, f64)) -> (i32, i32),
) -> anyhow::Result<()> {
    match shape {
        Shape::Polygon(points) => {
            let px: Vec<(i32, i32)> = points.iter().map(|&p| to_px(p)).collect();
            area.draw(&Polygon::new(px, color.filled())).map_err(err)?;
        }
        Shape::Circle(c, r) => {
            let radius = (r * scale).round().max(1.0) as i32;
            area.draw(&Circle::new(to_px(*c), radius, color.filled()))
                .map_err(err)?;
        }
        Shape::Capsule(a, b, r) => {
            let stroke = ((2.0 * r * scale).round() as u32).max(1);
            area.draw(&PathElement::new(
                vec![to_px(*a), to_px(*b)],
                color.stroke_width(stroke),
            ))
            .map_err(err)?;
            for end in [a, b] {
                let radius = (r * scale).round().max(1.0) as i32;
                area.draw(&Circle::new(to_px(*end), radius, color.filled()))
                    .map_err(err)?;
            }
        }
        Shape::Polyline(points) => {
            let px: Vec<(i32, i32)> = points.iter().map(|&p| to_px(p)).collect();
            area.draw(&PathElement::new(px, color.stroke_width(3)))
                .map_err(err)?;
        }
    }
    Ok(())
}

/// A bar of a round length (0.1, 0.2, 0.5, 1, 2, 5 ... metres) about an eighth of the width, in
/// the top right corner (the ground runs along the bottom).
fn draw_scale_bar(
    area: &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
    scale: f64,
) -> anyhow::Result<()> {
    let (width, _) = area.dim_in_pixel();
    let target = f64::from(width) / 8.0 / scale;
    let metres = [0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0]
        .into_iter()
        .min_by(|a, b| (a - target).abs().total_cmp(&(b - target).abs()))
        .unwrap_or(1.0);
    let length = (metres * scale).round() as i32;
    let (x1, y) = (width as i32 - 16, 30);
    let x0 = x1 - length;
    area.draw(&PathElement::new(
        vec![(x0, y), (x1, y)],
        BLACK.stroke_width(3),
    ))
    .map_err(err)?;
    for x in [x0, x1] {
        area.draw(&PathElement::new(
            vec![(x, y - 5), (x, y + 5)],
            BLACK.stroke_width(2),
        ))
        .map_err(err)?;
    }
    area.draw(&Text::new(
        format!("{metres} m"),
        (x0, y - 20),
        (FONT_FAMILY, 13).into_font().color(&BLACK),
    ))
    .map_err(err)
}

/// The committed actions over the coming steps, one line per action dimension; a filled marker
/// was decided at this step, a hollow one at an earlier step (the step is written above it).
fn draw_forecast(
    area: &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
    forecast: &Forecast<'_>,
) -> anyhow::Result<()> {
    let steps = forecast.actions.len();
    let first = forecast.step as f64;
    let (lo, hi) = forecast.action_range;
    let pad = 0.1 * f64::from((hi - lo).max(1e-3));
    let mut chart = ChartBuilder::on(area)
        .margin(8)
        .margin_top(36)
        .x_label_area_size(34)
        .y_label_area_size(48)
        .build_cartesian_2d(
            first - 0.5..first + steps.max(1) as f64 - 0.5,
            f64::from(lo) - pad..f64::from(hi) + pad,
        )
        .map_err(err)?;
    let label_font = (FONT_FAMILY, 12).into_font();
    chart
        .configure_mesh()
        .x_desc("episode step (the first is executed now)")
        .y_desc("action")
        .x_labels(steps.clamp(2, 12))
        .x_label_formatter(&|x| format!("{}", x.round() as i64))
        .y_labels(5)
        .label_style(label_font.clone())
        .axis_desc_style(label_font.clone())
        .light_line_style(WHITE.mix(0.0))
        .draw()
        .map_err(err)?;
    let dims = forecast.actions.first().map_or(0, Vec::len);
    for d in 0..dims {
        let color = chart::color(d);
        let points: Vec<(f64, f64)> = forecast
            .actions
            .iter()
            .enumerate()
            .map(|(i, a)| (first + i as f64, f64::from(a[d])))
            .collect();
        chart
            .draw_series(LineSeries::new(points.clone(), color.stroke_width(2)))
            .map_err(err)?;
        chart
            .draw_series(
                points
                    .iter()
                    .zip(forecast.decided_at)
                    .filter(|(_, at)| **at != forecast.step)
                    .map(|(&p, _)| Circle::new(p, 5, SKY.filled())),
            )
            .map_err(err)?;
        chart
            .draw_series(points.iter().zip(forecast.decided_at).map(|(&p, &at)| {
                if at == forecast.step {
                    Circle::new(p, 5, color.filled())
                } else {
                    Circle::new(p, 5, color.stroke_width(1))
                }
            }))
            .map_err(err)?;
    }
    // The step each action was decided at, above its column (every column while they fit).
    let every = steps.div_ceil(24).max(1);
    let plotting = chart.plotting_area();
    for (i, at) in forecast.decided_at.iter().enumerate().step_by(every) {
        // Backend pixels, made relative to the panel.
        let (x, y) = plotting.map_coordinate(&(first + i as f64, f64::from(hi) + pad));
        let (bx, by) = area.get_base_pixel();
        area.draw(&Text::new(
            at.to_string(),
            (x - bx - 6, y - by - 14),
            (FONT_FAMILY, 11).into_font().color(&RGBColor(90, 90, 90)),
        ))
        .map_err(err)?;
    }
    area.draw(&Text::new(
        format!(
            "committed actions ({dims} {}; filled: decided now, hollow: earlier; above: step decided at)",
            if dims == 1 { "dimension" } else { "dimensions" }
        ),
        (56, 6),
        (FONT_FAMILY, 12).into_font().color(&BLACK),
    ))
    .map_err(err)?;
    Ok(())
}
