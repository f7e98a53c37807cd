//! A loaded policy: SB3-style squashed-Gaussian actor, n critics and the dynamics model, with the
//! per-session [`Evaluator`] that runs them for Replan without allocating.

use std::sync::Arc;

use crate::manifest::{Manifest, Normalization, ObsNormalization, QAggregation};
use crate::nn::{Dense, Mlp, MlpScratch, resize};
use crate::plan::{MAX_ROWS_PER_SESSION, Networks, support_distance};

/// SB3 clamps log_std to this range.
pub(crate) const LOG_STD_MIN: f32 = -20.0;
pub(crate) const LOG_STD_MAX: f32 = 2.0;

/// The actor: `latent = trunk(obs)`, `mu = W_mu latent`. A Gaussian actor also has
/// `log_std = W_ls latent` and acts `tanh(mu + exp(log_std) * noise)`; the others (gSDE, TD3,
/// DDPG; `ActorKind`) act `tanh(clip(mu))` whatever the noise.
#[derive(Clone, Debug)]
pub(crate) struct Actor {
    /// SB3's `latent_pi` (ends in an activation).
    pub(crate) trunk: Mlp,
    pub(crate) mu: Dense,
    /// The Gaussian's log-std head; None for actors without one.
    pub(crate) log_std: Option<Dense>,
    /// The clip of the mean before tanh (gSDE's `clip_mean`); infinite where there is none.
    pub(crate) mean_clip: f32,
}

impl Actor {
    /// Whether a sampled action differs from the deterministic one.
    pub(crate) fn samples(&self) -> bool {
        self.log_std.is_some()
    }
}

/// Predicts `s' = s + denormalise(net(normalise(s), normalise(a)))`.
#[derive(Clone, Debug)]
pub struct DynamicsModel {
    pub(crate) net: Mlp,
    pub(crate) normalization: Normalization,
}

#[derive(Clone, Debug)]
pub struct Policy {
    pub manifest: Manifest,
    /// "sha256:<hex>" of the bundle file it came from.
    pub content_hash: String,
    pub(crate) actor: Actor,
    pub(crate) critics: Vec<Mlp>,
    /// None for a bundle without a dynamics model (which cannot imagine plans).
    pub model: Option<DynamicsModel>,
}

impl Policy {
    pub fn obs_dim(&self) -> usize {
        self.manifest.obs_dim
    }
    pub fn act_dim(&self) -> usize {
        self.manifest.act_dim
    }

    /// What each observation and action entry is: the bundle's own, else its domain's where
    /// the domain is one of prac's and its sizes are that domain's (an imported bundle may
    /// reuse a name for other data).
    pub fn features(&self) -> Option<crate::domains::Features> {
        self.manifest.features.clone().or_else(|| {
            crate::domains::features(&self.manifest.domain).filter(|f| {
                f.observation.len() == self.obs_dim() && f.action.len() == self.act_dim()
            })
        })
    }

    /// Maps an action from [-1, 1] to the action bounds.
    pub fn unscale_action(&self, squashed: &[f32], out: &mut [f32]) {
        unscale_action(
            &self.manifest.action_low,
            &self.manifest.action_high,
            squashed,
            out,
        );
    }

    /// Maps an action from the action bounds to [-1, 1].
    pub(crate) fn scale_action(&self, action: &[f32], out: &mut [f32]) {
        let (lo, hi) = (&self.manifest.action_low, &self.manifest.action_high);
        for i in 0..action.len() {
            out[i] = scale_component(lo[i], hi[i], action[i]);
        }
    }

    /// Moves each squashed action of `actions` (entries of act_dim values) to the nearest value
    /// that survives the trip to the action bounds and back: `scale(unscale(s)) == s` in f32. A
    /// client holds its plan in the action bounds; resumed from it, the plan's squashed actions
    /// are then the very ones the uninterrupted session holds. Allocates nothing.
    pub(crate) fn make_actions_round_trip(&self, actions: &mut [f32]) {
        let (lo, hi) = (&self.manifest.action_low, &self.manifest.action_high);
        let act_dim = lo.len();
        for (k, s) in actions.iter_mut().enumerate() {
            let i = k % act_dim;
            *s = round_trip_fixed_point(lo[i], hi[i], *s);
        }
    }

    /// How many critics it has.
    pub fn critic_count(&self) -> usize {
        self.critics.len()
    }

