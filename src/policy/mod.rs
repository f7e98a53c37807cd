//! A loaded policy: SB3-style squashed-Gaussian actor, n critics and the dynamics model, with the
//! per-session [`Evaluator`] that runs them for Replan without allocating.

use std::sync::Arc;

use nalgebra::{DMatrix, DVector, DVectorView};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::bundle::{Manifest, Normalization, QAggregation};
use crate::nn::{Activation, BatchScratch, Dense, Mlp, MlpScratch};
use crate::plan::Networks;

/// SB3 clamps log_std to this range.
pub const LOG_STD_MIN: f32 = -20.0;
pub const LOG_STD_MAX: f32 = 2.0;

/// Squashed-Gaussian actor: `latent = trunk(obs)`, `mu = W_mu latent`, `log_std = W_ls latent`,
/// action `tanh(mu + exp(log_std) * noise)`.
#[derive(Clone, Debug)]
pub struct Actor {
    /// SB3's `latent_pi` (ends in an activation).
    pub trunk: Mlp,
    pub mu: Dense,
    pub log_std: Dense,
}

/// Predicts `s' = s + denormalise(net(normalise(s), normalise(a)))`.
#[derive(Clone, Debug)]
pub struct DynamicsModel {
    pub net: Mlp,
    pub normalization: Normalization,
}

#[derive(Clone, Debug)]
pub struct Policy {
    pub manifest: Manifest,
    /// "sha256:<hex>" of the bundle file it came from.
    pub content_hash: String,
    pub actor: Actor,
    pub critics: Vec<Mlp>,
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

    /// A policy with PyTorch-default random weights (U(+-1/sqrt(fan_in))) for the manifest's
    /// architecture: for benchmarks and tests.
    pub fn random(manifest: Manifest, seed: u64) -> Policy {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (obs, act) = (manifest.obs_dim, manifest.act_dim);
        let mut dense = |out: usize, inp: usize| {
            let bound = 1.0 / (inp as f32).sqrt();
            let w: Vec<f32> = (0..out * inp)
                .map(|_| rng.random_range(-bound..bound))
                .collect();
            let b: Vec<f32> = (0..out).map(|_| rng.random_range(-bound..bound)).collect();
            Dense::from_row_major(out, inp, &w, &b)
        };
        let mut chain = |inp: usize, hidden: &[usize], out: Option<usize>| {
            let mut layers = Vec::new();
            let mut width = inp;
            for &h in hidden.iter().chain(out.as_ref()) {
                layers.push(dense(h, width));
                width = h;
            }
            layers
        };
        let spec = &manifest.actor;
        let trunk = Mlp::new(obs, chain(obs, &spec.hidden, None), spec.activation, true)
            .expect("consistent shapes");
        let latent = trunk.output_dim();
        let critics = (0..manifest.critic.n_critics)
            .map(|_| {
                Mlp::new(
                    obs + act,
                    chain(obs + act, &manifest.critic.hidden, Some(1)),
                    manifest.critic.activation,
                    false,
                )
                .expect("consistent shapes")
            })
            .collect();
        let model = manifest.model.as_ref().map(|spec| DynamicsModel {
            net: Mlp::new(
                obs + act,
                chain(obs + act, &spec.hidden, Some(obs)),
                spec.activation,
                false,
            )
            .expect("consistent shapes"),
            normalization: spec.normalization.clone(),
        });
        let mu = chain(latent, &[], Some(act)).remove(0);
        let log_std = chain(latent, &[], Some(act)).remove(0);
        Policy {
            content_hash: String::new(),
            actor: Actor { trunk, mu, log_std },
            critics,
            model,
            manifest,
        }
    }

    /// Maps an action from [-1, 1] to the action bounds.
    pub fn unscale_action(&self, squashed: &[f32], out: &mut [f32]) {
        let (lo, hi) = (&self.manifest.action_low, &self.manifest.action_high);
        for i in 0..squashed.len() {
            out[i] = lo[i] + 0.5 * (squashed[i] + 1.0) * (hi[i] - lo[i]);
        }
    }

    /// Maps an action from the action bounds to [-1, 1].
    pub fn scale_action(&self, action: &[f32], out: &mut [f32]) {
        let (lo, hi) = (&self.manifest.action_low, &self.manifest.action_high);
        for i in 0..action.len() {
            out[i] = 2.0 * (action[i] - lo[i]) / (hi[i] - lo[i]) - 1.0;
        }
    }

    /// FLOPs of one evaluation of the actor (mean only), of one critic, and of the model.
    pub fn flops(&self) -> (u64, u64, u64) {
        let head = 2 * (self.actor.mu.weight.len()) as u64;
        let critic = self.critics.iter().map(Mlp::flops).sum::<u64>() / self.critics.len() as u64;
        (
            self.actor.trunk.flops() + head,
            critic,
            self.model.as_ref().map_or(0, |m| m.net.flops()),
        )
    }

