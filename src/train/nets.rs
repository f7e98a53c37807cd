//! The trainable networks (burn modules) and their conversion to and from the inference
//! networks of a [`Policy`], which the bundle format stores.

use burn::module::{Module, Param};
use burn::nn::{LayerNorm, LayerNormConfig, Linear};
use burn::tensor::activation::{relu, tanh};
use burn::tensor::{Device, Tensor, TensorData};
use rand::Rng;

use crate::nn::{self, Dense, Mlp};
use crate::policy::{Actor, LOG_STD_MAX, LOG_STD_MIN};

/// ln(2 pi) / 2, for Gaussian log-densities.
const HALF_LN_TWO_PI: f32 = 0.918_938_5;
/// SB3's epsilon inside `log(1 - tanh(u)^2 + eps)`.
pub(crate) const SQUASH_EPS: f32 = 1e-6;

/// One affine layer with PyTorch's default initialisation, U(+-1/sqrt(fan_in)) for weight and
/// bias, drawn from `rng` so a seed fixes the whole run. Burn stores the weight as [in, out].
pub(crate) fn linear<R: Rng>(
    inputs: usize,
    outputs: usize,
    rng: &mut R,
    device: &Device,
) -> Linear {
    let bound = 1.0 / (inputs as f32).sqrt();
    let weight: Vec<f32> = (0..inputs * outputs)
        .map(|_| rng.random_range(-bound..bound))
        .collect();
    let bias: Vec<f32> = (0..outputs)
        .map(|_| rng.random_range(-bound..bound))
        .collect();
    linear_from(inputs, outputs, weight, bias, device)
}

/// A layer from [in, out] row-major weights and its bias.
pub(crate) fn linear_from(
    inputs: usize,
    outputs: usize,
    weight: Vec<f32>,
    bias: Vec<f32>,
    device: &Device,
) -> Linear {
    Linear {
        weight: Param::from_tensor(Tensor::from_data(
            TensorData::new(weight, [inputs, outputs]),
            device,
        )),
        bias: Some(Param::from_tensor(Tensor::from_data(
            TensorData::new(bias, [outputs]),
            device,
        ))),
    }
}

/// Rows of `values` ([rows, cols]) as a tensor.
pub(crate) fn matrix(values: &[f32], rows: usize, cols: usize, device: &Device) -> Tensor<2> {
    Tensor::from_data(TensorData::new(values.to_vec(), [rows, cols]), device)
}

fn values<const D: usize>(tensor: Tensor<D>) -> Vec<f32> {
    tensor
        .into_data()
        .try_to_vec::<f32>()
        .expect("f32 tensors read back as f32")
}

/// A burn layer as an inference layer (PyTorch [out, in] layout). Burn's [in, out] row-major
/// weight is the column-major [out, in] matrix that [`Dense`] stores.
pub(crate) fn to_dense(layer: &Linear) -> Dense {
    let [inputs, outputs] = layer.weight.val().dims();
    let weight = values(layer.weight.val());
    let bias = layer
        .bias
        .as_ref()
        .map_or_else(|| vec![0.0; outputs], |b| values(b.val()));
    Dense::new(
        nalgebra::DMatrix::from_column_slice(outputs, inputs, &weight),
        nalgebra::DVector::from_vec(bias),
    )
}

/// A burn layer norm with the given per-feature scale and shift.
fn layer_norm_from(scale: &[f32], shift: &[f32], device: &Device) -> LayerNorm {
    let d = scale.len();
    let mut norm = LayerNormConfig::new(d)
        .with_epsilon(f64::from(nn::LAYER_NORM_EPS))
        .init(device);
    let param =
        |v: &[f32]| Param::from_tensor(Tensor::from_data(TensorData::new(v.to_vec(), [d]), device));
    norm.gamma = param(scale);
    norm.beta = Some(param(shift));
    norm
}

/// Affine layers with ReLU between them (and after the last when `activate_output`), each
/// hidden layer's output layer-normalised first when `norms` is not empty.
#[derive(Module, Debug)]
pub(crate) struct MlpNet {
    pub(crate) layers: Vec<Linear>,
    /// Empty, or one per hidden layer (checkpoints of chains without them hold none).
    pub(crate) norms: Vec<LayerNorm>,
}