    /// Bytes of every network's weights as held in memory (f32; biases and norms are small).
    pub fn weight_bytes(&self) -> u64 {
        let actor = self.actor.trunk.flops()
            + self.actor.mu.flops()
            + self.actor.log_std.as_ref().map_or(0, |d| d.flops());
        let critics = self.critics.iter().map(Mlp::flops).sum::<u64>();
        let model = self.model.as_ref().map_or(0, |m| m.net.flops());
        // Two FLOPs per weight.
        (actor + critics + model) / 2 * 4
    }

    /// FLOPs of one evaluation of the actor (mean only), of one critic, and of the model.
    pub fn flops(&self) -> (u64, u64, u64) {
        let head = 2 * (self.actor.mu.weight().len()) as u64;
        let critic = self.critics.iter().map(Mlp::flops).sum::<u64>() / self.critics.len() as u64;
        (
            self.actor.trunk.flops() + head,
            critic,
            self.model.as_ref().map_or(0, |m| m.net.flops()),
        )
    }
}

/// Folds critic `k`'s value into the running aggregate (a sum for the mean).
#[inline]
fn aggregate(how: QAggregation, k: usize, acc: f32, value: f32) -> f32 {
    match how {
        _ if k == 0 => value,
        QAggregation::Min => acc.min(value),
        QAggregation::Mean => acc + value,
    }
}

/// Runs a policy's networks for Replan, over batches of any size: owns every buffer a step
/// needs (one per session, or one per batch worker).
#[derive(Clone, Debug)]
pub struct Evaluator {
    policy: Arc<Policy>,
    /// The bundle's observation normalisation, for the actor and critics.
    obs_scale: Option<ObsScale>,
    /// The bundle's observation space (low, high; infinite where unbounded), which every
    /// predicted observation is kept inside.
    obs_limits: Option<(Vec<f32>, Vec<f32>)>,
    /// Normalised observations of the current call.
    normalized: Vec<f32>,
    actor: MlpScratch,
    mu: Vec<f32>,
    log_std: Vec<f32>,
    /// Critic inputs: n rows of (obs, a) then n rows of (obs, b).
    critic_input: Vec<f32>,
    critics: Vec<MlpScratch>,
    model_input: Vec<f32>,
    model: MlpScratch,
    /// FLOPs of one row of the actor, of every critic together, and of the model.
    row_flops: (u64, u64, u64),
    /// FLOPs evaluated since the last [`Evaluator::take_flops`].
    flops: u64,
}

impl Evaluator {
    /// An evaluator for one session: its buffers fit a batch of one from the start.
    pub fn new(policy: Arc<Policy>) -> Evaluator {
        Evaluator::with_capacity(policy, 1)
    }

    /// An evaluator for Replan over up to `sessions` sessions at once: it never grows (Replan
    /// evaluates at most [`MAX_ROWS_PER_SESSION`] states per session in one call).
    pub fn for_sessions(policy: Arc<Policy>, sessions: usize) -> Evaluator {
        Evaluator::with_capacity(policy, sessions * MAX_ROWS_PER_SESSION)
    }

    /// An evaluator whose buffers fit batches of up to `rows` states without growing.
    pub fn with_capacity(policy: Arc<Policy>, rows: usize) -> Evaluator {
        let (od, ad) = (policy.obs_dim(), policy.act_dim());
        Evaluator {
            obs_scale: policy
                .manifest
                .obs_normalization
                .as_ref()
                .map(ObsScale::new),
            obs_limits: policy.manifest.obs_bounds.as_ref().map(|b| b.limits()),
            normalized: Vec::with_capacity(rows * od),
            actor: policy.actor.trunk.scratch_for(rows),
            mu: Vec::with_capacity(rows * ad),
            log_std: Vec::with_capacity(rows * ad),
            critic_input: Vec::with_capacity(2 * rows * (od + ad)),
            critics: policy
                .critics
                .iter()
                .map(|c| c.scratch_for(2 * rows))
                .collect(),
            model_input: Vec::with_capacity(rows * (od + ad)),
            model: policy
                .model
                .as_ref()
                .map_or_else(MlpScratch::default, |m| m.net.scratch_for(rows)),
            row_flops: {
                let (actor, critic, model) = policy.flops();
                (actor, critic * policy.critic_count() as u64, model)
            },
            flops: 0,
            policy,
        }
    }