    /// Deterministic actions (tanh(mu)) of many states: `obs` is [obs_dim, batch].
    pub fn mean_actions_batch(
        &self,
        obs: &DMatrix<f32>,
        scratch: &mut BatchScratch,
    ) -> DMatrix<f32> {
        let latent = self.actor.trunk.forward_batch(obs, scratch);
        let mut mu = DMatrix::zeros(self.act_dim(), obs.ncols());
        for mut column in mu.column_iter_mut() {
            column.copy_from(&self.actor.mu.bias);
        }
        mu.gemm(1.0, &self.actor.mu.weight, latent, 1.0);
        mu.apply(|v| *v = v.tanh());
        mu
    }

    /// Aggregated Q of many (state, action) pairs: `obs_actions` is [obs_dim + act_dim, batch].
    pub fn q_batch(&self, obs_actions: &DMatrix<f32>, scratch: &mut BatchScratch) -> DVector<f32> {
        let mut q = DVector::zeros(obs_actions.ncols());
        for (k, critic) in self.critics.iter().enumerate() {
            let out = critic.forward_batch(obs_actions, scratch);
            for (j, v) in out.row(0).iter().enumerate() {
                q[j] = aggregate(self.manifest.q_aggregation, k, q[j], *v);
            }
        }
        if self.manifest.q_aggregation == QAggregation::Mean {
            q /= self.critics.len() as f32;
        }
        q
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

/// Runs a policy's networks for one session: owns every buffer a step needs.
#[derive(Clone, Debug)]
pub struct Evaluator {
    policy: Arc<Policy>,
    actor: MlpScratch,
    mu: DVector<f32>,
    log_std: DVector<f32>,
    critics: Vec<MlpScratch>,
    /// Second state of each critic's pair forward.
    critics_pair: Vec<MlpScratch>,
    model: Option<MlpScratch>,
}

impl Evaluator {
    pub fn new(policy: Arc<Policy>) -> Evaluator {
        Evaluator {
            actor: policy.actor.trunk.scratch(),
            mu: DVector::zeros(policy.act_dim()),
            log_std: DVector::zeros(policy.act_dim()),
            critics: policy.critics.iter().map(Mlp::scratch).collect(),
            critics_pair: policy.critics.iter().map(Mlp::scratch).collect(),
            model: policy.model.as_ref().map(|m| m.net.scratch()),
            policy,
        }
    }
    pub fn policy(&self) -> &Arc<Policy> {
        &self.policy
    }
}

impl Networks for Evaluator {
    fn obs_dim(&self) -> usize {
        self.policy.obs_dim()
    }
    fn act_dim(&self) -> usize {
        self.policy.act_dim()
    }

    fn act(&mut self, obs: &[f32], noise: Option<&[f32]>, action: &mut [f32]) {
        let actor = &self.policy.actor;
        let latent = actor.trunk.forward(obs, &mut self.actor);
        let latent = DVectorView::from_slice(latent, latent.len());
        self.mu.copy_from(&actor.mu.bias);
        self.mu.gemv(1.0, &actor.mu.weight, &latent, 1.0);
        match noise {
            None => {
                for (a, m) in action.iter_mut().zip(self.mu.iter()) {
                    *a = m.tanh();
                }
            }
            Some(noise) => {
                self.log_std.copy_from(&actor.log_std.bias);
                self.log_std.gemv(1.0, &actor.log_std.weight, &latent, 1.0);
                for i in 0..action.len() {
                    let std = self.log_std[i].clamp(LOG_STD_MIN, LOG_STD_MAX).exp();
                    action[i] = (self.mu[i] + std * noise[i]).tanh();
                }
            }
        }
    }

    fn q(&mut self, obs: &[f32], action: &[f32]) -> f32 {
        let how = self.policy.manifest.q_aggregation;
        let mut q = 0.0;
        for (k, (critic, scratch)) in self
            .policy
            .critics
            .iter()
            .zip(&mut self.critics)
            .enumerate()
        {
            let input = critic.input_buffer(scratch);
            input[..obs.len()].copy_from_slice(obs);
            input[obs.len()..].copy_from_slice(action);
            q = aggregate(how, k, q, critic.forward_scratch_input(scratch)[0]);
        }
        match how {
            QAggregation::Min => q,
            QAggregation::Mean => q / self.policy.critics.len() as f32,
        }
    }

    fn q_pair(&mut self, obs: &[f32], a: &[f32], b: &[f32]) -> (f32, f32) {
        let how = self.policy.manifest.q_aggregation;
        let (mut qa, mut qb) = (0.0, 0.0);
        let scratches = self.critics.iter_mut().zip(&mut self.critics_pair);
        for (k, (critic, (sa, sb))) in self.policy.critics.iter().zip(scratches).enumerate() {
            for (scratch, action) in [(&mut *sa, a), (&mut *sb, b)] {
                let input = critic.input_buffer(scratch);
                input[..obs.len()].copy_from_slice(obs);
                input[obs.len()..].copy_from_slice(action);
            }
            critic.forward_pair_scratch_inputs(sa, sb);
            qa = aggregate(how, k, qa, sa.output()[0]);
            qb = aggregate(how, k, qb, sb.output()[0]);
        }
        match how {
            QAggregation::Min => (qa, qb),
            QAggregation::Mean => {
                let n = self.policy.critics.len() as f32;
                (qa / n, qb / n)
            }
        }
    }

    fn predict_next(&mut self, obs: &[f32], action: &[f32], next_obs: &mut [f32]) {
        // Without a model there is no prediction: NaN makes Replan refuse the plan (NonFinite).
        let (Some(model), Some(scratch)) = (&self.policy.model, &mut self.model) else {
            next_obs.fill(f32::NAN);
            return;
        };
        let n = &model.normalization;
        let input = model.net.input_buffer(scratch);
        let (input_obs, input_act) = input.split_at_mut(obs.len());
        for i in 0..obs.len() {
            input_obs[i] = (obs[i] - n.obs_mean[i]) / n.obs_std[i];
        }
        for i in 0..action.len() {
            input_act[i] = (action[i] - n.action_mean[i]) / n.action_std[i];
        }
        let delta = model.net.forward_scratch_input(scratch);
        for i in 0..obs.len() {
            next_obs[i] = obs[i] + delta[i] * n.delta_std[i] + n.delta_mean[i];
        }
    }
}

/// The architecture of the paper's Hopper policy (SB3 defaults, model 4 x 64), for benchmarks and
/// tests.
pub fn hopper_sized_manifest() -> Manifest {
    test_manifest(
        "hopper-bench",
        "hopper",
        15,
        3,
        &[256, 256],
        &[64, 64, 64, 64],
    )
}

/// A manifest with identity normalisation, symmetric unit action bounds and a made-up value
/// scale: for benchmarks and tests that build their own networks.
pub fn test_manifest(
    name: &str,
    domain: &str,
    obs_dim: usize,
    act_dim: usize,
    hidden: &[usize],
    model_hidden: &[usize],
) -> Manifest {
    use crate::bundle::{CriticSpec, FORMAT_VERSION, ModelSpec, NetSpec, Provenance, ValueScale};
    Manifest {
        format_version: FORMAT_VERSION,
        name: name.to_string(),
        domain: domain.to_string(),
        obs_dim,
        act_dim,
        action_low: vec![-1.0; act_dim],
        action_high: vec![1.0; act_dim],
        gamma: 0.98,
        actor: NetSpec {
            hidden: hidden.to_vec(),
            activation: Activation::Relu,
        },
        critic: CriticSpec {
            n_critics: 2,
            hidden: hidden.to_vec(),
            activation: Activation::Relu,
        },
        model: Some(ModelSpec {
            hidden: model_hidden.to_vec(),
            activation: Activation::Relu,
            normalization: Normalization::identity(obs_dim, act_dim),
        }),
        q_aggregation: QAggregation::Min,
        value_scale: Some(ValueScale {
            v_pi: 10.0,
            v_rand: -10.0,
        }),
        provenance: Provenance {
            trainer: "random init (test)".to_string(),
            steps: 0,
            seed: 0,
            date: "1970-01-01T00:00:00Z".to_string(),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batched_and_single_evaluations_agree() {
        let policy = Arc::new(Policy::random(
            test_manifest("t", "d", 5, 2, &[16, 16], &[8]),
            3,
        ));
        let mut eval = Evaluator::new(policy.clone());
        let states: Vec<Vec<f32>> = (0..6)
            .map(|k| (0..5).map(|i| ((k * 7 + i) as f32).sin()).collect())
            .collect();
        let mut obs = DMatrix::zeros(5, 6);
        for (k, s) in states.iter().enumerate() {
            obs.column_mut(k).copy_from_slice(s);
        }
        let mut scratch = BatchScratch::default();
        let actions = policy.mean_actions_batch(&obs, &mut scratch);
        let mut obs_actions = DMatrix::zeros(7, 6);
        obs_actions.rows_mut(0, 5).copy_from(&obs);
        obs_actions.rows_mut(5, 2).copy_from(&actions);
        let q = policy.q_batch(&obs_actions, &mut scratch);
        for (k, s) in states.iter().enumerate() {
            let mut a = [0.0f32; 2];
            eval.act(s, None, &mut a);
            assert!((a[0] - actions[(0, k)]).abs() < 1e-5 && (a[1] - actions[(1, k)]).abs() < 1e-5);
            assert!((eval.q(s, &a) - q[k]).abs() < 1e-4);
            let other = [0.3f32, -0.6];
            let (qa, qb) = eval.q_pair(s, &a, &other);
            assert!((qa - q[k]).abs() < 1e-4);
            assert!((qb - eval.q(s, &other)).abs() < 1e-4);
        }
    }

    #[test]
    fn action_scaling_round_trips() {
        let mut manifest = test_manifest("t", "d", 3, 2, &[4], &[4]);
        manifest.action_low = vec![-2.0, 0.0];
        manifest.action_high = vec![2.0, 10.0];
        let policy = Policy::random(manifest, 0);
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
        let mut policy = Policy::random(manifest, 0);
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
