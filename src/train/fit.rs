//! `prac fit-model`: (re)trains a bundle's dynamics model from recorded transitions, for agents
//! trained elsewhere, and reports its prediction error on held-out data.

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, bail};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use safetensors::SafeTensors;
use serde::Serialize;

use super::model::ModelTrainer;
use super::sac::{SacConfig, train_device};
use crate::bundle::ModelSpec;
use crate::eval::{ModelError, Trajectory, model_errors, model_errors_by_action};
use crate::nn::Activation;
use crate::policy::Policy;

/// Transitions as row-major arrays; actions in the domain's units.
pub struct Transitions {
    pub len: usize,
    pub obs: Vec<f32>,
    pub action: Vec<f32>,
    pub next_obs: Vec<f32>,
    /// Per row, whether its action was exploratory (the optional `explore` array).
    pub exploratory: Option<Vec<bool>>,
}

fn tensor_f32(st: &SafeTensors, path: &Path, name: &str, cols: usize) -> anyhow::Result<Vec<f32>> {
    let view = st.tensor(name).map_err(|_| {
        anyhow::anyhow!(
            "{}: {name}: missing (need obs, action, next_obs)",
            path.display()
        )
    })?;
    if view.dtype() != safetensors::Dtype::F32 {
        bail!(
            "{}: {name}: dtype {:?}; expected F32",
            path.display(),
            view.dtype()
        );
    }
    let shape = view.shape();
    if shape.len() != 2 || shape[1] != cols {
        bail!(
            "{}: {name}: shape {shape:?}; expected [N, {cols}]",
            path.display()
        );
    }
    Ok(view
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect())
}

impl Transitions {
    /// Reads `obs` [N, obs_dim], `action` [N, act_dim] and `next_obs` [N, obs_dim] (f32), and
    /// `explore` [N] (f32, nonzero where the action was exploratory) when present.
    pub fn load(path: &Path, obs_dim: usize, act_dim: usize) -> anyhow::Result<Transitions> {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let st = SafeTensors::deserialize(&bytes)
            .map_err(|e| anyhow::anyhow!("{}: not a safetensors file: {e}", path.display()))?;
        let obs = tensor_f32(&st, path, "obs", obs_dim)?;
        let action = tensor_f32(&st, path, "action", act_dim)?;
        let next_obs = tensor_f32(&st, path, "next_obs", obs_dim)?;
        let len = obs.len() / obs_dim;
        if action.len() / act_dim != len || next_obs.len() / obs_dim != len {
            bail!(
                "{}: obs, action and next_obs have different row counts",
                path.display()
            );
        }
        if len < 2 {
            bail!("{}: {len} transitions; need at least 2", path.display());
        }
        if let Some(i) = obs
            .iter()
            .chain(&action)
            .chain(&next_obs)
            .position(|v| !v.is_finite())
        {
            bail!(
                "{}: value {i} (in file order) is not finite",
                path.display()
            );
        }
        let exploratory = match st.tensor("explore") {
            Err(_) => None,
            Ok(view) => {
                if view.dtype() != safetensors::Dtype::F32 || view.shape() != [len] {
                    bail!(
                        "{}: explore: {:?} {:?}; expected F32 [{len}]",
                        path.display(),
                        view.dtype(),
                        view.shape()
                    );
                }
                Some(
                    view.data()
                        .chunks_exact(4)
                        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]) != 0.0)
                        .collect(),
                )
            }
        };
        Ok(Transitions {
            len,
            obs,
            action,
            next_obs,
            exploratory,
        })
    }

    /// Writes the arrays as a safetensors file.
    pub fn save(&self, path: &Path) -> anyhow::Result<()> {
        use safetensors::tensor::TensorView;
        let to_bytes = |v: &[f32]| -> Vec<u8> { v.iter().flat_map(|x| x.to_le_bytes()).collect() };
        let (o, a, n) = (
            to_bytes(&self.obs),
            to_bytes(&self.action),
            to_bytes(&self.next_obs),
        );
        let od = self.obs.len() / self.len;
        let ad = self.action.len() / self.len;
        let explore: Option<Vec<u8>> = self.exploratory.as_ref().map(|rows| {
            rows.iter()
                .flat_map(|&e| f32::from(u8::from(e)).to_le_bytes())
                .collect()
        });
        let mut views = vec![
            (
                "obs",
                TensorView::new(safetensors::Dtype::F32, vec![self.len, od], &o)?,
            ),
            (
                "action",
                TensorView::new(safetensors::Dtype::F32, vec![self.len, ad], &a)?,
            ),
            (
                "next_obs",
                TensorView::new(safetensors::Dtype::F32, vec![self.len, od], &n)?,
            ),
        ];
        if let Some(e) = &explore {
            views.push((
                "explore",
                TensorView::new(safetensors::Dtype::F32, vec![self.len], e)?,
            ));
        }
        std::fs::write(path, safetensors::serialize(views, None)?)?;
        Ok(())
    }
}

/// Splits rows into chains of consecutive transitions (next_obs of one is obs of the next).
pub(crate) fn chains(obs: &[f32], next_obs: &[f32], od: usize) -> Vec<std::ops::Range<usize>> {
    let n = obs.len() / od;
    let mut out = Vec::new();
    let mut start = 0;
    for i in 0..n {
        if i + 1 == n || next_obs[i * od..(i + 1) * od] != obs[(i + 1) * od..(i + 2) * od] {
            out.push(start..i + 1);
            start = i + 1;
        }
    }
    out
}