    /// FLOPs of the network rows evaluated since the last call: what the steps in between
    /// cost, whatever the batch they were evaluated in.
    pub fn take_flops(&mut self) -> u64 {
        std::mem::take(&mut self.flops)
    }
    pub(crate) fn policy(&self) -> &Arc<Policy> {
        &self.policy
    }

    /// The actor over `obs`: `mu` and, for a Gaussian actor, `log_std` hold its rows after.
    /// Says whether the actor is Gaussian.
    fn run_actor(&mut self, obs: &[f32]) -> bool {
        let actor = &self.policy.actor;
        let n = obs.len() / self.policy.obs_dim();
        let ad = self.policy.act_dim();
        self.flops += n as u64 * self.row_flops.0;
        let obs = normalize(&self.obs_scale, obs, &mut self.normalized);
        let latent = actor.trunk.forward_rows(obs, &mut self.actor);
        resize(&mut self.mu, n * ad);
        actor.mu.forward_rows(latent, &mut self.mu);
        let Some(log_std_head) = &actor.log_std else {
            return false;
        };
        resize(&mut self.log_std, n * ad);
        log_std_head.forward_rows(latent, &mut self.log_std);
        true
    }

    /// Per row of the last actor pass, the largest [`support_distance`] of `actions` from its
    /// Gaussian; NaN for an actor without one.
    fn distances(&self, gaussian: bool, actions: &[f32], distance: &mut [f32]) {
        let ad = self.policy.act_dim();
        let n = self.mu.len() / ad;
        if !gaussian {
            distance[..n].fill(f32::NAN);
            return;
        }
        for (k, d) in distance[..n].iter_mut().enumerate() {
            *d = (k * ad..(k + 1) * ad)
                .map(|i| {
                    let std = self.log_std[i].clamp(LOG_STD_MIN, LOG_STD_MAX).exp();
                    support_distance(actions[i], self.mu[i], std)
                })
                .fold(0.0, |m: f32, v| if v > m || v.is_nan() { v } else { m });
        }
    }

    /// The actor's mean (before tanh) over `obs` and, for a Gaussian actor, its log-std clamped
    /// as SB3 clamps it.
    #[cfg(feature = "onnx")]
    pub(crate) fn actor_heads(&mut self, obs: &[f32]) -> (Vec<f32>, Option<Vec<f32>>) {
        let gaussian = self.run_actor(obs);
        let log_std = gaussian.then(|| {
            self.log_std
                .iter()
                .map(|v| v.clamp(LOG_STD_MIN, LOG_STD_MAX))
                .collect()
        });
        (self.mu.clone(), log_std)
    }

    /// Each critic's values of (obs, actions), actions in [-1, 1]: one row of values per critic.
    #[cfg(feature = "onnx")]
    pub(crate) fn each_critic(&mut self, obs: &[f32], actions: &[f32]) -> Vec<Vec<f32>> {
        let (od, ad) = (self.policy.obs_dim(), self.policy.act_dim());
        let obs = normalize(&self.obs_scale, obs, &mut self.normalized);
        self.critic_input.clear();
        for (o, a) in obs.chunks_exact(od).zip(actions.chunks_exact(ad)) {
            self.critic_input.extend_from_slice(o);
            self.critic_input.extend_from_slice(a);
        }
        self.policy
            .critics
            .iter()
            .zip(&mut self.critics)
            .map(|(critic, scratch)| critic.forward_rows(&self.critic_input, scratch).to_vec())
            .collect()
    }

    /// Aggregated critic values of (obs, a) and (obs, b), and where asked the largest gap one
    /// critic sees, `max_c (Q_c(obs, a) - Q_c(obs, b))`.
    fn q_values(
        &mut self,
        obs: &[f32],
        a: &[f32],
        b: &[f32],
        q_a: &mut [f32],
        q_b: &mut [f32],
        mut largest_gap: Option<&mut [f32]>,
    ) {
        let (od, ad) = (self.policy.obs_dim(), self.policy.act_dim());
        let n = obs.len() / od;
        self.flops += 2 * n as u64 * self.row_flops.1;
        let obs = normalize(&self.obs_scale, obs, &mut self.normalized);
        self.critic_input.clear();
        for actions in [a, b] {
            for k in 0..n {
                self.critic_input
                    .extend_from_slice(&obs[k * od..(k + 1) * od]);
                self.critic_input
                    .extend_from_slice(&actions[k * ad..(k + 1) * ad]);
            }
        }
        let how = self.policy.manifest.q_aggregation;
        for (c, (critic, scratch)) in self
            .policy
            .critics
            .iter()
            .zip(&mut self.critics)
            .enumerate()
        {
            let q = critic.forward_rows(&self.critic_input, scratch);
            for k in 0..n {
                q_a[k] = aggregate(how, c, q_a[k], q[k]);
                q_b[k] = aggregate(how, c, q_b[k], q[n + k]);
            }
            if let Some(gap) = largest_gap.as_deref_mut() {
                for k in 0..n {
                    let g = q[k] - q[n + k];
                    gap[k] = if c == 0 || g > gap[k] || g.is_nan() {
                        g
                    } else {
                        gap[k]
                    };
                }
            }
        }
        if how == QAggregation::Mean {
            let count = self.policy.critics.len() as f32;
            q_a.iter_mut()
                .chain(q_b.iter_mut())
                .for_each(|q| *q /= count);
        }
    }
}

