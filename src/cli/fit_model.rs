//! `prac fit-model`: (re)trains a bundle's dynamics model from recorded transitions.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use prac::train::fit::{FitOptions, Transitions, fit_model};

#[derive(Args, Debug)]
pub struct FitModelArgs {
    /// The bundle whose model is (re)trained.
    #[arg(long)]
    pub bundle: PathBuf,
    /// safetensors with f32 arrays obs [N, obs_dim], action [N, act_dim] (domain units) and
    /// next_obs [N, obs_dim]; consecutive rows form episodes for the k-step error.
    #[arg(long)]
    pub transitions: PathBuf,
    /// Where to write the bundle [default: replace --bundle].
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Gradient steps.
    #[arg(long, default_value_t = 20_000)]
    pub steps: usize,
    #[arg(long, default_value_t = 256)]
    pub batch_size: usize,
    #[arg(long, default_value_t = 1e-4)]
    pub learning_rate: f64,
    /// Fraction of rows (the last ones) held out for the error report.
    #[arg(long, default_value_t = 0.1)]
    pub holdout: f64,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

impl FitModelArgs {
    pub fn run(self) -> anyhow::Result<()> {
        let args = self;
        anyhow::ensure!(
            args.holdout > 0.0 && args.holdout < 1.0,
            "--holdout must be in (0, 1)"
        );
        anyhow::ensure!(args.batch_size > 0, "--batch-size must be > 0");
        let policy = prac::bundle::load(&args.bundle)?;
        let data = Transitions::load(&args.transitions, policy.obs_dim(), policy.act_dim())?;
        let options = FitOptions {
            steps: args.steps,
            batch_size: args.batch_size,
            learning_rate: args.learning_rate,
            holdout: args.holdout,
            seed: args.seed,
            ..FitOptions::default()
        };
        // The output's folder before the fit, as `prac train` makes its --out's: a fit is minutes.
        let out = args.out.unwrap_or(args.bundle);
        if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
        let (fitted, report) = fit_model(&policy, &data, &options)?;
        prac::bundle::save(&fitted, &out).with_context(|| format!("writing {}", out.display()))?;
        println!("{}", serde_json::to_string_pretty(&report)?);
        Ok(())
    }
}
