//! Soft actor-critic as Stable-Baselines3 implements it: twin critics with Polyak-averaged
//! targets, a tanh-squashed Gaussian actor and an automatically tuned entropy coefficient.

use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor};
use rand::Rng;
use serde::{Deserialize, Serialize};

use super::nets::{ActorNet, CriticNet, EntropyCoef, matrix, scalar};

/// SAC's hyperparameters: SB3's defaults with the paper's gamma, plus its per-domain overrides.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SacConfig {
    pub gamma: f64,
    pub learning_rate: f64,
    pub buffer_size: usize,
    pub batch_size: usize,
    pub tau: f64,
    /// Steps of uniformly random actions before learning starts.
    pub learning_starts: u64,
    /// Environment steps between rounds of gradient steps.
    pub train_freq: u64,
    pub gradient_steps: usize,
    pub(crate) ent_coef_init: f64,
    /// Defaults to -dim(A).
    pub(crate) target_entropy: Option<f64>,
    pub hidden: Vec<usize>,
    pub(crate) n_critics: usize,
    /// The dynamics model (4 x 64 ReLU, Adam 1e-4, one step per SAC gradient step).
    pub(crate) model_hidden: Vec<usize>,
    pub(crate) model_learning_rate: f64,
    /// Actor and critics see observations normalised by the running mean and variance of those
    /// seen so far, as the SB3 zoo's `normalize: true` (VecNormalize) does; the bundle carries
    /// the statistics as its `obs_normalization`. Off by default (absent in older checkpoints).
    #[serde(default)]
    pub norm_obs: bool,
    /// A layer norm after each of the critics' hidden layers: the regularised critics with which
    /// recent sample-efficient SAC variants take several gradient steps per environment step.
    /// Off by default (absent in older checkpoints).
    #[serde(default)]
    pub critic_layer_norm: bool,
}

impl Default for SacConfig {
    fn default() -> Self {
        SacConfig {
            gamma: 0.98,
            learning_rate: 3e-4,
            buffer_size: 1_000_000,
            batch_size: 256,
            tau: 0.005,
            learning_starts: 100,
            train_freq: 1,
            gradient_steps: 1,
            ent_coef_init: 1.0,
            target_entropy: None,
            hidden: vec![256, 256],
            n_critics: 2,
            model_hidden: vec![64, 64, 64, 64],
            model_learning_rate: 1e-4,
            norm_obs: false,
            critic_layer_norm: false,
        }
    }
}

impl SacConfig {
    /// The paper's settings for a domain (section 4.1): SB3 defaults with gamma 0.98, and the
    /// zoo's overrides for Cheetah and Humanoid.
    /// Refuses settings SAC cannot learn with.
    pub(crate) fn validate(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            self.gamma > 0.0 && self.gamma < 1.0,
            "--gamma must be in (0, 1), got {}",
            self.gamma
        );
        anyhow::ensure!(self.batch_size > 0, "--batch-size must be > 0");
        anyhow::ensure!(self.train_freq > 0, "--train-freq must be > 0");
        anyhow::ensure!(
            self.learning_rate > 0.0 && self.learning_rate.is_finite(),
            "--learning-rate must be > 0, got {}",
            self.learning_rate
        );
        anyhow::ensure!(
            !self.hidden.is_empty() && self.hidden.iter().all(|&h| h > 0),
            "--hidden needs at least one layer, all > 0"
        );
        Ok(())
    }

    pub(crate) fn for_domain(domain: &str) -> SacConfig {
        let base = SacConfig::default();
        match domain {
            "cheetah" => SacConfig {
                learning_rate: 7.3e-4,
                buffer_size: 300_000,
                tau: 0.02,
                train_freq: 8,
                gradient_steps: 8,
                learning_starts: 10_000,
                ..base
            },
            "humanoid" => SacConfig {
                batch_size: 64,
                learning_starts: 1000,
                ..base
            },
            _ => base,
        }
    }
}

/// A minibatch of transitions, row-major; actions in [-1, 1] (the squashed space).
#[derive(Clone, Debug, Default)]
pub(crate) struct Batch {
    pub(crate) len: usize,
    pub(crate) obs: Vec<f32>,
    pub(crate) actions: Vec<f32>,
    pub(crate) rewards: Vec<f32>,
    pub(crate) next_obs: Vec<f32>,
    /// 1.0 where the episode terminated (not where it was truncated).
    pub(crate) dones: Vec<f32>,
}

/// What one gradient step measured.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub(crate) struct SacLosses {
    pub(crate) critic: f32,
    pub(crate) actor: f32,
    pub(crate) ent_coef: f32,
    pub(crate) ent_coef_loss: f32,
}

/// The learner: networks, target critics, temperature and their Adam optimisers.
pub(crate) struct Sac {
    pub(crate) config: SacConfig,
    pub(crate) obs_dim: usize,
    pub(crate) act_dim: usize,
    pub(crate) device: Device,
    pub(crate) actor: ActorNet,
    pub(crate) critic: CriticNet,
    /// Polyak-averaged critics, without autodiff.
    pub(crate) critic_target: CriticNet,
    pub(crate) ent_coef: EntropyCoef,
    pub(crate) actor_optim: ModuleOptimizer,
    pub(crate) critic_optim: ModuleOptimizer,
    pub(crate) ent_coef_optim: ModuleOptimizer,
    target_entropy: f32,
}

