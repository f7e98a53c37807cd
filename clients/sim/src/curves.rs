//! Training-with-PrAC curves (the paper's Figure 4) from `prac train` CSVs: episode return
//! (normalised when asked) and forecast against training steps, as rolling means over 20
//! episodes with one standard deviation; runs of one setting at several seeds also as their
//! mean and std across seeds, as the paper draws it.

use std::path::Path;

use anyhow::{Context, bail};
use prac::eval::mean_std;
use prac::render::chart::{Panel, Series, line_panels};

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

/// The setting a run belongs to: `NAME-seedK` and `NAME` (the default seed 0) are seeds of
/// one setting `NAME`.
pub fn setting_of(run: &str) -> &str {
    match run.rsplit_once("-seed") {
        Some((setting, k)) if !k.is_empty() && k.bytes().all(|b| b.is_ascii_digit()) => setting,
        _ => run,
    }
}

/// Points on the grid across the steps every run has reached.
const SEED_GRID_POINTS: f64 = 500.0;

/// Mean and std across runs (one per seed) of their rolling means, on an even grid over the
/// steps all of them have reached: each run contributes its latest point at or before a grid
/// step. The std is the population std, so two seeds' band spans exactly the two runs.
pub fn across_seeds(runs: &[&[(f64, f64, f64)]]) -> Vec<(f64, f64, f64)> {
    if runs.is_empty() || runs.iter().any(|r| r.is_empty()) {
        return Vec::new();
    }
    let start = runs
        .iter()
        .map(|r| r[0].0)
        .fold(f64::NEG_INFINITY, f64::max);
    let end = runs
        .iter()
        .map(|r| r[r.len() - 1].0)
        .fold(f64::INFINITY, f64::min);
    if start > end {
        return Vec::new();
    }
    let every = ((end - start) / SEED_GRID_POINTS).max(1.0);
    let latest = |run: &[(f64, f64, f64)], x: f64| run[run.partition_point(|p| p.0 <= x) - 1].1;
    let mut points = Vec::new();
    let mut x = start;
    loop {
        let (mean, std) = mean_std(&runs.iter().map(|r| latest(r, x)).collect::<Vec<_>>());
        points.push((x, mean, std));
        if x >= end {
            return points;
        }
        x = (x + every).min(end);
    }
}

/// One line of Figure 4: a run's rolling curves (one point per episode), or a setting's mean
/// across seeds.
struct Line {
    name: String,
    returns: Vec<(f64, f64, f64)>,
    forecasts: Vec<(f64, f64, f64)>,
}

/// Writes DIR/curves.png (every run) and, where a setting has runs at several seeds,
/// DIR/curves-seeds.png (per setting, the mean and std across its seeds); returns a summary
/// and the pictures written.
pub fn write(
    csvs: &[std::path::PathBuf],
    normalize: Option<(f64, f64)>,
    dir: &Path,
) -> anyhow::Result<(String, Vec<std::path::PathBuf>)> {
    std::fs::create_dir_all(dir)?;
    let scale = |r: f64| match normalize {
        Some((rand, reference)) => (r - rand) / (reference - rand),
        None => r,
    };
    let mut runs = Vec::new();
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
        runs.push(Line {
            name,
            returns: rolling(&rows, |r| scale(r.1)),
            forecasts: rolling(&rows, |r| r.2),
        });
    }
    let mut summary = String::new();
    for run in &runs {
        let last = run.returns.last().copied().unwrap_or_default();
        summary.push_str(&format!(
            "{}: {} episodes to step {}; last {WINDOW}: return {:.3} +- {:.3}, forecast {:.2}\n",
            run.name,
            run.returns.len(),
            last.0,
            last.1,
            last.2,
            run.forecasts.last().map_or(0.0, |f| f.1)
        ));
    }
    let y = if normalize.is_some() {
        "normalised return"
    } else {
        "episode return"
    };
    let every_run = dir.join("curves.png");
    draw(&every_run, &runs, y)?;
    let mut written = vec![every_run];

    let mut settings: Vec<(&str, Vec<&Line>)> = Vec::new();
    for run in &runs {
        let setting = setting_of(&run.name);
        match settings.iter_mut().find(|(s, _)| *s == setting) {
            Some((_, seeds)) => seeds.push(run),
            None => settings.push((setting, vec![run])),
        }
    }
    if settings.iter().any(|(_, seeds)| seeds.len() > 1) {
        let mut lines = Vec::new();
        for (setting, seeds) in &settings {
            let returns = across_seeds(&seeds.iter().map(|r| &r.returns[..]).collect::<Vec<_>>());
            let forecasts =
                across_seeds(&seeds.iter().map(|r| &r.forecasts[..]).collect::<Vec<_>>());
            let last = returns.last().copied().unwrap_or_default();
            summary.push_str(&format!(
                "{setting}: {} seeds to step {}; mean of their last-{WINDOW} returns {:.3} +- {:.3} across seeds, forecast {:.2}\n",
                seeds.len(),
                last.0,
                last.1,
                last.2,
                forecasts.last().map_or(0.0, |f| f.1)
            ));
            let name = match seeds.len() {
                1 => format!("{setting} (1 seed)"),
                n => format!("{setting} ({n} seeds)"),
            };
            lines.push(Line {
                name,
                returns,
                forecasts,
            });
        }
        let by_setting = dir.join("curves-seeds.png");
        draw(&by_setting, &lines, &format!("{y}, mean across seeds"))?;
        written.push(by_setting);
    }
    Ok((summary, written))
}

