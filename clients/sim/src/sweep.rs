//! Training-then-PrAC (the paper's Figure 3): V_rand and V_pi measured, then for each eps
//! coefficient the normalised performance, the forecast and the Lemma-1 bound.

use std::fmt::Write as _;
use std::path::Path;

use prac::eval::{Summary, mean_std, random_episodes};
use prac::proto::PolicyInfo;
use prac::render::chart::{Panel, Series, line_panels};
use serde::Serialize;

use crate::play::{Client, EpisodeResult, PlanShape, Tol, play_episode};

#[derive(Clone, Debug, Serialize)]
pub struct SweepRow {
    pub coef: f64,
    pub epsilon: f64,
    pub np: f64,
    pub np_std: f64,
    pub forecast: f64,
    pub forecast_std: f64,
    pub bound: f64,
    pub discounted_return: f64,
    pub return_mean: f64,
    pub replans_per_step: f64,
    pub episodes: usize,
    /// Episodes a walker ended by falling (None for tasks without falls).
    pub falls: Option<usize>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Sweep {
    pub policy: String,
    pub domain: String,
    pub gamma: f64,
    pub v_pi: f64,
    pub v_rand: f64,
    /// The plans' growth and cap where they are not the server's defaults.
    pub plan: Option<String>,
    pub rows: Vec<SweepRow>,
}

/// Plays `episodes` episodes (seeds `seed..`) at one tolerance, several at once.
pub async fn play_many(
    client: &Client,
    info: &PolicyInfo,
    tol: Tol,
    plan: PlanShape,
    episodes: usize,
    seed: u64,
    bar: &indicatif::ProgressBar,
) -> anyhow::Result<Vec<EpisodeResult>> {
    let games = (0..episodes as u64).map(|k| {
        let mut client = client.clone();
        let info = info.clone();
        let bar = bar.clone();
        async move {
            let (result, _) = play_episode(&mut client, &info, tol, plan, seed + k, None).await?;
            bar.inc(1);
            anyhow::Ok(result)
        }
    });
    futures::future::try_join_all(games).await
}

pub async fn run(
    client: &Client,
    info: &PolicyInfo,
    coefs: &[f64],
    plan: PlanShape,
    episodes: usize,
    seed: u64,
    show_progress: bool,
) -> anyhow::Result<Sweep> {
    let gamma = info.gamma;
    let mut env = prac::domains::make(&info.domain)
        .ok_or_else(|| anyhow::anyhow!("unknown domain '{}'", info.domain))?;
    let randoms = random_episodes(env.as_mut(), gamma, episodes, seed)?;
    let v_rand = Summary::of_episodes(&randoms).discounted_mean;
    let bar = crate::progress((coefs.len() + 1) as u64 * episodes as u64, show_progress);
    // V_pi from episodes of their own, so NP at coefficient 0 is an independent estimate of 1.
    let greedy = play_many(
        client,
        info,
        Tol::Absolute(0.0),
        plan,
        episodes,
        seed + 1_000_000,
        &bar,
    )
    .await?;
    let v_pi = Summary::of(greedy.iter().map(|e| e.outcome())).discounted_mean;
    let range = v_pi - v_rand;
    anyhow::ensure!(
        range > 0.0,
        "V_pi = {v_pi:.3} is not above V_rand = {v_rand:.3}: the policy does no better than random"
    );
    let mut rows = Vec::new();
    for &coef in coefs {
        let asked = coef * range;
        let results = play_many(
            client,
            info,
            Tol::Absolute(asked),
            plan,
            episodes,
            seed,
            &bar,
        )
        .await?;
        let np: Vec<f64> = results
            .iter()
            .map(|e| (e.discounted - v_rand) / range)
            .collect();
        let forecasts: Vec<f64> = results.iter().map(|e| e.forecast).collect();
        let (np, np_std) = mean_std(&np);
        let (forecast, forecast_std) = mean_std(&forecasts);
        let summary = Summary::of(results.iter().map(|e| e.outcome()));
        // The eps in force: a guard's max_epsilon_coef may hold it below what was asked.
        let epsilon = results.first().map_or(asked, |e| e.epsilon);
        rows.push(SweepRow {
            coef,
            epsilon,
            np,
            np_std,
            forecast,
            forecast_std,
            // Lemma 1: V^PrAC >= V_pi - eps / (1 - gamma), normalised.
            bound: 1.0 - epsilon / ((1.0 - gamma) * range),
            discounted_return: summary.discounted_mean,
            return_mean: summary.return_mean,
            replans_per_step: mean_std(
                &results
                    .iter()
                    .map(|e| e.replans_per_step)
                    .collect::<Vec<_>>(),
            )
            .0,
            episodes: summary.episodes,
            // Falls only where a fall means something: the walkers, which move forward.
            falls: summary.distance_mean.map(|_| summary.terminated),
        });
    }
    bar.finish_and_clear();
    Ok(Sweep {
        policy: info.name.clone(),
        domain: info.domain.clone(),
        gamma,
        v_pi,
        v_rand,
        plan: plan.describe(),
        rows,
    })
}

pub const CSV_HEADER: &str = "coef,epsilon,np,np_std,forecast,forecast_std,bound,discounted_return,return,replans_per_step,episodes,falls";

impl Sweep {
    /// The largest coefficient whose episodes fell no more often than at eps 0 (walkers only).
    pub fn largest_coef_without_more_falls(&self) -> Option<f64> {
        let baseline = self.rows.iter().find(|r| r.coef == 0.0)?.falls?;
        self.rows
            .iter()
            .filter(|r| r.falls.is_some_and(|f| f <= baseline))
            .map(|r| r.coef)
            .reduce(f64::max)
    }
}

/// Writes DIR/sweep.csv, DIR/sweep.md and DIR/sweep.png.
pub fn write(sweep: &Sweep, dir: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)?;
    let mut csv = format!("{CSV_HEADER}\n");
    for r in &sweep.rows {
        writeln!(
            csv,
            "{},{},{},{},{},{},{},{},{},{},{},{}",
            r.coef,
            r.epsilon,
            r.np,
            r.np_std,
            r.forecast,
            r.forecast_std,
            r.bound,
            r.discounted_return,
            r.return_mean,
            r.replans_per_step,
            r.episodes,
            r.falls.map_or(String::new(), |f| f.to_string())
        )?;
    }
    std::fs::write(dir.join("sweep.csv"), csv)?;

