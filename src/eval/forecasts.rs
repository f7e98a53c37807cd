//! How far served forecasts are from what then happens (`prac model-error`): one session
//! in-process on the bundle's own domain, replanned as `prac serve` replans it, with every step's
//! forecast (the plan's predicted observations) set against the observations that followed.

use std::sync::Arc;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use super::{ModelError, Trajectory, model_errors, normalised_rms, observation_scale};
use crate::domains::{Env, EnvError, EpisodeTotals};
use crate::plan::{Networks, NonFinite, Planner, ReplanConfig};
use crate::policy::{Evaluator, Policy, unscale_action};

/// Forecast steps reported: the action executed now is step 1.
pub const FORECAST_STEPS: [usize; 5] = [1, 5, 10, 20, 32];

/// Steps before a fall that its trace shows.
pub const STEPS_BEFORE_FALL: usize = 30;

/// What the forecasts of one setting came to, over its episodes.
#[derive(Clone, Debug, Serialize)]
pub struct ForecastReport {
    /// The session's absolute eps.
    pub epsilon: f32,
    pub episodes: usize,
    pub steps: usize,
    /// Mean committed forecast f_t of the executed actions.
    pub mean_forecast: f64,
    /// Mean plan length (the forecast the user sees).
    pub mean_plan: f64,
    /// Per step k: the forecast of step k against the observation that followed, over the
    /// forecasts whose first k actions were all executed (the plan was held that long).
    pub held: Vec<ModelError>,
    /// Per step k: the model rolled along the executed actions from every state, held or not
    /// (at eps 0: along the policy's own actions).
    pub executed: Vec<ModelError>,
    /// Per step k: the largest |predicted observation| and the share of predicted entries outside
    /// the domain's observation bounds.
    pub bounds: Vec<BoundsAtStep>,
    /// Seeds of the episodes that ended in a fall (a walker's termination before the step limit).
    pub fallen_seeds: Vec<u64>,
    /// The steps before each fall.
    pub falls: Vec<FallTrace>,
}

#[derive(Clone, Copy, Debug, Serialize)]
pub struct BoundsAtStep {
    pub k: usize,
    pub largest: f32,
    pub outside: f64,
    pub forecasts: usize,
}

/// The last steps of an episode that ended in a fall.
#[derive(Clone, Debug, Serialize)]
pub struct FallTrace {
    pub seed: u64,
    /// The episode's length (the fall came after its last step).
    pub length: usize,
    pub steps: Vec<StepTrace>,
}

/// One executed step, as the critic and the model saw it.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct StepTrace {
    pub step: usize,
    /// The executed action was an old plan's, kept by the test.
    pub kept: bool,
    /// Steps since the executed action was decided (0: decided now).
    pub age: u64,
    /// Q(s, pi(s)) at the real state.
    pub value: f32,
    /// Q(s, pi(s)) - Q(s, a) for the executed action a: the test keeps a while this is <= eps.
    pub q_gap: f32,
    /// Normalised RMS error of this action's predicted observation against the one that came.
    pub model_error: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum ForecastError {
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error(transparent)]
    NonFinite(#[from] NonFinite),
}

/// One episode as played: observations, executed actions (in [-1, 1]) and per step the plan.
struct Played {
    seed: u64,
    observations: Vec<f32>,
    actions: Vec<f32>,
    /// Per step, [`FORECAST_STEPS`]' last entry of predicted observations (NaN past the plan).
    forecasts: Vec<f32>,
    plan_len: Vec<usize>,
    kept: Vec<bool>,
    age: Vec<u64>,
    forecast: Vec<u64>,
    fell: bool,
}

