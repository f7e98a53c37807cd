//! What a policy is: sizes, action bounds, the networks' architecture, normalisation and
//! provenance. A bundle stores it as JSON in its safetensors `__metadata__` under the key
//! `manifest`; the policy and the bundle loader both read it, so it depends on neither.

use serde::{Deserialize, Serialize};

pub use crate::nn::Activation;
pub use crate::plan::Guard;

/// The version a bundle is written with when it uses nothing newer (every bundle `prac train`
/// writes): old servers keep reading them.
pub(crate) const FORMAT_VERSION: u32 = 1;
/// Version 2 adds `actor.kind` and `actor.mean_clip` (actors without a Gaussian head) and
/// `obs_normalization`.
pub const FORMAT_VERSION_ACTOR_KINDS: u32 = 2;
/// Version 3 adds `critic.layer_norm` (critics with a layer norm after each hidden layer).
pub(crate) const FORMAT_VERSION_CRITIC_NORMS: u32 = 3;
/// Version 4 adds `obs_bounds` (the observation space, which keeps the model's forecasts inside
/// it).
pub const FORMAT_VERSION_OBS_BOUNDS: u32 = 4;
/// Version 5 adds `default_guard` (the plan guard of sessions that ask for none): an older
/// server must refuse such a bundle rather than serve it without its guard.
pub const FORMAT_VERSION_DEFAULT_GUARD: u32 = 5;
/// Version 6 adds `default_guard.max_epsilon_coef` (a bundle's cap on its sessions' eps): a
/// version-5 server would ignore the field and serve the larger eps.
pub const FORMAT_VERSION_EPSILON_LIMIT: u32 = 6;
/// The newest version this prac reads.
pub(crate) const NEWEST_FORMAT_VERSION: u32 = FORMAT_VERSION_EPSILON_LIMIT;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format_version: u32,
    /// Policy name (informational; the server serves a bundle under its file name).
    pub name: String,
    /// Domain the policy controls, e.g. "hopper".
    pub domain: String,
    pub obs_dim: usize,
    pub act_dim: usize,
    /// Action bounds; the networks act in [-1, 1] and the server maps to [low, high].
    pub action_low: Vec<f32>,
    pub action_high: Vec<f32>,
    /// Discount of the critics' returns, in (0, 1).
    pub gamma: f64,
    pub actor: ActorSpec,
    pub critic: CriticSpec,
    /// The dynamics model; absent in bundles made from agents trained elsewhere until
    /// `prac fit-model` adds one. The server needs it to imagine plans.
    #[serde(default)]
    pub model: Option<ModelSpec>,
    #[serde(default)]
    pub q_aggregation: QAggregation,
    /// Discounted start-state values, for eps coefficients; absent means absolute eps only.
    #[serde(default)]
    pub value_scale: Option<ValueScale>,
    /// The observation normalisation the actor and critics were trained behind (format 2).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub obs_normalization: Option<ObsNormalization>,
    /// The observation space (format 4): every observation the model predicts is clamped into it.
    /// Absent: forecasts are not bounded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub obs_bounds: Option<ObsBounds>,
    /// The plan guard of a session that sets none (format 5), chosen from the bundle's measured
    /// falls. Absent: the paper's test.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub default_guard: Option<Guard>,
    /// What each observation and action entry is, by name and unit (informational: a server
    /// that does not know the field serves the bundle the same). Absent: prac's domain's, where
    /// it knows the domain.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub features: Option<Features>,
    pub provenance: Provenance,
}

/// One entry of an observation or action.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Feature {
    pub name: String,
    /// Its unit or scaling, e.g. "rad", "0.3 m/s", "joint range mapped to [-1, 1]".
    pub unit: String,
}

/// A policy's observation and action entries, in order.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Features {
    pub observation: Vec<Feature>,
    pub action: Vec<Feature>,
}

/// Per feature, the lowest and highest value an observation takes; null on a side where the
/// space is unbounded (a gymnasium Box's infinite bounds).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObsBounds {
    pub low: Vec<Option<f32>>,
    pub high: Vec<Option<f32>>,
}