/// Adam as SB3 configures it (PyTorch's eps 1e-8, no weight decay).
pub(crate) fn adam() -> ModuleOptimizer {
    AdamConfig::new().with_epsilon(1e-8).init()
}

/// The autodiff CPU device training runs on.
pub(crate) fn train_device() -> Device {
    Device::flex().autodiff()
}

impl Sac {
    pub(crate) fn new<R: Rng>(
        config: SacConfig,
        obs_dim: usize,
        act_dim: usize,
        rng: &mut R,
    ) -> Sac {
        let device = train_device();
        let actor = ActorNet::new(obs_dim, act_dim, &config.hidden, rng, &device);
        let critic = CriticNet::new(
            obs_dim,
            act_dim,
            &config.hidden,
            config.n_critics,
            config.critic_layer_norm,
            rng,
            &device,
        );
        let critic_target = critic.valid();
        let target_entropy = config.target_entropy.unwrap_or(-(act_dim as f64)) as f32;
        Sac {
            ent_coef: EntropyCoef::new(config.ent_coef_init as f32, &device),
            actor,
            critic,
            critic_target,
            actor_optim: adam(),
            critic_optim: adam(),
            ent_coef_optim: adam(),
            target_entropy,
            config,
            obs_dim,
            act_dim,
            device,
        }
    }

    /// One gradient step on `batch` (SB3's order: temperature, critics, actor, targets).
    /// `noise` holds 2 x len x act_dim standard normal draws: the actor's samples at the
    /// observations, then at the next observations.
    pub(crate) fn update(&mut self, batch: &Batch, noise: &[f32]) -> SacLosses {
        let (n, od, ad) = (batch.len, self.obs_dim, self.act_dim);
        let dev = &self.device;
        let obs = matrix(&batch.obs, n, od, dev);
        let actions = matrix(&batch.actions, n, ad, dev);
        let rewards = matrix(&batch.rewards, n, 1, dev);
        let next_obs = matrix(&batch.next_obs, n, od, dev);
        let dones = matrix(&batch.dones, n, 1, dev);
        let noise_now = matrix(&noise[..n * ad], n, ad, dev);
        let noise_next = matrix(&noise[n * ad..2 * n * ad], n, ad, dev);
        let lr = self.config.learning_rate;

        let (pi_actions, log_prob) = self.actor.sample(obs.clone(), noise_now);

        // Temperature: the coefficient used below is the one before this step.
        let ent_coef = self.ent_coef.alpha();
        let ent_coef_loss = (self.ent_coef.log_alpha.val().unsqueeze::<2>()
            * log_prob.clone().detach().add_scalar(self.target_entropy))
        .mean()
        .neg();
        let grads = GradientsParams::from_grads(ent_coef_loss.backward(), &self.ent_coef);
        self.ent_coef = self.ent_coef_optim.step(lr, self.ent_coef.clone(), grads);

        let target = self
            .td_targets(&rewards, &dones, &next_obs, noise_next, ent_coef)
            .autodiff();
        let critic_loss = self
            .critic
            .forward(obs.clone(), actions)
            .into_iter()
            .map(|q| (q - target.clone()).square().mean())
            .reduce(|a, b| a + b)
            .expect("at least one critic")
            .mul_scalar(0.5);
        let critic_loss_value = scalar(critic_loss.clone().without_autodiff());
        let grads = GradientsParams::from_grads(critic_loss.backward(), &self.critic);
        self.critic = self.critic_optim.step(lr, self.critic.clone(), grads);

        // Actor against the updated critics; their weights get no gradient.
        let frozen = self.critic.clone().no_grad();
        let min_q = frozen.min_q(obs, pi_actions);
        let actor_loss = (log_prob.mul_scalar(ent_coef) - min_q).mean();
        let actor_loss_value = scalar(actor_loss.clone().without_autodiff());
        let grads = GradientsParams::from_grads(actor_loss.backward(), &self.actor);
        self.actor = self.actor_optim.step(lr, self.actor.clone(), grads);

        self.critic_target
            .soft_update(&self.critic, self.config.tau as f32);
        SacLosses {
            critic: critic_loss_value,
            actor: actor_loss_value,
            ent_coef,
            ent_coef_loss: scalar(ent_coef_loss.without_autodiff()),
        }
    }
}

impl Sac {
    /// Critic targets `r + (1 - done) gamma (min target Q(s', a') - alpha log pi(a'|s'))`, with
    /// `a'` the actor's sample at `s'` for `noise_next`; no autodiff.
    pub(crate) fn td_targets(
        &self,
        rewards: &Tensor<2>,
        dones: &Tensor<2>,
        next_obs: &Tensor<2>,
        noise_next: Tensor<2>,
        ent_coef: f32,
    ) -> Tensor<2> {
        let actor = self.actor.valid();
        let next_obs = next_obs.clone().without_autodiff();
        let (next_actions, next_log_prob) =
            actor.sample(next_obs.clone(), noise_next.without_autodiff());
        let next_q =
            self.critic_target.min_q(next_obs, next_actions) - next_log_prob.mul_scalar(ent_coef);
        let not_done = dones.clone().without_autodiff().neg().add_scalar(1.0);
        rewards.clone().without_autodiff()
            + (not_done * next_q).mul_scalar(self.config.gamma as f32)
    }
}
