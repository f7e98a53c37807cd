//! Rollouts for evaluation: episode returns (plain and discounted), the value scale
//! (V_pi and V_rand at the start state) and the dynamics model's prediction error.

pub mod forecasts;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::bundle::ValueScale;
use crate::domains::{Env, EnvError, EpisodeTotals, forward_distance};
use crate::plan::Networks;
use crate::policy::{Evaluator, Policy, unscale_action};

/// One finished episode: its returns and the visited states and actions (actions in [-1, 1]).
#[derive(Clone, Debug, Default)]
pub struct Episode {
    pub ret: f64,
    pub(crate) discounted: f64,
    pub len: usize,
    /// It ended by the task's termination (a walker fell, the lander landed or crashed), not by
    /// the step limit.
    pub terminated: bool,
    /// How far the robot moved forward (`Env::forward_position`), metres.
    pub distance: Option<f64>,
    /// len + 1 observations.
    pub(crate) observations: Vec<f32>,
    pub(crate) actions: Vec<f32>,
}

impl Episode {
    pub(crate) fn outcome(&self) -> Outcome {
        Outcome {
            ret: self.ret,
            discounted: self.discounted,
            steps: self.len as f64,
            terminated: self.terminated,
            distance: self.distance,
        }
    }
}

/// What one episode came to, whoever played it (a rollout here, a robot driven by the server
/// in prac-sim, random actions in `prac bench-domains`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Outcome {
    pub ret: f64,
    pub discounted: f64,
    pub steps: f64,
    /// Ended by the task (a fall, a landing), not the step limit.
    pub terminated: bool,
    /// Metres forward, for the domains that have a forward direction.
    pub distance: Option<f64>,
}

/// What a set of episodes came to: the figures every report of episodes gives (`prac
/// evaluate`, training's evaluations and final report, `prac bench-domains`, prac-sim).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Summary {
    pub episodes: usize,
    pub return_mean: f64,
    pub return_std: f64,
    pub discounted_mean: f64,
    pub discounted_std: f64,
    pub steps_mean: f64,
    pub steps_std: f64,
    /// Episodes the task ended early (a walker's falls).
    pub terminated: usize,
    /// Mean and population standard deviation of the forward distance; None unless every
    /// episode has one.
    pub distance_mean: Option<f64>,
    pub distance_std: Option<f64>,
}

impl Summary {
    /// Means and population standard deviations, in the episodes' order.
    pub fn of(outcomes: impl IntoIterator<Item = Outcome>) -> Summary {
        let outcomes: Vec<Outcome> = outcomes.into_iter().collect();
        let of = |f: fn(&Outcome) -> f64| mean_std(&outcomes.iter().map(f).collect::<Vec<_>>());
        let (return_mean, return_std) = of(|o| o.ret);
        let (discounted_mean, discounted_std) = of(|o| o.discounted);
        let (steps_mean, steps_std) = of(|o| o.steps);
        let distances: Option<Vec<f64>> = outcomes.iter().map(|o| o.distance).collect();
        let distance = distances.map(|d| mean_std(&d));
        Summary {
            episodes: outcomes.len(),
            return_mean,
            return_std,
            discounted_mean,
            discounted_std,
            steps_mean,
            steps_std,
            terminated: outcomes.iter().filter(|o| o.terminated).count(),
            distance_mean: distance.map(|d| d.0),
            distance_std: distance.map(|d| d.1),
        }
    }

    /// Of rollouts played here.
    pub fn of_episodes(episodes: &[Episode]) -> Summary {
        Summary::of(episodes.iter().map(Episode::outcome))
    }
}

