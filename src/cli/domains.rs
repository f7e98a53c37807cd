//! `prac domains` (the table of domains), `prac bench-domains` (env speed and random-policy
//! returns) and `prac play-from-states` (a planar walker from PyBullet's states).

use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use std::path::Path;

use anyhow::Context;

use crate::domains::{DOMAINS, Env, EpisodeTotals, Planar, PlanarState, make};
use crate::eval::mean_std;

pub fn table() -> String {
    let mut out = format!(
        "{:<10} {:>7} {:>7} {:>14} {:>8}  {}\n",
        "name", "obs_dim", "act_dim", "episode_steps", "dt", "engine"
    );
    for name in DOMAINS {
        let env = make(name).expect("listed domains exist");
        let s = env.spec();
        out.push_str(&format!(
            "{:<10} {:>7} {:>7} {:>14} {:>8.4}  {}\n",
            s.name, s.obs_dim, s.act_dim, s.episode_len, s.control_period, s.engine
        ));
    }
    out
}

#[derive(serde::Serialize)]
pub struct DomainBench {
    pub name: &'static str,
    pub steps_per_second: f64,
    pub episodes: usize,
    pub mean_return: f64,
    pub std_return: f64,
    pub mean_discounted: f64,
    pub std_discounted: f64,
    pub mean_length: f64,
    pub std_length: f64,
    /// Episodes the task ended (a fall) before the step limit.
    pub terminated: usize,
    /// How far the robot moved forward per episode (`Env::forward_position`), walkers only.
    pub mean_distance: Option<f64>,
    pub std_distance: Option<f64>,
    /// Each reward term's mean per step over all episodes (`Env::reward_terms`).
    pub reward_terms: Vec<(&'static str, f64)>,
}

/// Steps/s under uniform random actions on one thread (for `per_domain`), then the returns of
/// `episodes` random-policy episodes, undiscounted and discounted with `gamma`.
pub fn bench(
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
        let (mut returns, mut discounted, mut lengths) = (Vec::new(), Vec::new(), Vec::new());
        let (mut distances, mut terminated) = (Vec::new(), 0);
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
            returns.push(totals.ret);
            discounted.push(totals.discounted);
            lengths.push(totals.steps as f64);
            terminated += usize::from(totals.terminated);
            distances.extend(crate::domains::forward_distance(start, env.as_ref()));
        }
        let (mean_return, std_return) = mean_std(&returns);
        let (mean_discounted, std_discounted) = mean_std(&discounted);
        let (mean_length, std_length) = mean_std(&lengths);
        let (mean_distance, std_distance) = match distances.is_empty() {
            true => (None, None),
            false => {
                let (m, s) = mean_std(&distances);
                (Some(m), Some(s))
            }
        };
        let steps: f64 = lengths.iter().sum();
        rows.push(DomainBench {
            name: spec.name,
            steps_per_second,
            episodes,
            mean_return,
            std_return,
            mean_discounted,
            std_discounted,
            mean_length,
            std_length,
            terminated,
            mean_distance,
            std_distance,
            reward_terms: term_sums
                .into_iter()
                .map(|(name, sum)| (name, sum / steps))
                .collect(),
        });
    }
    Ok(rows)
}

pub fn report(rows: &[DomainBench], episodes: usize, gamma: f64) -> String {
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

/// What `prac play-from-states` reads: a planar domain and, per case, a state and the actions
/// to play from it.
#[derive(serde::Deserialize)]
struct StateCases {
    domain: String,
    cases: Vec<StateCase>,
}

#[derive(serde::Deserialize)]
struct StateCase {
    state: PlanarState,
    actions: Vec<Vec<f32>>,
}

/// One step played from a matched state.
#[derive(serde::Serialize)]
struct PlayedStep {
    /// The action played (the case's, or the policy's).
    action: Vec<f32>,
    obs: Vec<f32>,
    reward: f64,
    reward_terms: std::collections::BTreeMap<&'static str, f64>,
    terminated: bool,
}

#[derive(serde::Serialize)]
struct PlayedCase {
    /// The observation of the set state, then one row per step played (a case stops where its
    /// episode ends).
    start: Vec<f32>,
    steps: Vec<PlayedStep>,
}

/// A policy that `play-from-states` plays from each state instead of the case's actions.
pub struct ClosedLoop<'a> {
    pub bundle: &'a Path,
    pub steps: usize,
}

/// Plays every case of `input` (see [`StateCases`]), or the bundle's deterministic policy from
/// each case's state when `closed_loop` is given, and writes the observations and reward terms
/// to `out`.
pub fn play_from_states(
    input: &Path,
    out: &Path,
    closed_loop: Option<ClosedLoop>,
) -> anyhow::Result<()> {
    let text =
        std::fs::read_to_string(input).with_context(|| format!("reading {}", input.display()))?;
    let cases: StateCases =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", input.display()))?;
    let mut env = Planar::named(&cases.domain).with_context(|| {
        format!(
            "{} is not a planar walker (hopper, walker, cheetah)",
            cases.domain
        )
    })?;
    let mut policy = match &closed_loop {
        Some(c) => {
            let policy = std::sync::Arc::new(crate::bundle::load(c.bundle)?);
            anyhow::ensure!(
                policy.manifest.domain == cases.domain,
                "the bundle is for {}, the cases for {}",
                policy.manifest.domain,
                cases.domain
            );
            Some(crate::policy::Evaluator::new(policy))
        }
        None => None,
    };
    let spec = env.spec();
    let zeros = vec![0.0; spec.act_dim];
    let mut obs = vec![0.0; spec.obs_dim];
    let mut action = vec![0.0; spec.act_dim];
    let mut played = Vec::with_capacity(cases.cases.len());
    for (k, case) in cases.cases.iter().enumerate() {
        env.set_state(&case.state, &mut obs)
            .with_context(|| format!("case {k}"))?;
        let start = obs.clone();
        let length = closed_loop.as_ref().map_or(case.actions.len(), |c| c.steps);
        let mut steps = Vec::with_capacity(length);
        for i in 0..length {
            match policy.as_mut() {
                Some(p) => crate::plan::Networks::act(p, &obs, &zeros, &mut action),
                None => action.clone_from(&case.actions[i]),
            }
            let t = env
                .step(&action, &mut obs)
                .with_context(|| format!("case {k}, step {}", steps.len()))?;
            steps.push(PlayedStep {
                action: action.clone(),
                obs: obs.clone(),
                reward: t.reward,
                reward_terms: env.reward_terms().iter().copied().collect(),
                terminated: t.terminated,
            });
            if t.terminated || t.truncated {
                break;
            }
        }
        played.push(PlayedCase { start, steps });
    }
    std::fs::write(out, serde_json::to_string(&played)?)
        .with_context(|| format!("writing {}", out.display()))
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