impl MlpNet {
    /// `inputs -> hidden... -> outputs` (no output layer when `outputs` is None).
    pub(crate) fn new<R: Rng>(
        inputs: usize,
        hidden: &[usize],
        outputs: Option<usize>,
        rng: &mut R,
        device: &Device,
    ) -> MlpNet {
        let mut layers = Vec::new();
        let mut width = inputs;
        for &h in hidden.iter().chain(outputs.as_ref()) {
            layers.push(linear(width, h, rng, device));
            width = h;
        }
        MlpNet {
            layers,
            norms: Vec::new(),
        }
    }

    /// The chain with a layer norm (scale 1, shift 0, as PyTorch starts one) after each hidden
    /// layer.
    pub(crate) fn with_layer_norms(mut self, device: &Device) -> MlpNet {
        let hidden = self.layers.len().saturating_sub(1);
        self.norms = self.layers[..hidden]
            .iter()
            .map(|l| {
                let [_, width] = l.weight.val().dims();
                layer_norm_from(&vec![1.0; width], &vec![0.0; width], device)
            })
            .collect();
        self
    }

    pub(crate) fn forward(&self, mut x: Tensor<2>, activate_output: bool) -> Tensor<2> {
        let last = self.layers.len() - 1;
        for (i, layer) in self.layers.iter().enumerate() {
            x = layer.forward(x);
            if let Some(norm) = self.norms.get(i) {
                x = norm.forward(x);
            }
            if i < last || activate_output {
                x = relu(x);
            }
        }
        x
    }

    pub(crate) fn to_mlp(&self, inputs: usize, activate_output: bool) -> Mlp {
        let mlp = Mlp::new(
            inputs,
            self.layers.iter().map(to_dense).collect(),
            crate::nn::Activation::Relu,
            activate_output,
        )
        .expect("a trained chain connects");
        if self.norms.is_empty() {
            return mlp;
        }
        let norms = self
            .norms
            .iter()
            .map(|n| {
                let scale = values(n.gamma.val());
                let shift = n
                    .beta
                    .as_ref()
                    .map_or_else(|| vec![0.0; scale.len()], |b| values(b.val()));
                nn::LayerNorm::new(scale, shift).expect("a trained norm's scale and shift agree")
            })
            .collect();
        mlp.with_layer_norms(norms)
            .expect("a trained chain's norms fit it")
    }
}

/// SB3's squashed Gaussian actor: a ReLU trunk, then mean and log-std heads.
#[derive(Module, Debug)]
pub(crate) struct ActorNet {
    pub(crate) trunk: MlpNet,
    pub(crate) mu: Linear,
    pub(crate) log_std: Linear,
}

impl ActorNet {
    pub(crate) fn new<R: Rng>(
        obs_dim: usize,
        act_dim: usize,
        hidden: &[usize],
        rng: &mut R,
        device: &Device,
    ) -> ActorNet {
        let trunk = MlpNet::new(obs_dim, hidden, None, rng, device);
        let latent = *hidden.last().unwrap_or(&obs_dim);
        ActorNet {
            trunk,
            mu: linear(latent, act_dim, rng, device),
            log_std: linear(latent, act_dim, rng, device),
        }
    }

    /// A reparameterised sample `tanh(mu + std * noise)` and its log-probability ([n, 1]) under
    /// the squashed Gaussian, with the change-of-variables correction
    /// `- sum log(1 - tanh(u)^2 + 1e-6)`.
    pub(crate) fn sample(&self, obs: Tensor<2>, noise: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let latent = self.trunk.forward(obs, true);
        let mu = self.mu.forward(latent.clone());
        let log_std = self.log_std.forward(latent).clamp(LOG_STD_MIN, LOG_STD_MAX);
        let u = mu + log_std.clone().exp() * noise.clone();
        let action = tanh(u);
        // (u - mu) / std is the noise itself.
        let gaussian = (noise.square().mul_scalar(-0.5) - log_std).add_scalar(-HALF_LN_TWO_PI);
        let squash = (action.clone().square().neg().add_scalar(1.0 + SQUASH_EPS)).log();
        let log_prob = (gaussian - squash).sum_dim(1);
        (action, log_prob)
    }

    /// The deterministic action `tanh(mu)`.
    #[cfg(test)]
    pub(crate) fn mean_action(&self, obs: Tensor<2>) -> Tensor<2> {
        let latent = self.trunk.forward(obs, true);
        tanh(self.mu.forward(latent))
    }