/// Plays one episode from `seed`; `act(obs, action)` writes an action in [-1, 1], which is
/// scaled to the domain's bounds.
pub(crate) fn run_episode(
    env: &mut dyn Env,
    seed: u64,
    gamma: f64,
    act: &mut dyn FnMut(&[f32], &mut [f32]),
) -> Result<Episode, EnvError> {
    let spec = env.spec().clone();
    let (od, ad) = (spec.obs_dim, spec.act_dim);
    let mut obs = vec![0.0; od];
    env.reset(seed, &mut obs)?;
    let start = env.forward_position();
    let mut episode = Episode {
        observations: obs.clone(),
        ..Episode::default()
    };
    let mut action = vec![0.0; ad];
    let mut scaled = vec![0.0; ad];
    let mut totals = EpisodeTotals::new(gamma);
    loop {
        act(&obs, &mut action);
        unscale_action(&spec.action_low, &spec.action_high, &action, &mut scaled);
        let transition = env.step(&scaled, &mut obs)?;
        episode.actions.extend_from_slice(&action);
        episode.observations.extend_from_slice(&obs);
        if totals.record(&transition, 1) {
            episode.ret = totals.ret;
            episode.discounted = totals.discounted;
            episode.len = totals.steps as usize;
            episode.terminated = totals.terminated;
            episode.distance = forward_distance(start, env);
            return Ok(episode);
        }
    }
}

/// Mean and population standard deviation.
pub fn mean_std(values: &[f64]) -> (f64, f64) {
    if values.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    (mean, var.sqrt())
}

/// Episodes of the deterministic policy `tanh(mu)`, seeds `seed..seed + episodes`.
pub fn policy_episodes(
    policy: &std::sync::Arc<Policy>,
    env: &mut dyn Env,
    episodes: usize,
    seed: u64,
) -> Result<Vec<Episode>, EnvError> {
    let mut evaluator = Evaluator::new(policy.clone());
    let zeros = vec![0.0; policy.act_dim()];
    let gamma = policy.manifest.gamma;
    (0..episodes as u64)
        .map(|k| {
            run_episode(env, seed + k, gamma, &mut |obs, action| {
                evaluator.act(obs, &zeros, action)
            })
        })
        .collect()
}

/// Episodes of uniformly random actions.
pub fn random_episodes(
    env: &mut dyn Env,
    gamma: f64,
    episodes: usize,
    seed: u64,
) -> Result<Vec<Episode>, EnvError> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_0fa1);
    (0..episodes as u64)
        .map(|k| {
            run_episode(env, seed + k, gamma, &mut |_, action| {
                action
                    .iter_mut()
                    .for_each(|a| *a = rng.random_range(-1.0..=1.0))
            })
        })
        .collect()
}

/// V_pi(s0) (deterministic policy) and V_rand(s0) (uniform random actions): mean discounted
/// returns over `episodes` episodes each, with the bundle's gamma.
pub fn value_scale(
    policy: &std::sync::Arc<Policy>,
    env: &mut dyn Env,
    episodes: usize,
    seed: u64,
) -> Result<ValueScale, EnvError> {
    let discounted =
        |eps: &[Episode]| mean_std(&eps.iter().map(|e| e.discounted).collect::<Vec<_>>()).0;
    let v_pi = discounted(&policy_episodes(policy, env, episodes, seed)?);
    let v_rand = discounted(&random_episodes(
        env,
        policy.manifest.gamma,
        episodes,
        seed,
    )?);
    Ok(ValueScale { v_pi, v_rand })
}

/// The model's error `k` steps ahead, rolling its own predictions forward under the recorded
/// actions: RMS over features of the error in units of each feature's standard deviation (the
/// model's normalisation), averaged over every start state with k steps left in its episode.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct ModelError {
    pub k: usize,
    pub nrmse: f64,
    pub samples: usize,
}

/// One chain of consecutive transitions: len + 1 observations and len actions.
pub struct Trajectory<'a> {
    pub observations: &'a [f32],
    pub actions: &'a [f32],
    /// Per action, whether it was exploratory (random or noisy, not the policy's own); empty
    /// where that was not recorded.
    pub exploratory: &'a [bool],
}