impl Networks for Evaluator {
    fn obs_dim(&self) -> usize {
        self.policy.obs_dim()
    }
    fn act_dim(&self) -> usize {
        self.policy.act_dim()
    }

    fn act(&mut self, obs: &[f32], noise: &[f32], actions: &mut [f32]) {
        if self.run_actor(obs) {
            for i in 0..self.mu.len() {
                let std = self.log_std[i].clamp(LOG_STD_MIN, LOG_STD_MAX).exp();
                actions[i] = (self.mu[i] + std * noise[i]).tanh();
            }
        } else {
            let clip = self.policy.actor.mean_clip;
            for (a, mu) in actions.iter_mut().zip(&self.mu) {
                *a = mu.clamp(-clip, clip).tanh();
            }
        }
    }

    fn q_pair(
        &mut self,
        obs: &[f32],
        a: &[f32],
        b: &[f32],
        q_a: &mut [f32],
        q_b: &mut [f32],
        largest_gap: Option<&mut [f32]>,
    ) {
        self.q_values(obs, a, b, q_a, q_b, largest_gap);
    }

    fn policy_distance(&mut self, obs: &[f32], actions: &[f32], distance: &mut [f32]) {
        let gaussian = self.run_actor(obs);
        self.distances(gaussian, actions, distance);
    }

    fn act_and_distance(
        &mut self,
        obs: &[f32],
        noise: &[f32],
        actions: &mut [f32],
        planned: &[f32],
        distance: &mut [f32],
    ) {
        self.act(obs, noise, actions);
        let gaussian = self.policy.actor.log_std.is_some();
        self.distances(gaussian, planned, distance);
    }

    fn predict_next(&mut self, obs: &[f32], actions: &[f32], next_obs: &mut [f32]) {
        // Without a model there is no prediction: NaN makes Replan refuse the plan (NonFinite).
        let Some(model) = &self.policy.model else {
            next_obs.fill(f32::NAN);
            return;
        };
        let (od, ad) = (self.policy.obs_dim(), self.policy.act_dim());
        let n = obs.len() / od;
        self.flops += n as u64 * self.row_flops.2;
        let norm = &model.normalization;
        self.model_input.clear();
        for k in 0..n {
            let (o, a) = (&obs[k * od..(k + 1) * od], &actions[k * ad..(k + 1) * ad]);
            let obs_part = o.iter().zip(&norm.obs_mean).zip(&norm.obs_std);
            self.model_input
                .extend(obs_part.map(|((v, mean), std)| (v - mean) / std));
            let act_part = a.iter().zip(&norm.action_mean).zip(&norm.action_std);
            self.model_input
                .extend(act_part.map(|((v, mean), std)| (v - mean) / std));
        }
        let delta = model.net.forward_rows(&self.model_input, &mut self.model);
        for k in 0..n {
            for i in 0..od {
                let d = delta[k * od + i] * norm.delta_std[i] + norm.delta_mean[i];
                next_obs[k * od + i] = obs[k * od + i] + d;
            }
        }
        if let Some((low, high)) = &self.obs_limits {
            for row in next_obs[..n * od].chunks_exact_mut(od) {
                for ((v, &lo), &hi) in row.iter_mut().zip(low).zip(high) {
                    *v = keep_inside(*v, lo, hi);
                }
            }
        }
    }
}

/// `v` clamped to [lo, hi]; NaN stays NaN (Replan refuses it as a non-finite prediction).
fn keep_inside(v: f32, lo: f32, hi: f32) -> f32 {
    if v < lo {
        lo
    } else if v > hi {
        hi
    } else {
        v
    }
}