/// Plays `episodes` episodes (seeds `seed..`) of `env` with one session of `config`, and sets
/// every step's forecast against what followed.
pub fn forecast_errors(
    policy: &Arc<Policy>,
    env: &mut dyn Env,
    config: ReplanConfig,
    episodes: usize,
    seed: u64,
) -> Result<ForecastReport, ForecastError> {
    let mut played = Vec::with_capacity(episodes);
    let mut nets = Evaluator::new(policy.clone());
    for k in 0..episodes as u64 {
        played.push(play(&mut nets, env, config, seed + k)?);
    }
    let scale = observation_scale(policy);
    let (low, high) = (&env.spec().obs_low, &env.spec().obs_high);
    let od = env.spec().obs_dim;
    let longest = FORECAST_STEPS[FORECAST_STEPS.len() - 1];
    let (mut held_sum, mut held_count) = (vec![0.0; longest + 1], vec![0usize; longest + 1]);
    let mut largest = vec![0.0f32; longest + 1];
    let (mut outside, mut forecasts) = (vec![0usize; longest + 1], vec![0usize; longest + 1]);
    for p in &played {
        let len = p.kept.len();
        // held_after[t]: how many steps after t kept the plan of step t going.
        let mut held_after = vec![0usize; len];
        for t in (0..len.saturating_sub(1)).rev() {
            held_after[t] = if p.kept[t + 1] {
                held_after[t + 1] + 1
            } else {
                0
            };
        }
        for (t, (&plan_len, &held)) in p.plan_len.iter().zip(&held_after).enumerate() {
            for k in 1..=plan_len.min(longest) {
                let predicted = &p.forecasts[(t * longest + k - 1) * od..][..od];
                largest[k] = predicted.iter().fold(largest[k], |m, v| m.max(v.abs()));
                outside[k] += predicted
                    .iter()
                    .zip(low.iter().zip(high))
                    .filter(|&(&v, (&lo, &hi))| !(lo..=hi).contains(&v))
                    .count();
                forecasts[k] += 1;
                if k <= held + 1 && t + k <= len {
                    let truth = &p.observations[(t + k) * od..][..od];
                    held_sum[k] += normalised_rms(&scale, predicted, truth);
                    held_count[k] += 1;
                }
            }
        }
    }
    let trajectories: Vec<Trajectory<'_>> = played
        .iter()
        .map(|p| Trajectory {
            observations: &p.observations,
            actions: &p.actions,
            exploratory: &[],
        })
        .collect();
    let executed = model_errors(policy, &trajectories, &FORECAST_STEPS);
    let steps: usize = played.iter().map(|p| p.kept.len()).sum();
    let per_step = |v: f64| v / steps.max(1) as f64;
    let mut falls = Vec::new();
    for p in played.iter().filter(|p| p.fell) {
        falls.push(fall_trace(&mut nets, p, &scale, od, longest));
    }
    Ok(ForecastReport {
        epsilon: config.epsilon,
        episodes,
        steps,
        mean_forecast: per_step(played.iter().flat_map(|p| &p.forecast).sum::<u64>() as f64),
        mean_plan: per_step(played.iter().flat_map(|p| &p.plan_len).sum::<usize>() as f64),
        held: FORECAST_STEPS
            .iter()
            .map(|&k| ModelError {
                k,
                nrmse: match held_count[k] {
                    0 => f64::NAN,
                    n => held_sum[k] / n as f64,
                },
                samples: held_count[k],
            })
            .collect(),
        executed,
        bounds: FORECAST_STEPS
            .iter()
            .map(|&k| BoundsAtStep {
                k,
                largest: largest[k],
                outside: outside[k] as f64 / (forecasts[k] * od).max(1) as f64,
                forecasts: forecasts[k],
            })
            .collect(),
        fallen_seeds: played.iter().filter(|p| p.fell).map(|p| p.seed).collect(),
        falls,
    })
}

fn play(
    nets: &mut Evaluator,
    env: &mut dyn Env,
    config: ReplanConfig,
    seed: u64,
) -> Result<Played, ForecastError> {
    let spec = env.spec().clone();
    let (od, ad) = (spec.obs_dim, spec.act_dim);
    let longest = FORECAST_STEPS[FORECAST_STEPS.len() - 1];
    let mut planner = Planner::new(config, od, ad, ChaCha8Rng::seed_from_u64(seed));
    let mut obs = vec![0.0; od];
    env.reset(seed, &mut obs)?;
    // Walkers have a forward position; their termination is a fall.
    let walker = env.forward_position().is_some();
    let mut played = Played {
        seed,
        observations: obs.clone(),
        actions: Vec::new(),
        forecasts: Vec::new(),
        plan_len: Vec::new(),
        kept: Vec::new(),
        age: Vec::new(),
        forecast: Vec::new(),
        fell: false,
    };
    let mut scaled = vec![0.0; ad];
    let mut totals = EpisodeTotals::new(1.0);
    for t in 0u64.. {
        let outcome = planner.replan(nets, &obs, t)?;
        let plan = planner.plan();
        played.kept.push(outcome.kept > 0);
        played.age.push(t - plan.decided_at(0));
        played.forecast.push(planner.forecast(t));
        played.plan_len.push(plan.len());
        for i in 0..longest {
            match i < plan.len() {
                true => played.forecasts.extend_from_slice(plan.next_obs(i)),
                false => played.forecasts.extend(std::iter::repeat_n(f32::NAN, od)),
            }
        }
        played.actions.extend_from_slice(plan.action(0));
        unscale_action(
            &spec.action_low,
            &spec.action_high,
            plan.action(0),
            &mut scaled,
        );
        let transition = env.step(&scaled, &mut obs)?;
        played.observations.extend_from_slice(&obs);
        if totals.record(&transition, 1) {
            played.fell = walker && totals.terminated;
            break;
        }
    }
    Ok(played)
}

