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
pub const FONT_FAMILY: &str = "sans-serif";

/// Registers the embedded font with plotters (once per process).
pub fn register_font() {
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
const GROUND: RGBColor = RGBColor(90, 90, 90);
const DETAIL: RGBColor = RGBColor(200, 170, 40);
const PLAN: RGBColor = RGBColor(220, 60, 40);

/// Draws `scene` into a `width` x `height` PNG at `path`, with `plan` (points in world
/// coordinates) as a line of dots fading with distance into the future, and a caption.
pub fn render_scene(
    scene: &Scene,
    plan: &[(f64, f64)],
    caption: &str,
    path: &Path,
    (width, height): (u32, u32),
) -> anyhow::Result<()> {
    check_folder(path)?;
    register_font();
    let root = BitMapBackend::new(path, (width, height)).into_drawing_area();
    root.fill(&SKY).map_err(err)?;
    let scale = (f64::from(width) / scene.width).min(f64::from(height) / scene.height);
    let (cx, cy) = scene.center;
    let to_px = |(x, y): (f64, f64)| -> (i32, i32) {
        (
            (f64::from(width) / 2.0 + (x - cx) * scale).round() as i32,
            (f64::from(height) / 2.0 - (y - cy) * scale).round() as i32,
        )
    };
    // Ground first, then details, then the body on top.
    for layer in [Part::Ground, Part::Detail, Part::Body] {
        let color = match layer {
            Part::Body => BODY,
            Part::Ground => GROUND,
            Part::Detail => DETAIL,
        };
        for (part, shape) in &scene.shapes {
            if *part != layer {
                continue;
            }
            match shape {
                Shape::Polygon(points) => {
                    let px: Vec<(i32, i32)> = points.iter().map(|&p| to_px(p)).collect();
                    root.draw(&Polygon::new(px, color.filled())).map_err(err)?;
                }
                Shape::Circle(c, r) => {
                    let radius = (r * scale).round().max(1.0) as i32;
                    root.draw(&Circle::new(to_px(*c), radius, color.filled()))
                        .map_err(err)?;
                }
                Shape::Capsule(a, b, r) => {
                    let stroke = ((2.0 * r * scale).round() as u32).max(1);
                    root.draw(&PathElement::new(
                        vec![to_px(*a), to_px(*b)],
                        color.stroke_width(stroke),
                    ))
                    .map_err(err)?;
                    for end in [a, b] {
                        let radius = (r * scale).round().max(1.0) as i32;
                        root.draw(&Circle::new(to_px(*end), radius, color.filled()))
                            .map_err(err)?;
                    }
                }
                Shape::Polyline(points) => {
                    let px: Vec<(i32, i32)> = points.iter().map(|&p| to_px(p)).collect();
                    root.draw(&PathElement::new(px, color.stroke_width(3)))
                        .map_err(err)?;
                }
            }
        }
    }
    if !plan.is_empty() {
        let px: Vec<(i32, i32)> = plan.iter().map(|&p| to_px(p)).collect();
        root.draw(&PathElement::new(px.clone(), PLAN.mix(0.5).stroke_width(2)))
            .map_err(err)?;
        for (i, p) in px.iter().enumerate() {
            let fade = 1.0 - 0.7 * i as f64 / px.len() as f64;
            root.draw(&Circle::new(*p, 4, PLAN.mix(fade).filled()))
                .map_err(err)?;
        }
    }
    root.draw(&Text::new(
        caption.to_string(),
        (10, 10),
        (FONT_FAMILY, 18).into_font().color(&BLACK),
    ))
    .map_err(err)?;
    root.present()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