/// The observations as the actor and critics see them: `obs` itself, or normalised into `out`.
fn normalize<'a>(scale: &Option<ObsScale>, obs: &'a [f32], out: &'a mut Vec<f32>) -> &'a [f32] {
    let Some(scale) = scale else {
        return obs;
    };
    out.clear();
    scale.extend_normalized(obs, out);
    out
}

/// A bundle's observation normalisation ready to apply: `clip((s - mean) / sqrt(var + eps))`
/// per feature, as SB3's VecNormalize computes it. The server and training share it.
#[derive(Clone, Debug)]
pub(crate) struct ObsScale {
    mean: Vec<f32>,
    inverse_std: Vec<f32>,
    clip: f32,
}

impl ObsScale {
    pub(crate) fn new(normalization: &ObsNormalization) -> ObsScale {
        ObsScale {
            mean: normalization.mean.clone(),
            inverse_std: normalization.inverse_std(),
            clip: normalization.clip_obs,
        }
    }

    /// Appends the normalised rows of `obs` (rows of the normalisation's width) to `out`.
    pub(crate) fn extend_normalized(&self, obs: &[f32], out: &mut Vec<f32>) {
        let clip = self.clip;
        for row in obs.chunks_exact(self.mean.len()) {
            out.extend(
                row.iter()
                    .zip(&self.mean)
                    .zip(&self.inverse_std)
                    .map(|((s, m), k)| ((s - m) * k).clamp(-clip, clip)),
            );
        }
    }
}

/// Maps an action from [-1, 1] to the bounds [low, high] (the policy's or the domain's).
pub fn unscale_action(low: &[f32], high: &[f32], squashed: &[f32], out: &mut [f32]) {
    for i in 0..squashed.len() {
        out[i] = unscale_component(low[i], high[i], squashed[i]);
    }
}

fn unscale_component(low: f32, high: f32, squashed: f32) -> f32 {
    low + 0.5 * (squashed + 1.0) * (high - low)
}

fn scale_component(low: f32, high: f32, action: f32) -> f32 {
    2.0 * (action - low) / (high - low) - 1.0
}

