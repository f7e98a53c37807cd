//! Figure 4's table from `prac train` CSVs: per run, the training return at chosen steps (the
//! last 20 episodes' mean) and relative to plain SAC of the same seed, the forecast, how many
//! training episodes ended before the domain's step limit, the last deterministic evaluation
//! and the wall seconds per 1,000 steps; per setting with several seeds, their mean.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};

use crate::curves::{WINDOW, setting_of};

/// Named numeric columns of a CSV with a header row. A cell may be empty: `prac train` leaves
/// a value out where it has none (a lander's distance) and where an older CSV was widened.
struct Columns {
    header: Vec<String>,
    rows: Vec<Vec<Option<f64>>>,
}

impl Columns {
    fn read(path: &Path) -> anyhow::Result<Columns> {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let mut lines = text.lines().filter(|line| !line.trim().is_empty());
        let header: Vec<String> = lines
            .next()
            .with_context(|| format!("{}: an empty CSV", path.display()))?
            .split(',')
            .map(str::to_string)
            .collect();
        let mut rows = Vec::new();
        for (i, line) in lines.enumerate() {
            let row: Vec<Option<f64>> = line
                .split(',')
                .map(|v| match v.trim() {
                    "" => Ok(None),
                    v => v.parse::<f64>().map(Some),
                })
                .collect::<Result<_, _>>()
                .with_context(|| format!("{}: row {} is not all numbers", path.display(), i + 2))?;
            if row.len() != header.len() {
                bail!(
                    "{}: row {} has {} values for {} columns",
                    path.display(),
                    i + 2,
                    row.len(),
                    header.len()
                );
            }
            rows.push(row);
        }
        Ok(Columns { header, rows })
    }

    /// A column's cells, where the CSV has it.
    fn cells(&self, name: &str) -> Option<Vec<Option<f64>>> {
        let at = self.header.iter().position(|h| h == name)?;
        Some(self.rows.iter().map(|r| r[at]).collect())
    }

    /// A column every row must fill.
    fn column(&self, path: &Path, name: &str) -> anyhow::Result<Vec<f64>> {
        let cells = self
            .cells(name)
            .with_context(|| format!("{}: no '{name}' column", path.display()))?;
        cells
            .iter()
            .enumerate()
            .map(|(i, v)| {
                v.with_context(|| format!("{}: row {}: no '{name}'", path.display(), i + 2))
            })
            .collect()
    }
}

/// What the table says of one run.
#[derive(Clone, Debug, PartialEq)]
pub struct RunSummary {
    pub name: String,
    pub setting: String,
    pub seed: u64,
    /// Every episode ran with eps 0 and a forecast of 1: plain SAC.
    pub plain_sac: bool,
    /// The last step the run recorded (an episode's end or an evaluation).
    pub steps: f64,
    /// Per asked step: the mean return of the last `WINDOW` episodes ended by it, where the run
    /// reached it.
    pub returns_at: Vec<Option<f64>>,
    /// Mean forecast of the last `WINDOW` episodes.
    pub forecast: f64,
    pub episodes: usize,
    /// Episodes shorter than the domain's step limit (a fall, or a lander's landing or crash).
    pub ended_early: Option<usize>,
    /// The last evaluation: its step, mean return and episodes that ended early (where its CSV
    /// records them).
    pub final_eval: Option<(f64, f64, Option<f64>)>,
    /// Median wall seconds per 1,000 steps over the evaluation intervals.
    pub seconds_per_1k: Option<f64>,
}

fn seed_of(name: &str) -> u64 {
    name.rsplit_once("-seed")
        .and_then(|(_, k)| k.parse().ok())
        .unwrap_or(0)
}

fn median(mut values: Vec<f64>) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    values.sort_by(f64::total_cmp);
    let n = values.len();
    Some(match n % 2 {
        1 => values[n / 2],
        _ => (values[n / 2 - 1] + values[n / 2]) / 2.0,
    })
}