/// The critic's view of the steps before a fall: Q(s, pi(s)) and the executed action's gap, at
/// the real states.
fn fall_trace(
    nets: &mut Evaluator,
    p: &Played,
    scale: &[f64],
    od: usize,
    longest: usize,
) -> FallTrace {
    let ad = p.actions.len() / p.kept.len().max(1);
    let len = p.kept.len();
    let first = len.saturating_sub(STEPS_BEFORE_FALL);
    let rows = len - first;
    let states = &p.observations[first * od..len * od];
    let executed = &p.actions[first * ad..len * ad];
    let mut policy_actions = vec![0.0; rows * ad];
    nets.act(states, &vec![0.0; rows * ad], &mut policy_actions);
    let (mut q_policy, mut q_executed) = (vec![0.0; rows], vec![0.0; rows]);
    nets.q_pair(
        states,
        &policy_actions,
        executed,
        &mut q_policy,
        &mut q_executed,
        None,
    );
    let steps = (first..len)
        .enumerate()
        .map(|(r, t)| StepTrace {
            step: t,
            kept: p.kept[t],
            age: p.age[t],
            value: q_policy[r],
            q_gap: q_policy[r] - q_executed[r],
            model_error: normalised_rms(
                scale,
                &p.forecasts[t * longest * od..][..od],
                &p.observations[(t + 1) * od..][..od],
            ),
        })
        .collect();
    FallTrace {
        seed: p.seed,
        length: len,
        steps,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::Growth;
    use crate::testing::{hopper_sized_manifest, random_policy};

    fn report(epsilon: f32) -> ForecastReport {
        let policy = Arc::new(random_policy(hopper_sized_manifest(), 3));
        let mut env = crate::domains::make("hopper").expect("hopper");
        let config = ReplanConfig {
            epsilon,
            growth: Growth::Fixed(32),
            max_horizon: 32,
            sampled: false,
            ..ReplanConfig::default()
        };
        forecast_errors(&policy, env.as_mut(), config, 2, 0).expect("plays")
    }

    #[test]
    fn every_step_executes_its_forecasts_first_action() {
        let r = report(0.0);
        // The first forecast of every step is from the real state with the executed action: the
        // held figure at k = 1 is the model's one-step error along the executed actions.
        assert_eq!(r.held[0].samples, r.steps);
        assert_eq!(r.executed[0].samples, r.steps);
        assert!((r.held[0].nrmse - r.executed[0].nrmse).abs() < 1e-9);
        assert!(r.mean_plan == 32.0 && r.mean_forecast >= 1.0);
        assert!(
            r.bounds
                .iter()
                .all(|b| b.forecasts == r.steps && (0.0..=1.0).contains(&b.outside))
        );
    }

    #[test]
    fn plans_held_whole_are_measured_at_every_step_they_reach() {
        // An eps no Q gap reaches keeps every plan: the forecast of step t is held for as many
        // steps as the episode has left.
        let r = report(1e30);
        let at_5 = r.held.iter().find(|e| e.k == 5).expect("k = 5");
        let episodes_len_sum = r.steps;
        assert_eq!(
            at_5.samples,
            episodes_len_sum - 2 * 4,
            "every start with 5 steps left"
        );
        assert!(r.mean_forecast > 1.0);
        // A random policy falls: each fall is traced over its last steps.
        assert_eq!(r.falls.len(), r.fallen_seeds.len());
        for fall in &r.falls {
            assert_eq!(fall.steps.len(), STEPS_BEFORE_FALL.min(fall.length));
            assert_eq!(fall.steps.last().map(|s| s.step), Some(fall.length - 1));
            assert!(
                fall.steps
                    .iter()
                    .all(|s| s.q_gap.is_finite() && s.model_error.is_finite())
            );
        }
    }
}
