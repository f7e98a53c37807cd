//! `prac model-error`: the dynamics model's forecasts against what followed, on the bundle's own
//! domain, at each eps coefficient of the sweeps; and what the plan held before each fall.

use std::path::PathBuf;
use std::sync::Arc;

use clap::Args;

use prac::eval::forecasts::{FORECAST_STEPS, ForecastReport, STEPS_BEFORE_FALL, forecast_errors};
use prac::proto::session_options::{Growth, Tolerance};
use prac::testing::serve::SessionSettings;

#[derive(Args, Debug)]
pub struct ModelErrorArgs {
    /// The bundle (its domain must be one of prac's).
    bundle: PathBuf,
    /// eps coefficients to play at (eps = coef x (V_pi - V_rand)); 0 is the policy's own plans.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0,0.001,0.003,0.005,0.008,0.01"
    )]
    coefs: Vec<f64>,
    /// Episodes per coefficient, seeds --seed, --seed + 1, ...
    #[arg(long, default_value_t = 5)]
    episodes: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Extend every plan to this many actions (the session option `fixed`), so that every
    /// forecast reaches that far; without it, the session's default growth.
    #[arg(long)]
    fixed: Option<u32>,
    /// Guard the plans (the session option guard.every_critic): any one critic rating a kept
    /// action more than eps below pi(s) also breaks the plan.
    #[arg(long)]
    every_critic: bool,
    /// Guard the plans (guard.support_limit): an action further than Z of the policy's
    /// standard deviations from its mean also breaks the plan [default: no limit].
    #[arg(long, value_name = "Z")]
    support_limit: Option<f64>,
    /// The paper's test alone, whatever guard the bundle sets by default (without any guard flag
    /// the sessions get the bundle's default_guard, as served).
    #[arg(long, conflicts_with_all = ["every_critic", "support_limit"])]
    paper_test: bool,
    /// Also write every figure, with the traces before falls, as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
}

impl ModelErrorArgs {
    pub fn run(self) -> anyhow::Result<()> {
        let policy = Arc::new(prac::bundle::load(&self.bundle)?);
        let domain = policy.manifest.domain.clone();
        let mut env = prac::domains::make(&domain).ok_or_else(|| {
            anyhow::anyhow!("the bundle is for domain {domain:?}, which this build does not have")
        })?;
        if policy.model.is_none() {
            anyhow::bail!("the bundle has no dynamics model: it makes no forecasts");
        }
        let mut reports = Vec::with_capacity(self.coefs.len());
        for &coef in &self.coefs {
            let options = prac::proto::SessionOptions {
                tolerance: Some(Tolerance::EpsilonCoef(coef)),
                growth: self.fixed.map(Growth::Fixed),
                guard: (self.every_critic || self.support_limit.is_some() || self.paper_test)
                    .then_some(prac::proto::PlanGuard {
                        every_critic: self.every_critic,
                        support_limit: self.support_limit.unwrap_or(0.0),
                        ..Default::default()
                    }),
                ..Default::default()
            };
            let config = SessionSettings::resolve(Some(&options), &policy, prac::plan::MAX_CHUNK)
                .map_err(|e| anyhow::anyhow!(e))?
                .replan;
            let report = forecast_errors(&policy, env.as_mut(), config, self.episodes, self.seed)?;
            reports.push((coef, report));
        }
        let (low, high) = env.spec().obs_range();
        print!(
            "{}",
            markdown(&policy.manifest.name, &domain, &self, (low, high), &reports)
        );
        if let Some(path) = &self.json {
            let rows: Vec<_> = reports
                .iter()
                .map(|(coef, report)| serde_json::json!({"epsilon_coef": coef, "report": report}))
                .collect();
            std::fs::write(path, serde_json::to_string_pretty(&rows)?)?;
        }
        Ok(())
    }
}

