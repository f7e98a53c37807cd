//! The dynamics model of the paper (Nagabandi et al.): an MLP predicting the normalised change
//! `s' - s` from the normalised `(s, a)`, trained by Adam on squared error. Normalisation
//! statistics are running means and deviations of everything the trainer has seen; the bundle
//! stores the values in use when it was written.

use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::Device;
use rand::Rng;
use serde::{Deserialize, Serialize};

use super::nets::{MlpNet, matrix, scalar};
use crate::bundle::{Normalization, ObsNormalization};
use crate::policy::DynamicsModel;

/// A feature whose deviation is below this is constant in the data: it is normalised by 1, not
/// by its deviation, so the model's sensitivity to it (and to float rounding in it) stays that of
/// an ordinary feature instead of growing to 1 / deviation.
const CONSTANT_FEATURE_STD: f64 = 1e-4;

/// Welford running mean and variance per feature.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct RunningStats {
    pub(crate) count: u64,
    pub(crate) mean: Vec<f64>,
    pub(crate) m2: Vec<f64>,
}

impl RunningStats {
    pub(crate) fn new(dim: usize) -> RunningStats {
        RunningStats {
            count: 0,
            mean: vec![0.0; dim],
            m2: vec![0.0; dim],
        }
    }
    pub(crate) fn push(&mut self, values: &[f32]) {
        self.count += 1;
        let n = self.count as f64;
        for (i, &v) in values.iter().enumerate() {
            let v = f64::from(v);
            let delta = v - self.mean[i];
            self.mean[i] += delta / n;
            self.m2[i] += delta * (v - self.mean[i]);
        }
    }
    pub(crate) fn mean_f32(&self) -> Vec<f32> {
        self.mean.iter().map(|&m| m as f32).collect()
    }
    /// Population standard deviations; 1 for a constant feature and before two samples.
    pub(crate) fn std_f32(&self) -> Vec<f32> {
        self.m2
            .iter()
            .map(|&m2| {
                let std = (m2 / self.count.max(1) as f64).sqrt();
                if self.count < 2 || std < CONSTANT_FEATURE_STD {
                    1.0
                } else {
                    std as f32
                }
            })
            .collect()
    }

    /// The observation normalisation `--norm-obs` trains and ships with: these statistics'
    /// mean and population variance, with VecNormalize's clip 10 and epsilon 1e-8. A feature
    /// that has not varied (std below 1e-4) gets variance 1, as the model's normalisation gives
    /// it std 1: dividing by its float noise would make the networks hypersensitive to it.
    pub(crate) fn obs_normalization(&self) -> ObsNormalization {
        let std = self.std_f32();
        ObsNormalization {
            mean: self.mean_f32(),
            var: std.iter().map(|s| s * s).collect(),
            clip_obs: 10.0,
            epsilon: 1e-8,
        }
    }
}

/// Normalisation statistics of observations, actions and deltas.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct ModelStats {
    pub(crate) obs: RunningStats,
    pub(crate) action: RunningStats,
    pub(crate) delta: RunningStats,
}

impl ModelStats {
    pub(crate) fn new(obs_dim: usize, act_dim: usize) -> ModelStats {
        ModelStats {
            obs: RunningStats::new(obs_dim),
            action: RunningStats::new(act_dim),
            delta: RunningStats::new(obs_dim),
        }
    }
    pub(crate) fn push(
        &mut self,
        obs: &[f32],
        action: &[f32],
        next_obs: &[f32],
        delta: &mut Vec<f32>,
    ) {
        delta.clear();
        delta.extend(next_obs.iter().zip(obs).map(|(n, o)| n - o));
        self.obs.push(obs);
        self.action.push(action);
        self.delta.push(delta);
    }
    pub(crate) fn normalization(&self) -> Normalization {
        Normalization {
            obs_mean: self.obs.mean_f32(),
            obs_std: self.obs.std_f32(),
            action_mean: self.action.mean_f32(),
            action_std: self.action.std_f32(),
            delta_mean: self.delta.mean_f32(),
            delta_std: self.delta.std_f32(),
        }
    }
}

/// The model's network, optimiser and statistics.
pub(crate) struct ModelTrainer {
    pub(crate) obs_dim: usize,
    pub(crate) act_dim: usize,
    pub(crate) net: MlpNet,
    pub(crate) optim: ModuleOptimizer,
    pub(crate) stats: ModelStats,
    pub(crate) learning_rate: f64,
    device: Device,
}

/// Normalised inputs `[(s - mu_s) / sd_s, (a - mu_a) / sd_a]` and targets for a batch.
pub(crate) fn normalise_batch(
    norm: &Normalization,
    obs: &[f32],
    actions: &[f32],
    next_obs: &[f32],
) -> (Vec<f32>, Vec<f32>) {
    let od = norm.obs_mean.len();
    let ad = norm.action_mean.len();
    let n = obs.len() / od;
    let mut inputs = Vec::with_capacity(n * (od + ad));
    let mut targets = Vec::with_capacity(n * od);
    for k in 0..n {
        let (o, a, o2) = (
            &obs[k * od..(k + 1) * od],
            &actions[k * ad..(k + 1) * ad],
            &next_obs[k * od..(k + 1) * od],
        );
        inputs.extend((0..od).map(|i| (o[i] - norm.obs_mean[i]) / norm.obs_std[i]));
        inputs.extend((0..ad).map(|i| (a[i] - norm.action_mean[i]) / norm.action_std[i]));
        targets.extend((0..od).map(|i| (o2[i] - o[i] - norm.delta_mean[i]) / norm.delta_std[i]));
    }
    (inputs, targets)
}

impl ModelTrainer {
    pub(crate) fn new<R: Rng>(
        obs_dim: usize,
        act_dim: usize,
        hidden: &[usize],
        learning_rate: f64,
        rng: &mut R,
        device: &Device,
    ) -> ModelTrainer {
        ModelTrainer {
            obs_dim,
            act_dim,
            net: MlpNet::new(obs_dim + act_dim, hidden, Some(obs_dim), rng, device),
            optim: AdamConfig::new().with_epsilon(1e-8).init(),
            stats: ModelStats::new(obs_dim, act_dim),
            learning_rate,
            device: device.clone(),
        }
    }

    /// One Adam step on the squared error of the normalised delta; returns the loss.
    pub(crate) fn update(&mut self, obs: &[f32], actions: &[f32], next_obs: &[f32]) -> f32 {
        let n = obs.len() / self.obs_dim;
        let norm = self.stats.normalization();
        let (inputs, targets) = normalise_batch(&norm, obs, actions, next_obs);
        let dev = &self.device;
        let x = matrix(&inputs, n, self.obs_dim + self.act_dim, dev);
        let y = matrix(&targets, n, self.obs_dim, dev);
        let loss = (self.net.forward(x, false) - y).square().mean();
        let value = scalar(loss.clone().without_autodiff());
        let grads = GradientsParams::from_grads(loss.backward(), &self.net);
        self.net = self.optim.step(self.learning_rate, self.net.clone(), grads);
        value
    }

    /// Widths of the hidden layers.
    pub(crate) fn hidden(&self) -> Vec<usize> {
        let layers = &self.net.layers;
        layers[..layers.len() - 1]
            .iter()
            .map(|l| l.weight.val().dims()[1])
            .collect()
    }

    /// The model as the server evaluates it.
    pub(crate) fn to_model(&self) -> DynamicsModel {
        DynamicsModel {
            net: self.net.to_mlp(self.obs_dim + self.act_dim, false),
            normalization: self.stats.normalization(),
        }
    }
}