/// Summarises the run whose train CSV is `train` (NAME.train.csv, with NAME.eval.csv beside it
/// where it evaluated); `episode_len` is the domain's step limit, where known.
pub fn summarise(train: &Path, at: &[f64], episode_len: Option<u32>) -> anyhow::Result<RunSummary> {
    let name = train
        .file_name()
        .and_then(|n| n.to_str())
        .map(|n| n.trim_end_matches(".csv").trim_end_matches(".train"))
        .unwrap_or_default()
        .to_string();
    let csv = Columns::read(train)?;
    let steps = csv.column(train, "step")?;
    let returns = csv.column(train, "return")?;
    let forecasts = csv.column(train, "forecast")?;
    let lengths = csv.column(train, "length")?;
    let epsilons = csv.column(train, "epsilon")?;
    if steps.is_empty() {
        bail!("{}: no episodes", train.display());
    }
    if let Some(i) = steps.windows(2).position(|w| w[1] < w[0]) {
        bail!(
            "{}: row {}: steps go back ({} after {})",
            train.display(),
            i + 3,
            steps[i + 1],
            steps[i]
        );
    }
    let eval_path = train.with_file_name(format!("{name}.eval.csv"));
    let eval = match eval_path.exists() {
        true => Some(Columns::read(&eval_path)?),
        false => None,
    };
    let (eval_steps, final_eval, seconds_per_1k) = match &eval {
        Some(e) if !e.rows.is_empty() => {
            let s = e.column(&eval_path, "step")?;
            let mean = e.column(&eval_path, "eval_return_mean")?;
            // Older evaluations recorded neither (no column, or empty cells once widened).
            let none = vec![None; s.len()];
            let ended = e.cells("eval_terminated").unwrap_or_else(|| none.clone());
            let seconds = e.cells("seconds").unwrap_or(none);
            let last = s.len() - 1;
            // Intervals across a resume restart the clock (a negative difference): skipped.
            let rates = (1..s.len())
                .filter_map(|i| {
                    let (from, to) = (seconds[i - 1]?, seconds[i]?);
                    (s[i] > s[i - 1] && to >= from)
                        .then(|| (to - from) / (s[i] - s[i - 1]) * 1000.0)
                })
                .collect();
            (
                s.clone(),
                Some((s[last], mean[last], ended[last])),
                median(rates),
            )
        }
        _ => (Vec::new(), None, None),
    };
    let last_step = steps[steps.len() - 1].max(eval_steps.last().copied().unwrap_or(0.0));
    let window_mean = |values: &[f64], end: usize| {
        let from = end.saturating_sub(WINDOW);
        values[from..end].iter().sum::<f64>() / (end - from) as f64
    };
    let returns_at = at
        .iter()
        .map(|&x| {
            let ended_by = steps.partition_point(|&s| s <= x);
            (last_step >= x && ended_by > 0).then(|| window_mean(&returns, ended_by))
        })
        .collect();
    Ok(RunSummary {
        setting: setting_of(&name).to_string(),
        seed: seed_of(&name),
        // eps 0 alone does not make plain SAC: a critic below V_rand gives eps 0 too, and plans
        // can still hold; plain SAC's plans are one action long.
        plain_sac: epsilons.iter().all(|&e| e == 0.0) && forecasts.iter().all(|&f| f == 1.0),
        steps: last_step,
        returns_at,
        forecast: window_mean(&forecasts, forecasts.len()),
        episodes: steps.len(),
        ended_early: episode_len.map(|n| lengths.iter().filter(|&&l| l < f64::from(n)).count()),
        final_eval,
        seconds_per_1k,
        name,
    })
}

fn thousands(v: f64) -> String {
    let digits = format!("{:.0}", v.abs());
    let mut out = String::new();
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    if v < -0.5 { format!("-{out}") } else { out }
}

fn steps_label(x: f64) -> String {
    match x >= 1000.0 && x % 1000.0 == 0.0 {
        true => format!("{}k", thousands(x / 1000.0)),
        false => thousands(x),
    }
}

fn joined(values: impl Iterator<Item = String>) -> String {
    values.collect::<Vec<_>>().join(" / ")
}