impl ObsBounds {
    /// Bounds from limits where an infinite limit means unbounded.
    pub fn from_limits(low: &[f32], high: &[f32]) -> ObsBounds {
        let side = |v: &[f32]| v.iter().map(|&x| x.is_finite().then_some(x)).collect();
        ObsBounds {
            low: side(low),
            high: side(high),
        }
    }

    /// The limits to clamp to, infinite where unbounded.
    pub(crate) fn limits(&self) -> (Vec<f32>, Vec<f32>) {
        (
            self.low
                .iter()
                .map(|v| v.unwrap_or(f32::NEG_INFINITY))
                .collect(),
            self.high
                .iter()
                .map(|v| v.unwrap_or(f32::INFINITY))
                .collect(),
        )
    }
}

/// The actor: its trunk's widths and activation, and what its heads mean.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ActorSpec {
    pub hidden: Vec<usize>,
    pub activation: Activation,
    /// Absent in version-1 bundles, which are all Gaussian.
    #[serde(default, skip_serializing_if = "ActorKind::is_gaussian")]
    pub kind: ActorKind,
    /// gSDE actors: the mean is clipped to [-mean_clip, mean_clip] before tanh (SB3's
    /// `clip_mean`, a Hardtanh after the mean layer); absent where SB3 did not clip.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mean_clip: Option<f32>,
}

/// What the actor's heads are, and so what a sampled action is.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ActorKind {
    /// SAC's squashed Gaussian: `tanh(mu + exp(log_std) noise)`, `log_std` a head on the latent
    /// (`actor.log_std.*`); deterministic action `tanh(mu)`.
    #[default]
    Gaussian,
    /// SAC with generalised state-dependent exploration (SB3 `use_sde`): deterministic action
    /// `tanh(clip(mu))`. Its noise comes from exploration matrices resampled during training,
    /// not from the weights, so the bundle has no sampling distribution: sampled sessions are
    /// refused.
    GaussianSde,
    /// TD3 or DDPG: the action is `tanh(mu)` and there is no distribution; sampled sessions are
    /// refused.
    Deterministic,
}

impl ActorKind {
    pub(crate) fn is_gaussian(&self) -> bool {
        *self == ActorKind::Gaussian
    }
    pub fn as_str(self) -> &'static str {
        match self {
            ActorKind::Gaussian => "gaussian",
            ActorKind::GaussianSde => "gaussian_sde",
            ActorKind::Deterministic => "deterministic",
        }
    }
}

/// The dynamics model: hidden widths, activation and its input/output normalisation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelSpec {
    pub hidden: Vec<usize>,
    pub activation: Activation,
    pub normalization: Normalization,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CriticSpec {
    /// Number of critics (SB3's n_critics; 2 for twin critics).
    pub n_critics: usize,
    pub hidden: Vec<usize>,
    pub activation: Activation,
    /// A layer norm after each hidden layer, before its activation: PyTorch's
    /// `Sequential(Linear, LayerNorm, ReLU, ..., Linear)`, so the k-th linear layer's tensors are
    /// `critic.qf{i}.{3k}.*` and its norm's `critic.qf{i}.{3k+1}.weight` (scale) and `.bias`
    /// (shift). Absent (false) in bundles without them.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub layer_norm: bool,
}

/// The dynamics model's normalisation: inputs are standardised with the obs and action
/// statistics, the output is the standardised delta s' - s.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Normalization {
    pub obs_mean: Vec<f32>,
    pub(crate) obs_std: Vec<f32>,
    pub(crate) action_mean: Vec<f32>,
    pub(crate) action_std: Vec<f32>,
    pub(crate) delta_mean: Vec<f32>,
    pub(crate) delta_std: Vec<f32>,
}

impl Normalization {
    /// No normalisation (zero means, unit stds).
    pub(crate) fn identity(obs_dim: usize, act_dim: usize) -> Normalization {
        Normalization {
            obs_mean: vec![0.0; obs_dim],
            obs_std: vec![1.0; obs_dim],
            action_mean: vec![0.0; act_dim],
            action_std: vec![1.0; act_dim],
            delta_mean: vec![0.0; obs_dim],
            delta_std: vec![1.0; obs_dim],
        }
    }
}

