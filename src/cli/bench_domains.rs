//! `prac bench-domains`: env steps/s under random actions and random-policy returns.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Args;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use prac::domains::{DOMAINS, EpisodeTotals, make};
use prac::eval::{Outcome, Summary};

#[derive(Args, Debug)]
pub struct BenchDomainsArgs {
    /// Seconds of stepping per domain.
    #[arg(long, default_value_t = 2.0)]
    seconds: f64,
    /// Random-policy episodes per domain.
    #[arg(long, default_value_t = 100)]
    episodes: usize,
    /// Discount of the discounted returns.
    #[arg(long, default_value_t = 0.98)]
    gamma: f64,
    /// Domains to measure [default: all].
    #[arg(long, value_delimiter = ',')]
    domains: Vec<String>,
    /// Also write every row as JSON (episode lengths, falls, forward distance, reward terms
    /// per step) to this file, as scripts/conformance reads it.
    #[arg(long)]
    json: Option<PathBuf>,
}

impl BenchDomainsArgs {
    pub fn run(self) -> anyhow::Result<()> {
        let names: Vec<&str> = if self.domains.is_empty() {
            DOMAINS.to_vec()
        } else {
            self.domains.iter().map(String::as_str).collect()
        };
        let episodes = self.episodes.max(1);
        let rows = bench(
            &names,
            Duration::from_secs_f64(self.seconds),
            episodes,
            self.gamma,
        )?;
        print!("{}", report(&rows, episodes, self.gamma));
        match self.json {
            Some(path) => std::fs::write(&path, serde_json::to_string_pretty(&rows)?)
                .with_context(|| format!("writing {}", path.display())),
            None => Ok(()),
        }
    }
}

#[derive(serde::Serialize)]
struct DomainBench {
    name: &'static str,
    steps_per_second: f64,
    episodes: usize,
    mean_return: f64,
    std_return: f64,
    mean_discounted: f64,
    std_discounted: f64,
    mean_length: f64,
    std_length: f64,
    /// Episodes the task ended (a fall) before the step limit.
    terminated: usize,
    /// How far the robot moved forward per episode (`Env::forward_position`), walkers only.
    mean_distance: Option<f64>,
    std_distance: Option<f64>,
    /// Each reward term's mean per step over all episodes (`Env::reward_terms`).
    reward_terms: Vec<(&'static str, f64)>,
}

/// Steps/s under uniform random actions on one thread (for `per_domain`), then the returns of
/// `episodes` random-policy episodes, undiscounted and discounted with `gamma`.
fn bench(
    names: &[&str],
    per_domain: Duration,
    episodes: usize,
    gamma: f64,
) -> anyhow::Result<Vec<DomainBench>> {
    let mut rows = Vec::new();
    for name in names {
        let mut env = make(name).ok_or_else(|| anyhow::anyhow!("unknown domain '{name}'"))?;
        let spec = env.spec().clone();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut obs = vec![0.0; spec.obs_dim];
        let mut action = vec![0.0; spec.act_dim];
        let random = |rng: &mut ChaCha8Rng, action: &mut [f32]| {
            for (i, a) in action.iter_mut().enumerate() {
                *a = rng.random_range(spec.action_low[i]..=spec.action_high[i]);
            }
        };
        env.reset(0, &mut obs)?;
        let start = Instant::now();
        let mut steps = 0u64;
        let mut episode = 0;
        while start.elapsed() < per_domain {
            for _ in 0..256 {
                random(&mut rng, &mut action);
                let t = env.step(&action, &mut obs)?;
                steps += 1;
                if t.terminated || t.truncated {
                    episode += 1;
                    env.reset(episode, &mut obs)?;
                }
            }
        }
        let steps_per_second = steps as f64 / start.elapsed().as_secs_f64();
        let mut outcomes = Vec::with_capacity(episodes);
        let mut term_sums: Vec<(&'static str, f64)> = Vec::new();
        // Actions of their own: how many the timed loop drew depends on the machine's speed.
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for e in 0..episodes {
            env.reset(1_000_000 + e as u64, &mut obs)?;
            let start = env.forward_position();
            let mut totals = EpisodeTotals::new(gamma);
            loop {
                random(&mut rng, &mut action);
                let transition = env.step(&action, &mut obs)?;
                for (k, &(name, value)) in env.reward_terms().iter().enumerate() {
                    match term_sums.get_mut(k) {
                        Some(sum) => sum.1 += value,
                        None => term_sums.push((name, value)),
                    }
                }
                if totals.record(&transition, 1) {
                    break;
                }
            }
            outcomes.push(Outcome {
                ret: totals.ret,
                discounted: totals.discounted,
                steps: totals.steps as f64,
                terminated: totals.terminated,
                distance: prac::domains::forward_distance(start, env.as_ref()),
            });
        }
        let steps: f64 = outcomes.iter().map(|o| o.steps).sum();
        let summary = Summary::of(outcomes);
        rows.push(DomainBench {
            name: spec.name,
            steps_per_second,
            episodes,
            mean_return: summary.return_mean,
            std_return: summary.return_std,
            mean_discounted: summary.discounted_mean,
            std_discounted: summary.discounted_std,
            mean_length: summary.steps_mean,
            std_length: summary.steps_std,
            terminated: summary.terminated,
            mean_distance: summary.distance_mean,
            std_distance: summary.distance_std,
            reward_terms: term_sums
                .into_iter()
                .map(|(name, sum)| (name, sum / steps))
                .collect(),
        });
    }
    Ok(rows)
}

fn report(rows: &[DomainBench], episodes: usize, gamma: f64) -> String {
    let mut out = format!(
        "one thread, uniform random actions; returns over {episodes} episodes (discount {gamma})\n\
         {:<10} {:>10} {:>20} {:>22}\n",
        "domain", "steps/s", "return mean (std)", "discounted mean (std)"
    );
    for r in rows {
        out.push_str(&format!(
            "{:<10} {:>10.0} {:>12.1} ({:>6.1}) {:>14.2} ({:>6.2})\n",
            r.name,
            r.steps_per_second,
            r.mean_return,
            r.std_return,
            r.mean_discounted,
            r.std_discounted
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_episodes_do_not_depend_on_how_long_the_speed_was_timed() {
        let short = bench(&["hopper"], Duration::ZERO, 3, 0.99).unwrap();
        let long = bench(&["hopper"], Duration::from_millis(30), 3, 0.99).unwrap();
        assert_eq!(short[0].mean_return, long[0].mean_return);
        assert_eq!(short[0].mean_length, long[0].mean_length);
    }
}
