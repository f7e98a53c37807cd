//! Training-with-PrAC curves (the paper's Figure 4) from `prac train` CSVs: episode return
//! (normalised when asked) and forecast against training steps, as rolling means over 20
//! episodes with one standard deviation.

use std::path::Path;

use anyhow::{Context, bail};
use prac::render::chart::{Panel, Series, line_panels};
use prac::train::eval::mean_std;

pub const WINDOW: usize = 20;

/// (step, return, forecast) per episode row.
pub fn read_curve(path: &Path) -> anyhow::Result<Vec<(f64, f64, f64)>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().context("an empty CSV")?.split(',').collect();
    let col = |name: &str| {
        header.iter().position(|h| *h == name).with_context(|| {
            format!(
                "{}: no '{name}' column (a prac train CSV has step, return, forecast)",
                path.display()
            )
        })
    };
    let (s, r, f) = (col("step")?, col("return")?, col("forecast")?);
    let mut rows = Vec::new();
    for (i, line) in lines.enumerate() {
        let v: Vec<&str> = line.split(',').collect();
        let get = |c: usize| -> anyhow::Result<f64> {
            v.get(c).and_then(|x| x.parse().ok()).with_context(|| {
                format!(
                    "{}: row {}: column {c} is not a number",
                    path.display(),
                    i + 2
                )
            })
        };
        rows.push((get(s)?, get(r)?, get(f)?));
    }
    if rows.is_empty() {
        bail!("{}: no episodes", path.display());
    }
    Ok(rows)
}

/// Rolling mean and std over the last `WINDOW` episodes at each episode's step.
pub fn rolling(
    rows: &[(f64, f64, f64)],
    value: impl Fn(&(f64, f64, f64)) -> f64,
) -> Vec<(f64, f64, f64)> {
    (0..rows.len())
        .map(|i| {
            let window: Vec<f64> = rows[i.saturating_sub(WINDOW - 1)..=i]
                .iter()
                .map(&value)
                .collect();
            let (m, s) = mean_std(&window);
            (rows[i].0, m, s)
        })
        .collect()
}

/// Writes DIR/curves.png; `normalize` = (random return, reference return).
pub fn write(
    csvs: &[std::path::PathBuf],
    normalize: Option<(f64, f64)>,
    dir: &Path,
) -> anyhow::Result<String> {
    std::fs::create_dir_all(dir)?;
    let mut returns = Vec::new();
    let mut forecasts = Vec::new();
    let mut summary = String::new();
    for path in csvs {
        let rows = read_curve(path)?;
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .map(|n| {
                n.trim_end_matches(".csv")
                    .trim_end_matches(".train")
                    .to_string()
            })
            .unwrap_or_default();
        let scale = |r: f64| match normalize {
            Some((rand, reference)) => (r - rand) / (reference - rand),
            None => r,
        };
        let ret = rolling(&rows, |r| scale(r.1));
        let fc = rolling(&rows, |r| r.2);
        let last = ret.last().copied().unwrap_or_default();
        summary.push_str(&format!(
            "{name}: {} episodes to step {}; last {WINDOW}: return {:.3} +- {:.3}, forecast {:.2}\n",
            rows.len(),
            last.0,
            last.1,
            last.2,
            fc.last().map_or(0.0, |f| f.1)
        ));
        returns.push(Series {
            name: name.clone(),
            points: ret,
        });
        forecasts.push(Series { name, points: fc });
    }
    let y = if normalize.is_some() {
        "normalised return"
    } else {
        "episode return"
    };
    line_panels(
        &dir.join("curves.png"),
        &[
            Panel {
                title: "training return".into(),
                x_label: "training steps".into(),
                y_label: y.into(),
                series: returns,
            },
            Panel {
                title: "forecast".into(),
                x_label: "training steps".into(),
                y_label: "mean forecast (steps)".into(),
                series: forecasts,
            },
        ],
        (1100, 450),
    )?;
    Ok(summary)
}