/// The first `s` from `squashed` on with `scale(unscale(s)) == s`. Both maps are monotone in f32
/// (each operation rounds to nearest), so iterating their composition walks one way to a fixed
/// point, in one or two steps in practice.
fn round_trip_fixed_point(low: f32, high: f32, squashed: f32) -> f32 {
    let mut s = squashed;
    for _ in 0..32 {
        let back = scale_component(low, high, unscale_component(low, high, s));
        if back == s || !back.is_finite() {
            return s;
        }
        s = back;
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::Activation;
    use crate::testing::test_manifest;

    #[test]
    fn one_actor_pass_gives_the_actions_and_distances_of_two() {
        let policy = Arc::new(crate::testing::toy_policy("toy", 3));
        assert!(policy.actor.log_std.is_some(), "the toy actor is Gaussian");
        let (od, ad) = (policy.obs_dim(), policy.act_dim());
        let obs: Vec<f32> = (0..5 * od).map(|i| (i as f32 * 0.37).sin()).collect();
        let noise: Vec<f32> = (0..5 * ad).map(|i| (i as f32 * 0.91).cos()).collect();
        let planned: Vec<f32> = (0..5 * ad).map(|i| (i as f32 * 0.53).sin()).collect();
        let mut evaluator = Evaluator::new(policy);
        let (mut actions, mut distance) = (vec![0.0; 5 * ad], vec![0.0; 5]);
        evaluator.act_and_distance(&obs, &noise, &mut actions, &planned, &mut distance);
        let (mut apart, mut apart_distance) = (vec![0.0; 5 * ad], vec![0.0; 5]);
        evaluator.act(&obs, &noise, &mut apart);
        evaluator.policy_distance(&obs, &planned, &mut apart_distance);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&actions), bits(&apart));
        assert_eq!(bits(&distance), bits(&apart_distance));
        assert!(distance.iter().all(|d| d.is_finite() && *d > 0.0));
    }

    #[test]
    fn the_evaluator_counts_the_flops_of_the_rows_it_evaluates() {
        let policy = Arc::new(crate::testing::toy_policy("toy", 1));
        let (actor, critic, model) = policy.flops();
        let critics = policy.critic_count() as u64;
        let (od, ad) = (policy.obs_dim(), policy.act_dim());
        let mut evaluator = Evaluator::new(policy);
        let (obs, actions) = (vec![0.1; 3 * od], vec![0.2; 3 * ad]);
        let mut out = vec![0.0; 3 * od];
        evaluator.act(&obs, &vec![0.0; 3 * ad], &mut out[..3 * ad]);
        evaluator.predict_next(&obs[..2 * od], &actions[..2 * ad], &mut out[..2 * od]);
        let (mut q_a, mut q_b) = (vec![0.0; 3], vec![0.0; 3]);
        evaluator.q_pair(&obs, &actions, &actions, &mut q_a, &mut q_b, None);
        assert_eq!(
            evaluator.take_flops(),
            3 * actor + 2 * model + 2 * 3 * critic * critics
        );
        assert_eq!(evaluator.take_flops(), 0);
    }

    #[test]
    fn round_tripped_actions_come_back_from_the_bounds_unchanged() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let mut moved = 0;
        for (low, high) in [
            (-1.0f32, 1.0f32),
            (-2.0, 2.0),
            (0.3, 5.7),
            (-0.4, 0.4),
            (-3.0, 1.0),
        ] {
            for _ in 0..20_000 {
                // tanh outputs: many tiny, many near the bounds.
                let s: f32 = match rng.random_range(0..3) {
                    0 => rng.random_range(-1.0..=1.0),
                    1 => rng.random_range(-1e-6..1e-6),
                    _ => (rng.random_range(-8.0f32..8.0)).tanh(),
                };
                let fixed = round_trip_fixed_point(low, high, s);
                let action = unscale_component(low, high, fixed);
                assert_eq!(
                    scale_component(low, high, action),
                    fixed,
                    "{s} in [{low}, {high}]"
                );
                assert!(
                    (fixed - s).abs() <= 4e-7 * (1.0 + (high - low)),
                    "{s} -> {fixed}"
                );
                moved += usize::from(fixed != s);
            }
        }
        // The plain trip does move some actions: the fixed point is what makes resuming exact.
        assert!(moved > 0);
    }

    #[test]
    fn batched_and_single_evaluations_agree() {
        let policy = Arc::new(crate::testing::random_policy(
            test_manifest("t", "d", 5, 2, &[16, 16], &[8]),
            3,
        ));
        let mut eval = Evaluator::new(policy.clone());
        let n = 11;
        let obs: Vec<f32> = (0..n * 5).map(|i| (i as f32).sin()).collect();
        let noise: Vec<f32> = (0..n * 2).map(|i| (i as f32 * 0.7).cos()).collect();
        let other: Vec<f32> = (0..n * 2).map(|i| (i as f32 * 0.3).sin()).collect();
        let mut actions = vec![0.0; n * 2];
        eval.act(&obs, &noise, &mut actions);
        let (mut qa, mut qb) = (vec![0.0; n], vec![0.0; n]);
        eval.q_pair(&obs, &actions, &other, &mut qa, &mut qb, None);
        let mut next = vec![0.0; n * 5];
        eval.predict_next(&obs, &actions, &mut next);
        for k in 0..n {
            let (o, z) = (&obs[k * 5..k * 5 + 5], &noise[k * 2..k * 2 + 2]);
            let mut a = [0.0f32; 2];
            eval.act(o, z, &mut a);
            assert_eq!(a, actions[k * 2..k * 2 + 2]);
            let (mut sa, mut sb) = ([0.0f32], [0.0f32]);
            eval.q_pair(o, &a, &other[k * 2..k * 2 + 2], &mut sa, &mut sb, None);
            assert_eq!((sa[0], sb[0]), (qa[k], qb[k]));
            // Q(s, a) at the same action in both slots is bitwise equal (the eps = 0 test).
            eval.q_pair(o, &a, &a, &mut sa, &mut sb, None);
            assert_eq!(sa, sb);
            let mut s_next = [0.0f32; 5];
            eval.predict_next(o, &a, &mut s_next);
            assert_eq!(s_next, next[k * 5..k * 5 + 5]);
        }
    }

    #[test]
    fn the_guards_quantities_are_each_critics_and_the_gaussians() {
        let policy = Arc::new(crate::testing::random_policy(
            test_manifest("t", "d", 5, 2, &[16, 16], &[8]),
            4,
        ));
        assert!(policy.critics.len() >= 2);
        let mut eval = Evaluator::new(policy.clone());
        let n = 7;
        let obs: Vec<f32> = (0..n * 5).map(|i| (i as f32 * 0.9).sin()).collect();
        let a: Vec<f32> = (0..n * 2).map(|i| (i as f32 * 0.4).cos() * 0.9).collect();
        let b: Vec<f32> = (0..n * 2).map(|i| (i as f32 * 0.2).sin()).collect();
        let (mut qa, mut qb, mut gap) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        eval.q_pair(&obs, &a, &b, &mut qa, &mut qb, Some(&mut gap));
        let (mut pa, mut pb) = (vec![0.0; n], vec![0.0; n]);
        eval.q_pair(&obs, &a, &b, &mut pa, &mut pb, None);
        assert_eq!((&qa, &qb), (&pa, &pb));
        let mut distance = vec![0.0; n];
        eval.policy_distance(&obs, &b, &mut distance);
        for k in 0..n {
            let (o, ak, bk) = (&obs[k * 5..][..5], &a[k * 2..][..2], &b[k * 2..][..2]);
            let each = |critic: &Mlp, act: &[f32]| {
                let input: Vec<f32> = o.iter().chain(act).copied().collect();
                critic.forward_rows(&input, &mut critic.scratch_for(1))[0]
            };
            let largest = policy
                .critics
                .iter()
                .map(|c| each(c, ak) - each(c, bk))
                .fold(f32::MIN, f32::max);
            assert_eq!(gap[k], largest, "row {k}");
            // The Gaussian's mean and std at o, from the actor's heads.
            let mut trunk = policy.actor.trunk.scratch_for(1);
            let latent = policy.actor.trunk.forward_rows(o, &mut trunk);
            let (mut mu, mut log_std) = ([0.0f32; 2], [0.0f32; 2]);
            policy.actor.mu.forward_rows(latent, &mut mu);
            policy
                .actor
                .log_std
                .as_ref()
                .unwrap()
                .forward_rows(latent, &mut log_std);
            let expected = (0..2)
                .map(|i| (bk[i].atanh() - mu[i]).abs() / log_std[i].exp())
                .fold(0.0, f32::max);
            assert!(
                (distance[k] - expected).abs() <= 1e-4 * expected.max(1.0),
                "row {k}"
            );
        }
        // The policy's own mean action lies at distance 0.
        let mut own = vec![0.0; n * 2];
        eval.act(&obs, &vec![0.0; n * 2], &mut own);
        eval.policy_distance(&obs, &own, &mut distance);
        assert!(distance.iter().all(|&d| d < 1e-3), "{distance:?}");
    }

    #[test]
    fn action_scaling_round_trips() {
        let mut manifest = test_manifest("t", "d", 3, 2, &[4], &[4]);
        manifest.action_low = vec![-2.0, 0.0];
        manifest.action_high = vec![2.0, 10.0];
        let policy = crate::testing::random_policy(manifest, 0);
        let mut env = [0.0; 2];
        policy.unscale_action(&[-1.0, 0.5], &mut env);
        assert_eq!(env, [-2.0, 7.5]);
        let mut back = [0.0; 2];
        policy.scale_action(&env, &mut back);
        assert_eq!(back, [-1.0, 0.5]);
    }

    #[test]
    fn model_predicts_the_denormalised_delta() {
        let mut manifest = test_manifest("t", "d", 2, 1, &[4], &[]);
        let normalization = &mut manifest.model.as_mut().unwrap().normalization;
        normalization.delta_mean = vec![1.0, -1.0];
        normalization.delta_std = vec![2.0, 2.0];
        normalization.obs_std = vec![0.5, 0.5];
        let mut policy = crate::testing::random_policy(manifest, 0);
        // A linear model (no hidden layers) whose output is its first two inputs.
        policy.model.as_mut().unwrap().net = Mlp::new(
            3,
            vec![Dense::from_row_major(
                2,
                3,
                &[1., 0., 0., 0., 1., 0.],
                &[0., 0.],
            )],
            Activation::Relu,
            false,
        )
        .unwrap();
        let mut eval = Evaluator::new(Arc::new(policy));
        let mut next = [0.0; 2];
        eval.predict_next(&[1.0, 2.0], &[0.3], &mut next);
        // normalised obs = (2, 4); delta = (2, 4) * 2 + (1, -1) = (5, 7); next = obs + delta.
        assert_eq!(next, [6.0, 9.0]);
    }
}
