//! `prac evaluate FILE`: a bundle's deterministic policy against uniformly random actions on its
//! domain, the figures the shipped bundles' task criteria (docs/results.md) are judged on.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::Context;
use clap::Args;
use serde::Serialize;

use prac::bundle;
use prac::domains;
use prac::eval::{Episode, Summary, policy_episodes, random_episodes};

#[derive(Args, Debug)]
pub struct EvaluateArgs {
    file: PathBuf,
    #[arg(long, default_value_t = 50)]
    episodes: usize,
    /// First episode's seed (the training runs evaluate from 2^41).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Print the evaluation as JSON.
    #[arg(long)]
    json: bool,
    /// Also write the evaluation as JSON to this file.
    #[arg(long)]
    json_out: Option<PathBuf>,
}

impl EvaluateArgs {
    pub fn run(self) -> anyhow::Result<()> {
        let e = evaluate(&self.file, self.episodes, self.seed)?;
        if let Some(path) = &self.json_out {
            std::fs::write(path, serde_json::to_string_pretty(&e)? + "\n")
                .with_context(|| format!("writing {}", path.display()))?;
        }
        let text = if self.json {
            serde_json::to_string_pretty(&e)? + "\n"
        } else {
            report(&e)
        };
        print!("{text}");
        Ok(())
    }
}

/// Episodes `seed`, `seed + 1`, ... of one way of acting.
#[derive(Debug, Serialize)]
pub struct Played {
    pub return_mean: f64,
    pub return_std: f64,
    pub discounted_mean: f64,
    /// Episodes the task ended early (a walker fell, the lander touched down or crashed).
    pub terminated: usize,
    pub steps_mean: f64,
    /// Forward distance in metres, for the walkers.
    pub distance_mean: Option<f64>,
}

#[derive(Debug, Serialize)]
pub struct Evaluation {
    pub bundle: String,
    pub domain: String,
    pub episodes: usize,
    pub seed: u64,
    pub policy: Played,
    pub random: Played,
}

fn summarise(episodes: &[Episode]) -> Played {
    let s = Summary::of_episodes(episodes);
    Played {
        return_mean: s.return_mean,
        return_std: s.return_std,
        discounted_mean: s.discounted_mean,
        terminated: s.terminated,
        steps_mean: s.steps_mean,
        distance_mean: s.distance_mean,
    }
}

/// Plays `episodes` episodes of the bundle's deterministic policy and as many of random actions,
/// from the same start seeds.
fn evaluate(path: &Path, episodes: usize, seed: u64) -> anyhow::Result<Evaluation> {
    anyhow::ensure!(episodes > 0, "--episodes must be at least 1");
    let policy = Arc::new(bundle::load(path)?);
    let domain = policy.manifest.domain.clone();
    let mut env = domains::make(&domain).ok_or_else(|| {
        anyhow::anyhow!("the bundle is for domain {domain:?}, which this build does not have")
    })?;
    let played = policy_episodes(&policy, env.as_mut(), episodes, seed)?;
    let randoms = random_episodes(env.as_mut(), policy.manifest.gamma, episodes, seed)?;
    Ok(Evaluation {
        bundle: path.display().to_string(),
        domain,
        episodes,
        seed,
        policy: summarise(&played),
        random: summarise(&randoms),
    })
}

/// The evaluation as a few lines of text.
fn report(e: &Evaluation) -> String {
    let line = |name: &str, p: &Played| {
        let distance = p
            .distance_mean
            .map(|d| format!(", {d:.2} m forward"))
            .unwrap_or_default();
        format!(
            "{name:<7} return {:.1} +- {:.1}, discounted {:.2}, {} of {} ended early, {:.0} steps{distance}\n",
            p.return_mean, p.return_std, p.discounted_mean, p.terminated, e.episodes, p.steps_mean
        )
    };
    format!(
        "{} ({}), {} episodes from seed {}\n{}{}",
        e.bundle,
        e.domain,
        e.episodes,
        e.seed,
        line("policy", &e.policy),
        line("random", &e.random)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evaluating_no_episodes_or_a_missing_bundle_is_an_error() {
        let missing = Path::new("/nonexistent/hopper.safetensors");
        assert!(
            evaluate(missing, 0, 0)
                .unwrap_err()
                .to_string()
                .contains("--episodes")
        );
        assert!(evaluate(missing, 1, 0).is_err());
    }
}