/// The return and forecast panels of Figure 4.
fn draw(path: &Path, lines: &[Line], y_label: &str) -> anyhow::Result<()> {
    let series = |points: fn(&Line) -> &Vec<(f64, f64, f64)>| {
        lines
            .iter()
            .map(|l| Series {
                name: l.name.clone(),
                points: points(l).clone(),
            })
            .collect()
    };
    line_panels(
        path,
        &[
            Panel {
                title: "training return".into(),
                x_label: "training steps".into(),
                y_label: y_label.into(),
                series: series(|l| &l.returns),
            },
            Panel {
                title: "forecast".into(),
                x_label: "training steps".into(),
                y_label: "mean forecast (steps)".into(),
                series: series(|l| &l.forecasts),
            },
        ],
        (1100, 450),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeds_of_a_setting_share_its_name() {
        assert_eq!(setting_of("cheetah-prac-0.01-seed2"), "cheetah-prac-0.01");
        assert_eq!(setting_of("cheetah-prac-0.01"), "cheetah-prac-0.01");
        assert_eq!(setting_of("lander-seed1"), "lander");
        assert_eq!(setting_of("lander-seeds"), "lander-seeds");
        assert_eq!(setting_of("lander-seed"), "lander-seed");
    }

    #[test]
    fn seeds_average_over_the_steps_all_of_them_reached() {
        // Seed a: 10 until step 100, then 30; seed b: 20 from step 50, ends at 200.
        let a = vec![(0.0, 10.0, 0.0), (100.0, 30.0, 0.0), (300.0, 50.0, 0.0)];
        let b = vec![(50.0, 20.0, 0.0), (200.0, 40.0, 0.0)];
        let points = across_seeds(&[&a, &b]);
        assert_eq!(
            points.first().unwrap().0,
            50.0,
            "starts where both have begun"
        );
        assert_eq!(
            points.last().unwrap().0,
            200.0,
            "ends where the shorter stops"
        );
        let at = |x: f64| *points.iter().find(|p| p.0 >= x).unwrap();
        assert_eq!(at(50.0), (50.0, 15.0, 5.0));
        let mid = at(100.0);
        assert!(mid.0 >= 100.0 && mid.0 < 200.0);
        assert_eq!((mid.1, mid.2), (25.0, 5.0));
        assert_eq!(at(200.0), (200.0, 35.0, 5.0));
        assert!(points.windows(2).all(|w| w[0].0 < w[1].0));
    }

    #[test]
    fn runs_that_never_overlap_have_no_mean() {
        let a = vec![(0.0, 1.0, 0.0), (10.0, 1.0, 0.0)];
        let b = vec![(20.0, 2.0, 0.0), (30.0, 2.0, 0.0)];
        assert!(across_seeds(&[&a, &b]).is_empty());
        assert!(across_seeds(&[]).is_empty());
    }
}