fn markdown(
    name: &str,
    domain: &str,
    args: &ModelErrorArgs,
    (low, high): (f32, f32),
    reports: &[(f64, ForecastReport)],
) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    let growth = match args.fixed {
        Some(n) => format!("plans extended to {n} actions (fixed {n})"),
        None => "the session's default growth".to_string(),
    };
    let ks: Vec<String> = FORECAST_STEPS.iter().map(|k| format!("k={k}")).collect();
    let head = |first: &str| {
        format!(
            "| {first} | {} |\n|---|{}",
            ks.join(" | "),
            "---:|".repeat(ks.len())
        )
    };
    let _ = writeln!(
        out,
        "# Forecasts against what followed: {name} ({domain})\n\n{} episodes per coefficient \
         (seeds from {}), {growth}. Errors are RMS over the observation's entries of \
         (predicted - observed) / the model's observation std; n: forecasts measured.\n",
        args.episodes, args.seed
    );
    let _ = writeln!(
        out,
        "| eps coef | eps | falls | forecast f_t | plan length |\n|---|---:|---:|---:|---:|"
    );
    for (coef, r) in reports {
        let _ = writeln!(
            out,
            "| {coef} | {:.4} | {}/{} | {:.2} | {:.2} |",
            r.epsilon,
            r.fallen_seeds.len(),
            r.episodes,
            r.mean_forecast,
            r.mean_plan
        );
    }
    let cell = |nrmse: f64, n: usize| match n {
        0 => "-".to_string(),
        n => format!("{nrmse:.3} ({n})"),
    };
    let _ = writeln!(
        out,
        "\nForecast of step k against the observation that followed, over forecasts held for \
         their first k actions:\n\n{}",
        head("eps coef")
    );
    for (coef, r) in reports {
        let cells: Vec<String> = r.held.iter().map(|e| cell(e.nrmse, e.samples)).collect();
        let _ = writeln!(out, "| {coef} | {} |", cells.join(" | "));
    }
    let _ = writeln!(
        out,
        "\nThe model rolled k steps along the executed actions, from every state:\n\n{}",
        head("eps coef")
    );
    for (coef, r) in reports {
        let cells: Vec<String> = r
            .executed
            .iter()
            .map(|e| cell(e.nrmse, e.samples))
            .collect();
        let _ = writeln!(out, "| {coef} | {} |", cells.join(" | "));
    }
    let _ = writeln!(
        out,
        "\nLargest |predicted observation| at step k, and the share of predicted entries \
         outside the observation bounds [{low}, {high}]:\n\n{}",
        head("eps coef")
    );
    for (coef, r) in reports {
        let cells: Vec<String> = r
            .bounds
            .iter()
            .map(|b| match b.forecasts {
                0 => "-".to_string(),
                _ => format!("{:.3} ({:.2} %)", b.largest, 100.0 * b.outside),
            })
            .collect();
        let _ = writeln!(out, "| {coef} | {} |", cells.join(" | "));
    }
    let baseline: Option<&ForecastReport> = reports
        .iter()
        .find(|(coef, _)| *coef == 0.0)
        .map(|(_, r)| r);
    let _ = writeln!(
        out,
        "\nThe last {} steps before each fall that did not happen at eps 0 (same seed): executed \
         actions that were kept old ones, the oldest one's age, the executed action's Q gap \
         Q(s, pi(s)) - Q(s, a) over eps (kept ones only), Q(s, pi(s)) first and last, and the \
         model's one-step error there against all steps':\n",
        STEPS_BEFORE_FALL
    );
    let _ = writeln!(
        out,
        "| eps coef | seed | length | kept | oldest | mean gap / eps | max gap / eps | value first -> last | 1-step error here / all |\n|---|---:|---:|---:|---:|---:|---:|---|---|"
    );
    for (coef, r) in reports {
        for fall in &r.falls {
            if baseline.is_some_and(|b| b.fallen_seeds.contains(&fall.seed)) {
                continue;
            }
            let kept: Vec<_> = fall.steps.iter().filter(|s| s.kept).collect();
            let gap = |g: f32| f64::from(g) / f64::from(r.epsilon).max(1e-9);
            let mean_gap =
                kept.iter().map(|s| gap(s.q_gap)).sum::<f64>() / kept.len().max(1) as f64;
            let max_gap = kept.iter().map(|s| gap(s.q_gap)).fold(f64::NAN, f64::max);
            let oldest = fall.steps.iter().map(|s| s.age).max().unwrap_or(0);
            let here = fall.steps.iter().map(|s| s.model_error).sum::<f64>()
                / fall.steps.len().max(1) as f64;
            let (first, last) = (
                fall.steps.first().map_or(f32::NAN, |s| s.value),
                fall.steps.last().map_or(f32::NAN, |s| s.value),
            );
            let _ = writeln!(
                out,
                "| {coef} | {} | {} | {}/{} | {oldest} | {mean_gap:.2} | {max_gap:.2} | {first:.1} -> {last:.1} | {here:.3} / {:.3} |",
                fall.seed,
                fall.length,
                kept.len(),
                fall.steps.len(),
                r.held[0].nrmse
            );
        }
    }
    out
}