/// SB3's VecNormalize of observations: the actor and critics see
/// `clip((s - mean) / sqrt(var + epsilon), -clip_obs, clip_obs)`. Clients, plans and the dynamics
/// model speak raw observations; the server applies it in front of the actor and critics only.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObsNormalization {
    pub mean: Vec<f32>,
    pub var: Vec<f32>,
    pub clip_obs: f32,
    pub epsilon: f32,
}

impl ObsNormalization {
    /// `1 / sqrt(var + epsilon)` per feature.
    pub(crate) fn inverse_std(&self) -> Vec<f32> {
        self.var
            .iter()
            .map(|&v| (1.0 / (f64::from(v) + f64::from(self.epsilon)).sqrt()) as f32)
            .collect()
    }
}

/// How the critics are combined into one Q.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum QAggregation {
    #[default]
    Min,
    Mean,
}

impl QAggregation {
    pub fn as_str(self) -> &'static str {
        match self {
            QAggregation::Min => "min",
            QAggregation::Mean => "mean",
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ValueScale {
    /// V_pi(s0), deterministic policy, discounted with the bundle's gamma.
    pub v_pi: f64,
    /// V_rand(s0), uniform random actions, discounted.
    pub v_rand: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    /// What produced the weights, e.g. "prac train 0.1.0" or "stable-baselines3 2.3.0".
    pub trainer: String,
    /// Environment steps trained.
    pub steps: u64,
    pub seed: u64,
    /// RFC 3339 date of creation.
    pub date: String,
}

impl Manifest {
    /// Checks everything the tensors do not: returns the offending field and why.
    pub fn validate(&self) -> Result<(), (String, String)> {
        let fail = |field: &str, why: String| Err((field.to_string(), why));
        if !(FORMAT_VERSION..=NEWEST_FORMAT_VERSION).contains(&self.format_version) {
            return fail(
                "format_version",
                format!(
                    "is {}, this prac reads versions {FORMAT_VERSION} to {NEWEST_FORMAT_VERSION}",
                    self.format_version
                ),
            );
        }
        if self.format_version < FORMAT_VERSION_ACTOR_KINDS && self.obs_normalization.is_some() {
            return fail(
                "obs_normalization",
                format!(
                    "needs format_version {FORMAT_VERSION_ACTOR_KINDS}, the bundle says {}",
                    self.format_version
                ),
            );
        }
        if let Some(bounds) = &self.obs_bounds {
            if self.format_version < FORMAT_VERSION_OBS_BOUNDS {
                return fail(
                    "obs_bounds",
                    format!(
                        "needs format_version {FORMAT_VERSION_OBS_BOUNDS}, the bundle says {}",
                        self.format_version
                    ),
                );
            }
            for (field, side) in [("low", &bounds.low), ("high", &bounds.high)] {
                if side.len() != self.obs_dim {
                    return fail(
                        &format!("obs_bounds.{field}"),
                        format!("has {} entries, obs_dim is {}", side.len(), self.obs_dim),
                    );
                }
                if let Some(i) = side.iter().position(|v| v.is_some_and(|v| !v.is_finite())) {
                    return fail(
                        &format!("obs_bounds.{field}[{i}]"),
                        "is not finite (null means unbounded)".into(),
                    );
                }
            }
            for (i, (lo, hi)) in bounds.low.iter().zip(&bounds.high).enumerate() {
                if let (Some(lo), Some(hi)) = (lo, hi)
                    && lo > hi
                {
                    return fail(
                        &format!("obs_bounds.low[{i}]"),
                        format!("{lo} is above obs_bounds.high[{i}] = {hi}"),
                    );
                }
            }
        }
        if let Some(guard) = &self.default_guard {
            self.validate_default_guard(guard)?;
        }
        if let Some(features) = &self.features {
            for (field, entries, size) in [
                ("observation", &features.observation, self.obs_dim),
                ("action", &features.action, self.act_dim),
            ] {
                if entries.len() != size {
                    return fail(
                        &format!("features.{field}"),
                        format!("has {} entries, the policy has {size}", entries.len()),
                    );
                }
                if let Some(i) = entries.iter().position(|e| e.name.is_empty()) {
                    return fail(&format!("features.{field}[{i}].name"), "is empty".into());
                }
            }
        }
        if self.format_version < FORMAT_VERSION_CRITIC_NORMS && self.critic.layer_norm {
            return fail(
                "critic.layer_norm",
                format!(
                    "needs format_version {FORMAT_VERSION_CRITIC_NORMS}, the bundle says {}",
                    self.format_version
                ),
            );
        }
        if let Some(n) = &self.obs_normalization {
            check_vector("obs_normalization.mean", &n.mean, self.obs_dim)?;
            check_vector("obs_normalization.var", &n.var, self.obs_dim)?;
            if let Some(i) = n.var.iter().position(|&v| v < 0.0) {
                return fail(
                    &format!("obs_normalization.var[{i}]"),
                    format!("is {}, a variance must be >= 0", n.var[i]),
                );
            }
            for (field, value) in [("clip_obs", n.clip_obs), ("epsilon", n.epsilon)] {
                if !(value.is_finite() && value > 0.0) {
                    return fail(
                        &format!("obs_normalization.{field}"),
                        format!("is {value}, expected a finite value > 0"),
                    );
                }
            }
        }
        if self.format_version < FORMAT_VERSION_ACTOR_KINDS
            && (!self.actor.kind.is_gaussian() || self.actor.mean_clip.is_some())
        {
            return fail(
                "actor.kind",
                format!(
                    "needs format_version {FORMAT_VERSION_ACTOR_KINDS}, the bundle says {}",
                    self.format_version
                ),
            );
        }
        match (self.actor.kind, self.actor.mean_clip) {
            (ActorKind::GaussianSde, Some(clip)) if !(clip.is_finite() && clip > 0.0) => {
                return fail(
                    "actor.mean_clip",
                    format!("is {clip}, expected a finite value > 0"),
                );
            }
            (ActorKind::Gaussian | ActorKind::Deterministic, Some(_)) => {
                return fail(
                    "actor.mean_clip",
                    format!(
                        "is only for gaussian_sde actors, this one is {}",
                        self.actor.kind.as_str()
                    ),
                );
            }
            _ => {}
        }
        if self.name.is_empty() {
            return fail("name", "is empty".into());
        }
        if self.obs_dim == 0 {
            return fail("obs_dim", "is 0".into());
        }
        if self.act_dim == 0 {
            return fail("act_dim", "is 0".into());
        }
        for (field, values) in [
            ("action_low", &self.action_low),
            ("action_high", &self.action_high),
        ] {
            check_vector(field, values, self.act_dim)?;
        }
        for (i, (lo, hi)) in self.action_low.iter().zip(&self.action_high).enumerate() {
            if lo >= hi {
                return fail(
                    &format!("action_low[{i}]"),
                    format!("{lo} is not below action_high[{i}] = {hi}"),
                );
            }
            // The server maps [-1, 1] onto [low, high] through high - low.
            if !(hi - lo).is_finite() {
                return fail(
                    &format!("action_high[{i}]"),
                    format!(
                        "the range [{lo}, {hi}] is wider than f32 can hold, so actions would \
                         not be finite; bound the action space"
                    ),
                );
            }
        }
        if !(self.gamma > 0.0 && self.gamma < 1.0) {
            return fail(
                "gamma",
                format!("is {}, expected a value in (0, 1)", self.gamma),
            );
        }
        if self.critic.n_critics == 0 {
            return fail("critic.n_critics", "is 0, expected at least 1".into());
        }
        let no_hidden = Vec::new();
        let model_hidden = self.model.as_ref().map_or(&no_hidden, |m| &m.hidden);
        for (field, hidden) in [
            ("actor.hidden", &self.actor.hidden),
            ("critic.hidden", &self.critic.hidden),
            ("model.hidden", model_hidden),
        ] {
            if let Some(i) = hidden.iter().position(|&w| w == 0) {
                return fail(&format!("{field}[{i}]"), "is 0, layers need a width".into());
            }
        }
        let Some(model) = &self.model else {
            return self.validate_value_scale();
        };
        let n = &model.normalization;
        for (field, values, dim, is_std) in [
            ("obs_mean", &n.obs_mean, self.obs_dim, false),
            ("obs_std", &n.obs_std, self.obs_dim, true),
            ("action_mean", &n.action_mean, self.act_dim, false),
            ("action_std", &n.action_std, self.act_dim, true),
            ("delta_mean", &n.delta_mean, self.obs_dim, false),
            ("delta_std", &n.delta_std, self.obs_dim, true),
        ] {
            let field = format!("model.normalization.{field}");
            check_vector(&field, values, dim)?;
            if is_std && let Some(i) = values.iter().position(|&v| v <= 0.0) {
                return fail(
                    &format!("{field}[{i}]"),
                    format!("is {}, a standard deviation must be > 0", values[i]),
                );
            }
        }
        self.validate_value_scale()
    }

    fn validate_default_guard(&self, guard: &Guard) -> Result<(), (String, String)> {
        let fail = |field: &str, why: String| Err((format!("default_guard{field}"), why));
        if self.format_version < FORMAT_VERSION_DEFAULT_GUARD {
            return fail(
                "",
                format!(
                    "needs format_version {FORMAT_VERSION_DEFAULT_GUARD}, the bundle says {}",
                    self.format_version
                ),
            );
        }
        let limit = guard.support_limit;
        if !(limit.is_finite() && limit >= 0.0) {
            return fail(
                ".support_limit",
                format!("is {limit}; expected a finite value >= 0 (0: no limit)"),
            );
        }
        if limit > 0.0 && !self.actor.kind.is_gaussian() {
            return fail(
                ".support_limit",
                format!(
                    "measures actions against the policy's Gaussian, and the actor is {}",
                    self.actor.kind.as_str()
                ),
            );
        }
        let coef = guard.max_epsilon_coef;
        if coef == 0.0 {
            return Ok(());
        }
        if self.format_version < FORMAT_VERSION_EPSILON_LIMIT {
            return fail(
                ".max_epsilon_coef",
                format!(
                    "needs format_version {FORMAT_VERSION_EPSILON_LIMIT}, the bundle says {}",
                    self.format_version
                ),
            );
        }
        if !(coef.is_finite() && coef > 0.0) {
            return fail(
                ".max_epsilon_coef",
                format!("is {coef}; expected a finite value >= 0 (0: no limit)"),
            );
        }
        if !self
            .value_scale
            .is_some_and(|scale| scale.v_pi > scale.v_rand)
        {
            return fail(
                ".max_epsilon_coef",
                "needs value_scale with V_pi > V_rand".to_string(),
            );
        }
        Ok(())
    }

    fn validate_value_scale(&self) -> Result<(), (String, String)> {
        match self.value_scale {
            Some(scale) if !scale.v_pi.is_finite() || !scale.v_rand.is_finite() => Err((
                "value_scale".to_string(),
                "holds a non-finite value".to_string(),
            )),
            // epsilon_coef multiplies V_pi - V_rand: it must stay a finite f32 tolerance.
            Some(scale) if (scale.v_pi - scale.v_rand).abs() > f32::MAX as f64 => Err((
                "value_scale".to_string(),
                format!(
                    "V_pi - V_rand = {} - {} is beyond f32's range; expected values in return \
                     units",
                    scale.v_pi, scale.v_rand
                ),
            )),
            _ => Ok(()),
        }
    }
}

fn check_vector(field: &str, values: &[f32], dim: usize) -> Result<(), (String, String)> {
    if values.len() != dim {
        return Err((
            field.to_string(),
            format!("has {} values, expected {dim}", values.len()),
        ));
    }
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err((format!("{field}[{i}]"), "is not finite".to_string()));
    }
    Ok(())
}