/// The markdown table of `runs` at the steps `at`: one row per run (plain SAC's settings first,
/// then by setting and seed), then one per setting with several seeds: the mean over the seeds
/// that reached each step, against plain SAC's mean over the same seeds. With `normalize`
/// (R_RAND, R_REF) training returns are shown normalised, so that ratios stay meaningful for a
/// domain whose returns can be negative; a ratio needs plain SAC's (normalised) return above 0.
pub fn markdown(runs: &[RunSummary], at: &[f64], normalize: Option<(f64, f64)>) -> String {
    let scale = |v: f64| normalize.map_or(v, |(rand, reference)| (v - rand) / (reference - rand));
    let number = |v: Option<f64>| match (v, normalize) {
        (None, _) => "-".to_string(),
        (Some(v), None) => thousands(v),
        (Some(v), Some(_)) => format!("{:.3}", scale(v)),
    };
    let (what, eval_return) = match normalize {
        Some(_) => ("normalised training return", "return (not normalised)"),
        None => ("training return", "return"),
    };
    let mut runs: Vec<&RunSummary> = runs.iter().collect();
    runs.sort_by(|a, b| {
        (!a.plain_sac, &a.setting, a.seed).cmp(&(!b.plain_sac, &b.setting, b.seed))
    });
    let at_label = joined(at.iter().map(|&x| steps_label(x)));
    let mut out = format!(
        "| run | steps | {what} at {at_label} (last {WINDOW} episodes) | relative to plain SAC of its seed | forecast (last {WINDOW} episodes) | training episodes ended early | last evaluation: step, {eval_return}, ended early | wall s per 1,000 steps (median) |\n|---|---:|---|---|---:|---:|---|---:|\n"
    );
    let plain = |seed: u64| runs.iter().find(|r| r.plain_sac && r.seed == seed);
    let ratio = |v: Option<f64>, base: Option<f64>| match (v.map(scale), base.map(scale)) {
        (Some(v), Some(b)) if b > 0.0 => format!("{:.2}", v / b),
        _ => "-".to_string(),
    };
    for run in &runs {
        let base = plain(run.seed);
        let relative = joined(
            run.returns_at
                .iter()
                .enumerate()
                .map(|(i, &v)| ratio(v, base.and_then(|b| b.returns_at[i]))),
        );
        let eval = run.final_eval.map_or("-".to_string(), |(s, r, e)| {
            let ended = e.map_or("-".to_string(), |e| format!("{e:.0}"));
            format!("{}, {:.1}, {ended}", steps_label(s), r)
        });
        out.push_str(&format!(
            "| {} | {} | {} | {relative} | {:.2} | {} | {eval} | {} |\n",
            run.name,
            thousands(run.steps),
            joined(run.returns_at.iter().map(|&v| number(v))),
            run.forecast,
            run.ended_early.map_or("-".to_string(), |e| format!(
                "{} of {}",
                thousands(e as f64),
                thousands(run.episodes as f64)
            )),
            run.seconds_per_1k
                .map_or("-".to_string(), |s| format!("{s:.1}")),
        ));
    }
    let mut settings: Vec<&str> = Vec::new();
    for run in &runs {
        if !settings.contains(&run.setting.as_str()) {
            settings.push(&run.setting);
        }
    }
    let mean = |values: &[f64]| {
        (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
    };
    for setting in settings {
        let seeds: Vec<&&RunSummary> = runs.iter().filter(|r| r.setting == setting).collect();
        if seeds.len() < 2 {
            continue;
        }
        let reached = |i: usize| -> Vec<&&RunSummary> {
            seeds
                .iter()
                .copied()
                .filter(|r| r.returns_at[i].is_some())
                .collect()
        };
        let counts = joined((0..at.len()).map(|i| reached(i).len().to_string()));
        let means = joined((0..at.len()).map(|i| {
            let values: Vec<f64> = reached(i).iter().filter_map(|r| r.returns_at[i]).collect();
            number(mean(&values))
        }));
        // Seeds whose plain SAC reached the step too, so both means are over the same seeds.
        let relative = joined((0..at.len()).map(|i| {
            let pairs: Vec<(f64, f64)> = reached(i)
                .iter()
                .filter_map(|r| Some((r.returns_at[i]?, plain(r.seed)?.returns_at[i]?)))
                .collect();
            let runs_mean = mean(&pairs.iter().map(|p| p.0).collect::<Vec<_>>());
            let plain_mean = mean(&pairs.iter().map(|p| p.1).collect::<Vec<_>>());
            ratio(runs_mean, plain_mean)
        }));
        let forecast = seeds.iter().map(|r| r.forecast).sum::<f64>() / seeds.len() as f64;
        out.push_str(&format!(
            "| {setting}, mean of {} seeds (seeds reaching each step: {counts}) | - | {means} | {relative} (means over the same seeds) | {forecast:.2} | - | - | - |\n",
            seeds.len()
        ));
    }
    out
}

/// Summaries of the runs whose train CSVs are `csvs`, in order.
pub fn summarise_all(
    csvs: &[PathBuf],
    at: &[f64],
    episode_len: Option<u32>,
) -> anyhow::Result<Vec<RunSummary>> {
    csvs.iter().map(|p| summarise(p, at, episode_len)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const TRAIN_HEADER: &str = "step,episode,return,discounted_return,length,forecast,epsilon,critic_loss,actor_loss,model_loss,ent_coef";

    /// A run of `episodes` episodes of 100 steps (every third ending early, at 40 steps), each
    /// returning its index times `scale`, with forecast `forecast` and eps `eps`.
    fn write_run(dir: &Path, name: &str, episodes: usize, scale: f64, eps: f64) -> PathBuf {
        let mut text = format!("{TRAIN_HEADER}\n");
        let mut step = 0;
        for e in 0..episodes {
            let length = if e % 3 == 2 { 40 } else { 100 };
            step += length;
            let forecast = if eps > 0.0 { 3.0 } else { 1.0 };
            text.push_str(&format!(
                "{step},{e},{},0,{length},{forecast},{eps},0,0,0,0\n",
                e as f64 * scale
            ));
        }
        let path = dir.join(format!("{name}.train.csv"));
        std::fs::write(&path, text).unwrap();
        path
    }

    #[test]
    fn a_run_is_summarised_at_the_steps_it_reached() {
        let dir = tempfile::tempdir().unwrap();
        let train = write_run(dir.path(), "fig4-sac", 30, 10.0, 0.0);
        std::fs::write(
            dir.path().join("fig4-sac.eval.csv"),
            "step,eval_return_mean,eval_return_std,eval_discounted_mean,eval_terminated,eval_distance_mean,seconds\n\
             1000,5,0,0,2,0,10\n2000,7.5,0,0,1,0,30\n2200,8,0,0,1,0,31\n2400,9,0,0,0,0,40\n",
        )
        .unwrap();
        let run = summarise(&train, &[1000.0, 2000.0, 3000.0], Some(100)).unwrap();
        // Episode ends: 100, 200, 240, 340, ... ; 12 episodes end by step 1000 (the 12th at 960).
        assert_eq!(run.episodes, 30);
        assert_eq!(run.ended_early, Some(10));
        assert!(run.plain_sac);
        assert_eq!((run.setting.as_str(), run.seed), ("fig4-sac", 0));
        // The last 20 episodes ended by step 1000 are episodes 0..=11: mean 5.5 * 10.
        assert_eq!(run.returns_at[0], Some(55.0));
        // By 2000: episodes 4..=23 (23 ends at 1920), mean 13.5 * 10.
        assert_eq!(run.returns_at[1], Some(135.0));
        // The run's last episode ends at 2400: 3000 was not reached.
        assert_eq!(run.steps, 2400.0);
        assert_eq!(run.returns_at[2], None);
        assert_eq!(run.forecast, 1.0);
        assert_eq!(run.final_eval, Some((2400.0, 9.0, Some(0.0))));
        // 20, 5 and 45 s per 1,000 steps between evaluations: the median is 20.
        assert_eq!(run.seconds_per_1k, Some(20.0));
    }

    #[test]
    fn runs_are_compared_with_plain_sac_of_their_seed_and_seeds_are_averaged() {
        let dir = tempfile::tempdir().unwrap();
        let csvs = vec![
            write_run(dir.path(), "fig4-sac", 30, 10.0, 0.0),
            write_run(dir.path(), "fig4-sac-seed1", 30, 20.0, 0.0),
            write_run(dir.path(), "fig4-prac-0.01", 30, 20.0, 0.5),
            write_run(dir.path(), "fig4-prac-0.01-seed1", 13, 20.0, 0.5),
        ];
        let at = [1000.0, 2000.0];
        let runs = summarise_all(&csvs, &at, None).unwrap();
        assert_eq!(runs[3].seed, 1);
        assert!(!runs[2].plain_sac);
        assert_eq!(runs[3].returns_at, vec![Some(110.0), None]);
        let table = markdown(&runs, &at, None);
        let row = |name: &str| {
            table
                .lines()
                .find(|l| l.starts_with(&format!("| {name} ")))
                .unwrap_or_else(|| panic!("no row {name} in\n{table}"))
                .to_string()
        };
        // Seed 0: PrAC returns twice plain SAC's at both steps.
        assert!(row("fig4-prac-0.01").contains("| 2.00 / 2.00 |"), "{table}");
        // Seed 1: as its own plain SAC at 1000, not reached at 2000.
        assert!(
            row("fig4-prac-0.01-seed1").contains("| 1.00 / - |"),
            "{table}"
        );
        assert!(row("fig4-sac").contains("| 1.00 / 1.00 |"), "{table}");
        // No step limit given: no count of episodes that ended early.
        assert!(row("fig4-prac-0.01").contains("| 3.00 | - |"), "{table}");
        // The PrAC setting's mean: (110 + 110) / 2 at 1000 against plain SAC's (55 + 110) / 2.
        let mean = row("fig4-prac-0.01, mean of 2 seeds");
        assert!(mean.contains("(seeds reaching each step: 2 / 1)"), "{mean}");
        assert!(mean.contains("| 110 / 270 |"), "{mean}");
        // Against plain SAC over the same seeds: both at 1000, seed 0 alone at 2000.
        let relative = format!(
            "| {:.2} / {:.2} (means over the same seeds) |",
            110.0 / 82.5,
            2.0
        );
        assert!(mean.contains(&relative), "{mean}");
        // Plain SAC's settings come first, then by setting and seed.
        let order: Vec<&str> = table
            .lines()
            .skip(2)
            .map(|l| l.split(" | ").next().unwrap())
            .collect();
        assert_eq!(
            &order[..4],
            [
                "| fig4-sac",
                "| fig4-sac-seed1",
                "| fig4-prac-0.01",
                "| fig4-prac-0.01-seed1"
            ]
        );
    }

    #[test]
    fn an_older_evaluation_csv_without_falls_or_time_still_gives_its_return() {
        let dir = tempfile::tempdir().unwrap();
        let train = write_run(dir.path(), "lander", 30, 1.0, 0.0);
        std::fs::write(
            dir.path().join("lander.eval.csv"),
            "step,eval_return_mean,eval_return_std\n1000,-5,1\n\n2000,7.5,2\n",
        )
        .unwrap();
        let run = summarise(&train, &[1000.0], Some(100)).unwrap();
        assert_eq!(run.final_eval, Some((2000.0, 7.5, None)));
        assert_eq!(run.seconds_per_1k, None);
        let table = markdown(&[run], &[1000.0], None);
        assert!(table.contains("| 2k, 7.5, - | - |"), "{table}");
        // Widened by a resumed run: empty cells before, values after; a distance it never had.
        std::fs::write(
            dir.path().join("lander.eval.csv"),
            "step,eval_return_mean,eval_return_std,eval_discounted_mean,eval_terminated,eval_distance_mean,seconds\n\
             1000,-5,1,0,,,\n2000,7.5,2,0,,,\n3000,9,2,0,1,,50\n4000,9.5,2,0,0,,80\n",
        )
        .unwrap();
        let run = summarise(&train, &[1000.0], Some(100)).unwrap();
        assert_eq!(run.final_eval, Some((4000.0, 9.5, Some(0.0))));
        assert_eq!(
            run.seconds_per_1k,
            Some(30.0),
            "only the interval with both times"
        );
    }

    #[test]
    fn normalised_returns_keep_ratios_meaningful_where_returns_are_negative() {
        let dir = tempfile::tempdir().unwrap();
        // Plain SAC returns index * -1 (0 down to -29), PrAC index * -2: both below zero.
        let csvs = vec![
            write_run(dir.path(), "lander", 30, -1.0, 0.0),
            write_run(dir.path(), "lander-prac-0.01", 30, -2.0, 0.5),
        ];
        let runs = summarise_all(&csvs, &[1000.0], None).unwrap();
        // Raw, plain SAC's mean is -5.5: no ratio.
        let raw = markdown(&runs, &[1000.0], None);
        assert!(raw.contains("| -6 | - |"), "{raw}");
        // Normalised with R_RAND -100, R_REF 200: 94.5 / 300 and 89 / 300, ratio 0.94.
        let table = markdown(&runs, &[1000.0], Some((-100.0, 200.0)));
        assert!(
            table.contains("normalised training return at 1k"),
            "{table}"
        );
        assert!(table.contains("| 0.315 | 1.00 |"), "{table}");
        assert!(table.contains("| 0.297 | 0.94 |"), "{table}");
    }

    #[test]
    fn a_malformed_csv_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.train.csv");
        std::fs::write(&path, "step,return\n1,2\n").unwrap();
        let err = summarise(&path, &[1.0], None).unwrap_err().to_string();
        assert!(err.contains("no 'forecast' column"), "{err}");
        std::fs::write(&path, format!("{TRAIN_HEADER}\n1,2,3\n")).unwrap();
        let err = summarise(&path, &[1.0], None).unwrap_err().to_string();
        assert!(err.contains("row 2 has 3 values"), "{err}");
        let rows = "100,0,1,0,100,1,0,0,0,0,0\n50,1,1,0,100,1,0,0,0,0,0";
        std::fs::write(&path, format!("{TRAIN_HEADER}\n{rows}\n")).unwrap();
        let err = summarise(&path, &[1.0], None).unwrap_err().to_string();
        assert!(err.contains("row 3: steps go back (50 after 100)"), "{err}");
    }
}