    let mut md = format!(
        "# PrAC sweep: {} ({})\n\nV_pi(s0) = {:.3}, V_rand(s0) = {:.3}, gamma = {}; {} episodes per coefficient{}.\n\n\
         | eps coef | eps | NP | NP std | forecast | forecast std | Lemma-1 bound | return | falls |\n|---|---|---|---|---|---|---|---|---|\n",
        sweep.policy,
        sweep.domain,
        sweep.v_pi,
        sweep.v_rand,
        sweep.gamma,
        sweep.rows.first().map_or(0, |r| r.episodes),
        sweep
            .plan
            .as_ref()
            .map_or(String::new(), |p| format!("; plans: {p}"))
    );
    for r in &sweep.rows {
        writeln!(
            md,
            "| {} | {:.4} | {:.3} | {:.3} | {:.2} | {:.2} | {:.3} | {:.1} | {} |",
            r.coef,
            r.epsilon,
            r.np,
            r.np_std,
            r.forecast,
            r.forecast_std,
            r.bound,
            r.return_mean,
            r.falls
                .map_or("-".to_string(), |f| format!("{f}/{}", r.episodes))
        )?;
    }
    if let Some(coef) = sweep.largest_coef_without_more_falls() {
        writeln!(
            md,
            "\nLargest coefficient with no more falls than at eps 0: {coef}."
        )?;
    }
    std::fs::write(dir.join("sweep.md"), md)?;

    let points = |f: &dyn Fn(&SweepRow) -> (f64, f64)| -> Vec<(f64, f64, f64)> {
        sweep
            .rows
            .iter()
            .map(|r| {
                let (m, s) = f(r);
                (r.coef, m, s)
            })
            .collect()
    };
    line_panels(
        &dir.join("sweep.png"),
        &[
            Panel {
                title: format!("{}: normalised performance", sweep.domain),
                x_label: "eps coefficient".into(),
                y_label: "NP".into(),
                series: vec![
                    Series {
                        name: "PrAC".into(),
                        points: points(&|r| (r.np, r.np_std)),
                    },
                    Series {
                        name: "Lemma-1 bound".into(),
                        points: points(&|r| (r.bound, 0.0)),
                    },
                    Series {
                        name: "pi (1)".into(),
                        points: points(&|_| (1.0, 0.0)),
                    },
                    Series {
                        name: "random (0)".into(),
                        points: points(&|_| (0.0, 0.0)),
                    },
                ],
            },
            Panel {
                title: format!("{}: forecast", sweep.domain),
                x_label: "eps coefficient".into(),
                y_label: "mean forecast (steps)".into(),
                series: vec![Series {
                    name: "PrAC".into(),
                    points: points(&|r| (r.forecast, r.forecast_std)),
                }],
            },
        ],
        (1100, 450),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(coef: f64, falls: Option<usize>) -> SweepRow {
        SweepRow {
            coef,
            epsilon: 0.0,
            np: 1.0,
            np_std: 0.0,
            forecast: 1.0,
            forecast_std: 0.0,
            bound: 1.0,
            discounted_return: 0.0,
            return_mean: 0.0,
            replans_per_step: 0.0,
            episodes: 20,
            falls,
        }
    }

    fn sweep(rows: Vec<SweepRow>) -> Sweep {
        Sweep {
            policy: "p".into(),
            domain: "hopper".into(),
            gamma: 0.98,
            v_pi: 1.0,
            v_rand: 0.0,
            plan: None,
            rows,
        }
    }

    #[test]
    fn the_largest_coefficient_is_the_last_that_falls_no_more_than_eps_zero() {
        let rows = [(0.0, 1), (0.001, 0), (0.003, 1), (0.005, 4), (0.01, 7)];
        let s = sweep(rows.iter().map(|&(c, f)| row(c, Some(f))).collect());
        assert_eq!(s.largest_coef_without_more_falls(), Some(0.003));
        let none = sweep(vec![row(0.0, None), row(0.01, None)]);
        assert_eq!(none.largest_coef_without_more_falls(), None);
    }
}
