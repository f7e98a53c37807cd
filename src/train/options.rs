//! What a training run is asked to do ([`TrainOptions`], each default declared once) and how far
//! it got ([`Progress`]): the data both the run and its checkpoints hold.

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::sac::{SacConfig, SacLosses};
use crate::plan;

/// Checkpoints written before the option existed had no buffer; runs save it by default.
fn saves_replay() -> bool {
    true
}

/// Everything `prac train` takes.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TrainOptions {
    pub(crate) domain: String,
    pub steps: u64,
    pub seed: u64,
    /// > 0: act from the PrAC plan with eps = coef * (V_pi - V_rand).
    pub epsilon_coef: f64,
    pub max_horizon: usize,
    /// Fixed (V_pi, V_rand) for eps while training; otherwise V_rand is measured before training
    /// and V_pi is the critic's value of the current policy at each episode's first state.
    pub value_scale: Option<(f64, f64)>,
    pub sac: SacConfig,
    pub(crate) out: PathBuf,
    pub csv: PathBuf,
    pub eval_csv: PathBuf,
    pub checkpoint_dir: PathBuf,
    pub checkpoint_every: Duration,
    /// Checkpoints hold the replay buffer, so a resumed run learns on from the same data.
    #[serde(default = "saves_replay")]
    pub checkpoint_replay: bool,
    pub eval_every: u64,
    pub eval_episodes: usize,
    /// Episodes for V_pi and V_rand at the end.
    pub value_episodes: usize,
    pub progress: bool,
}

impl TrainOptions {
    pub const DEFAULT_STEPS: u64 = 100_000;
    pub const DEFAULT_CHECKPOINT_EVERY: Duration = Duration::from_secs(120);
    pub const DEFAULT_EVAL_EVERY: u64 = 10_000;
    pub const DEFAULT_EVAL_EPISODES: usize = 5;
    pub const DEFAULT_VALUE_EPISODES: usize = 50;

    /// Defaults for a domain, writing `out` and files beside it.
    pub fn new(domain: &str, out: &Path) -> TrainOptions {
        let stem = out.with_extension("");
        let beside = |suffix: &str| PathBuf::from(format!("{}{suffix}", stem.display()));
        TrainOptions {
            domain: domain.to_string(),
            steps: Self::DEFAULT_STEPS,
            seed: 0,
            epsilon_coef: 0.0,
            max_horizon: plan::DEFAULT_MAX_HORIZON,
            value_scale: None,
            sac: SacConfig::for_domain(domain),
            out: out.to_path_buf(),
            csv: beside(".train.csv"),
            eval_csv: beside(".eval.csv"),
            checkpoint_dir: beside(".ckpt"),
            checkpoint_every: Self::DEFAULT_CHECKPOINT_EVERY,
            checkpoint_replay: true,
            eval_every: Self::DEFAULT_EVAL_EVERY,
            eval_episodes: Self::DEFAULT_EVAL_EPISODES,
            value_episodes: Self::DEFAULT_VALUE_EPISODES,
            progress: true,
        }
    }

    /// Refuses settings no run can use; `Trainer::new` calls it, so the library refuses what
    /// the command line refuses.
    pub(crate) fn validate(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            self.epsilon_coef.is_finite() && self.epsilon_coef >= 0.0,
            "--epsilon-coef must be >= 0, got {}",
            self.epsilon_coef
        );
        if let Some((v_pi, v_rand)) = self.value_scale {
            anyhow::ensure!(
                v_pi > v_rand,
                "--value-scale takes V_PI,V_RAND with V_PI > V_RAND, got {v_pi},{v_rand}"
            );
        }
        anyhow::ensure!(self.max_horizon >= 1, "--max-horizon must be >= 1");
        anyhow::ensure!(self.eval_every > 0, "--eval-every must be > 0");
        anyhow::ensure!(self.eval_episodes > 0, "--eval-episodes must be > 0");
        anyhow::ensure!(self.value_episodes > 0, "--value-episodes must be > 0");
        self.sac.validate()
    }
}

/// Counters and recent history: what a checkpoint stores besides the networks.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Progress {
    pub step: u64,
    pub episode: u64,
    pub(crate) gradient_steps: u64,
    /// Transitions in the buffer since this process started: those it collected plus those
    /// restored from the checkpoint. Learning waits until they cover the warm-up.
    #[serde(skip)]
    pub(crate) fresh_steps: u64,
    pub(crate) v_rand: Option<f64>,
    pub(crate) recent_returns: Vec<f64>,
    pub(crate) recent_forecasts: Vec<f64>,
    pub(crate) last_losses: SacLosses,
    pub(crate) last_model_loss: f32,
    pub(crate) seconds: f64,
}