/// The model's k-step errors over every window of the trajectories.
pub fn model_errors(
    policy: &std::sync::Arc<Policy>,
    trajectories: &[Trajectory<'_>],
    ks: &[usize],
) -> Vec<ModelError> {
    grouped_model_errors(policy, trajectories, ks, 1, |_, _| 0).remove(0)
}

/// The k-step errors of windows whose actions were all the policy's own, and of windows with an
/// exploratory action.
pub fn model_errors_by_action(
    policy: &std::sync::Arc<Policy>,
    trajectories: &[Trajectory<'_>],
    ks: &[usize],
) -> (Vec<ModelError>, Vec<ModelError>) {
    let mut groups = grouped_model_errors(policy, trajectories, ks, 2, |traj, window| {
        usize::from(
            traj.exploratory
                .get(window)
                .is_some_and(|w| w.contains(&true)),
        )
    });
    let exploratory = groups.remove(1);
    (groups.remove(0), exploratory)
}

/// Each observation's scale for model errors: the model's observation standard deviations (1
/// without a model).
pub(crate) fn observation_scale(policy: &Policy) -> Vec<f64> {
    match &policy.model {
        Some(model) => model
            .normalization
            .obs_std
            .iter()
            .map(|&s| f64::from(s).max(1e-6))
            .collect(),
        None => vec![1.0; policy.obs_dim()],
    }
}

/// RMS over the entries of (predicted - truth) / scale.
pub(crate) fn normalised_rms(scale: &[f64], predicted: &[f32], truth: &[f32]) -> f64 {
    let sq: f64 = predicted
        .iter()
        .zip(truth)
        .zip(scale)
        .map(|((p, t), s)| ((f64::from(*p) - f64::from(*t)) / s).powi(2))
        .sum();
    (sq / predicted.len().max(1) as f64).sqrt()
}

/// Normalised RMS errors of k-step rollouts from every start, averaged per group of windows
/// (`group` of a trajectory and the window's action rows).
fn grouped_model_errors(
    policy: &std::sync::Arc<Policy>,
    trajectories: &[Trajectory<'_>],
    ks: &[usize],
    groups: usize,
    group: impl Fn(&Trajectory<'_>, std::ops::Range<usize>) -> usize,
) -> Vec<Vec<ModelError>> {
    let (od, ad) = (policy.obs_dim(), policy.act_dim());
    if policy.model.is_none() {
        return vec![Vec::new(); groups];
    }
    let scale = observation_scale(policy);
    let mut evaluator = Evaluator::new(policy.clone());
    let kmax = ks.iter().copied().max().unwrap_or(0);
    let mut sums = vec![vec![0.0f64; kmax + 1]; groups];
    let mut counts = vec![vec![0usize; kmax + 1]; groups];
    let mut state = vec![0.0; od];
    let mut next = vec![0.0; od];
    for traj in trajectories {
        let len = traj.actions.len() / ad;
        for start in 0..len {
            state.copy_from_slice(&traj.observations[start * od..(start + 1) * od]);
            for k in 1..=kmax.min(len - start) {
                let t = start + k - 1;
                evaluator.predict_next(&state, &traj.actions[t * ad..(t + 1) * ad], &mut next);
                state.copy_from_slice(&next);
                let truth = &traj.observations[(t + 1) * od..(t + 2) * od];
                let g = group(traj, start..start + k);
                sums[g][k] += normalised_rms(&scale, &state, truth);
                counts[g][k] += 1;
            }
        }
    }
    (0..groups)
        .map(|g| {
            ks.iter()
                .map(|&k| ModelError {
                    k,
                    // No window of that length: no error (null in JSON), not a perfect one.
                    nrmse: if counts[g][k] == 0 {
                        f64::NAN
                    } else {
                        sums[g][k] / counts[g][k] as f64
                    },
                    samples: counts[g][k],
                })
                .collect()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::{Outcome, Summary};

    fn outcome(ret: f64, terminated: bool, distance: Option<f64>) -> Outcome {
        Outcome {
            ret,
            discounted: ret / 2.0,
            steps: if terminated { 10.0 } else { 30.0 },
            terminated,
            distance,
        }
    }

    #[test]
    fn a_summary_gives_means_population_deviations_falls_and_distances() {
        let s = Summary::of([
            outcome(1.0, true, Some(2.0)),
            outcome(3.0, false, Some(4.0)),
        ]);
        assert_eq!(s.episodes, 2);
        assert_eq!((s.return_mean, s.return_std), (2.0, 1.0));
        assert_eq!((s.discounted_mean, s.discounted_std), (1.0, 0.5));
        assert_eq!((s.steps_mean, s.steps_std), (20.0, 10.0));
        assert_eq!(s.terminated, 1);
        assert_eq!((s.distance_mean, s.distance_std), (Some(3.0), Some(1.0)));
        // One episode without a distance: no distance figure at all.
        let partial = Summary::of([outcome(1.0, false, Some(2.0)), outcome(1.0, false, None)]);
        assert_eq!((partial.distance_mean, partial.distance_std), (None, None));
    }
}