    pub(crate) fn to_actor(&self, obs_dim: usize) -> Actor {
        Actor {
            trunk: self.trunk.to_mlp(obs_dim, true),
            mu: to_dense(&self.mu),
            log_std: Some(to_dense(&self.log_std)),
            mean_clip: f32::INFINITY,
        }
    }
}

/// Twin (or more) Q networks over `cat(obs, action)`.
#[derive(Module, Debug)]
pub(crate) struct CriticNet {
    pub(crate) q: Vec<MlpNet>,
}

impl CriticNet {
    /// `layer_norm` puts a layer norm after each hidden layer (the regularised critics of
    /// sample-efficient SAC variants, which take more updates per step).
    pub(crate) fn new<R: Rng>(
        obs_dim: usize,
        act_dim: usize,
        hidden: &[usize],
        n_critics: usize,
        layer_norm: bool,
        rng: &mut R,
        device: &Device,
    ) -> CriticNet {
        CriticNet {
            q: (0..n_critics)
                .map(|_| {
                    let q = MlpNet::new(obs_dim + act_dim, hidden, Some(1), rng, device);
                    if layer_norm {
                        q.with_layer_norms(device)
                    } else {
                        q
                    }
                })
                .collect(),
        }
    }

    /// Each critic's Q values ([n, 1] each).
    pub(crate) fn forward(&self, obs: Tensor<2>, action: Tensor<2>) -> Vec<Tensor<2>> {
        let input = Tensor::cat(vec![obs, action], 1);
        self.q
            .iter()
            .map(|q| q.forward(input.clone(), false))
            .collect()
    }

    /// The minimum over the critics ([n, 1]).
    pub(crate) fn min_q(&self, obs: Tensor<2>, action: Tensor<2>) -> Tensor<2> {
        self.forward(obs, action)
            .into_iter()
            .reduce(|a, b| a.min_pair(b))
            .expect("at least one critic")
    }

    pub(crate) fn to_mlps(&self, input_dim: usize) -> Vec<Mlp> {
        self.q.iter().map(|q| q.to_mlp(input_dim, false)).collect()
    }

    /// Polyak averaging `self = (1 - tau) self + tau online`, without autodiff (a target net).
    pub(crate) fn soft_update(&mut self, online: &CriticNet, tau: f32) {
        fn average<const D: usize>(t: &mut Param<Tensor<D>>, s: &Param<Tensor<D>>, tau: f32) {
            let v = t.val().mul_scalar(1.0 - tau) + s.val().without_autodiff().mul_scalar(tau);
            *t = Param::from_tensor(v);
        }
        for (target, source) in self.q.iter_mut().zip(&online.q) {
            for (t, s) in target.layers.iter_mut().zip(&source.layers) {
                average(&mut t.weight, &s.weight, tau);
                if let (Some(tb), Some(sb)) = (&mut t.bias, &s.bias) {
                    average(tb, sb, tau);
                }
            }
            for (t, s) in target.norms.iter_mut().zip(&source.norms) {
                average(&mut t.gamma, &s.gamma, tau);
                if let (Some(tb), Some(sb)) = (&mut t.beta, &s.beta) {
                    average(tb, sb, tau);
                }
            }
        }
    }
}

/// The learned temperature, as SB3 keeps it: log(alpha).
#[derive(Module, Debug)]
pub(crate) struct EntropyCoef {
    pub(crate) log_alpha: Param<Tensor<1>>,
}

impl EntropyCoef {
    pub(crate) fn new(initial: f32, device: &Device) -> EntropyCoef {
        EntropyCoef {
            log_alpha: Param::from_tensor(Tensor::from_data(
                TensorData::new(vec![initial.ln()], [1]),
                device,
            )),
        }
    }
    pub(crate) fn alpha(&self) -> f32 {
        values(self.log_alpha.val())[0].exp()
    }
}

/// Reads a [n, k] tensor back as row-major values.
#[cfg(test)]
pub(crate) fn rows(tensor: Tensor<2>) -> Vec<f32> {
    values(tensor)
}

/// Reads a one-element tensor.
pub(crate) fn scalar(tensor: Tensor<1>) -> f32 {
    values(tensor)[0]
}