#[derive(Clone, Debug, Serialize)]
pub struct FitReport {
    pub(crate) train_transitions: usize,
    pub(crate) heldout_transitions: usize,
    pub(crate) gradient_steps: usize,
    pub(crate) final_loss: f32,
    /// The bundle's model before fitting, when it had one.
    pub(crate) before: Vec<ModelError>,
    pub(crate) after: Vec<ModelError>,
    /// `after` over held-out windows whose actions were all the policy's own, and over windows
    /// with an exploratory action; only where the transitions say which rows explored.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(crate) after_by_action: Option<ErrorsByAction>,
}

#[derive(Clone, Debug, Serialize)]
pub(crate) struct ErrorsByAction {
    pub(crate) on_policy: Vec<ModelError>,
    pub(crate) exploratory: Vec<ModelError>,
}

pub struct FitOptions {
    pub steps: usize,
    pub batch_size: usize,
    pub learning_rate: f64,
    pub holdout: f64,
    pub seed: u64,
    pub ks: Vec<usize>,
}

impl Default for FitOptions {
    fn default() -> Self {
        FitOptions {
            steps: 20_000,
            batch_size: 256,
            learning_rate: SacConfig::default().model_learning_rate,
            holdout: 0.1,
            seed: 0,
            ks: vec![1, 5, 10],
        }
    }
}

/// Fits a fresh 4 x 64 model (normalisation from the training rows) to `data`; the last
/// `holdout` fraction of rows is held out. Returns the policy with its new model.
pub fn fit_model(
    policy: &Policy,
    data: &Transitions,
    options: &FitOptions,
) -> anyhow::Result<(Policy, FitReport)> {
    let (od, ad) = (policy.obs_dim(), policy.act_dim());
    // The model sees actions in the policy's [-1, 1] space, as Replan does.
    let mut squashed = vec![0.0; data.action.len()];
    for (a, s) in data
        .action
        .chunks_exact(ad)
        .zip(squashed.chunks_exact_mut(ad))
    {
        policy.scale_action(a, s);
    }
    let held = ((data.len as f64 * options.holdout).round() as usize).clamp(1, data.len - 1);
    let train = data.len - held;
    let device = train_device();
    let mut rng = ChaCha8Rng::seed_from_u64(options.seed);
    let hidden = SacConfig::default().model_hidden;
    let mut trainer = ModelTrainer::new(od, ad, &hidden, options.learning_rate, &mut rng, &device);
    let mut delta = Vec::new();
    for i in 0..train {
        trainer.stats.push(
            &data.obs[i * od..(i + 1) * od],
            &squashed[i * ad..(i + 1) * ad],
            &data.next_obs[i * od..(i + 1) * od],
            &mut delta,
        );
    }
    let heldout: Vec<(Vec<f32>, std::ops::Range<usize>)> =
        chains(&data.obs[train * od..], &data.next_obs[train * od..], od)
            .into_iter()
            .map(|rows| {
                let rows = train + rows.start..train + rows.end;
                let mut observations = data.obs[rows.start * od..rows.end * od].to_vec();
                observations.extend_from_slice(&data.next_obs[(rows.end - 1) * od..rows.end * od]);
                (observations, rows)
            })
            .collect();
    let trajectories: Vec<Trajectory> = heldout
        .iter()
        .map(|(observations, rows)| Trajectory {
            observations,
            actions: &squashed[rows.start * ad..rows.end * ad],
            exploratory: data
                .exploratory
                .as_ref()
                .map_or(&[][..], |e| &e[rows.clone()]),
        })
        .collect();
    let before = if policy.model.is_some() {
        model_errors(&Arc::new(policy.clone()), &trajectories, &options.ks)
    } else {
        Vec::new()
    };
    let (mut bo, mut ba, mut bn) = (Vec::new(), Vec::new(), Vec::new());
    let mut final_loss = f32::NAN;
    use rand::Rng;
    for _ in 0..options.steps {
        bo.clear();
        ba.clear();
        bn.clear();
        for _ in 0..options.batch_size {
            let i = rng.random_range(0..train);
            bo.extend_from_slice(&data.obs[i * od..(i + 1) * od]);
            ba.extend_from_slice(&squashed[i * ad..(i + 1) * ad]);
            bn.extend_from_slice(&data.next_obs[i * od..(i + 1) * od]);
        }
        final_loss = trainer.update(&bo, &ba, &bn);
    }
    let mut fitted = policy.clone();
    fitted.model = Some(trainer.to_model());
    if let Some(model) = &fitted.model {
        fitted.manifest.model = Some(ModelSpec {
            hidden,
            activation: Activation::Relu,
            normalization: model.normalization.clone(),
        });
    }
    let fitted_arc = Arc::new(fitted.clone());
    let after = model_errors(&fitted_arc, &trajectories, &options.ks);
    let after_by_action = data.exploratory.as_ref().map(|_| {
        let (on_policy, exploratory) =
            model_errors_by_action(&fitted_arc, &trajectories, &options.ks);
        ErrorsByAction {
            on_policy,
            exploratory,
        }
    });
    Ok((
        fitted,
        FitReport {
            train_transitions: train,
            heldout_transitions: held,
            gradient_steps: options.steps,
            final_loss,
            before,
            after,
            after_by_action,
        },
    ))
}
