//! `prac export-onnx`: a bundle's networks as ONNX files a robot can run without prac, with the
//! contract (`prac.json`) that says what goes in and comes out.
//!
//! - `actor.onnx`: `observation` -> `action` (deterministic, within the action bounds), `mean`
//!   (before tanh) and, for a Gaussian actor, `log_std` (clamped as SB3 does).
//! - `critic_K.onnx`: (`observation`, `action`) -> `q`, one file per critic.
//! - `model.onnx`: (`observation`, `action`) -> `next_observation`, kept inside the bundle's
//!   observation bounds.
//!
//! Observations and actions are in the environment's units; the bundle's observation
//! normalisation, the action scaling and the model's normalisation are inside the graphs.
//! `reference.safetensors` holds states the policy visits and prac's outputs on them, for
//! checking a runtime.

mod graph;
mod reference;

use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::Serialize;
use sha2::{Digest, Sha256};

use crate::manifest::{QAggregation, ValueScale};
use crate::plan::Guard;
use crate::policy::{LOG_STD_MAX, LOG_STD_MIN, Policy};
use graph::{Attribute, Graph};

pub use graph::OPSET;
pub use reference::ROWS as REFERENCE_ROWS;

/// The version of `prac.json`'s layout.
pub const CONTRACT_VERSION: u32 = 1;

/// One exported file: its path in the folder, its inputs and outputs, and its digest.
#[derive(Clone, Debug, Serialize)]
pub struct ExportedFile {
    pub path: String,
    pub inputs: Vec<String>,
    pub outputs: Vec<String>,
    /// "sha256:<hex>" of the file.
    pub sha256: String,
}

/// The observation or action space, in the environment's units.
#[derive(Clone, Debug, Serialize)]
pub struct Space {
    pub size: usize,
    /// Per feature; null where unbounded.
    pub low: Vec<Option<f32>>,
    pub high: Vec<Option<f32>>,
}

/// `prac.json`: what the exported files take and give, and what Replan needs beside them.
#[derive(Clone, Debug, Serialize)]
pub struct Contract {
    pub contract_version: u32,
    pub opset: i64,
    /// The bundle's name and domain, and "sha256:<hex>" of the bundle file: a client holding
    /// these files can check that a server serves the same bundle (`PolicyInfo`).
    pub name: String,
    pub domain: String,
    pub content_hash: String,
    pub observation: Space,
    /// Continuous, within these bounds.
    pub action: Space,
    pub action_kind: &'static str,
    /// Seconds per step on the bundle's domain, where prac knows the domain.
    pub control_period: Option<f64>,
    /// What each observation and action entry is (name and unit), where prac knows the domain.
    pub features: Option<crate::domains::Features>,
    pub gamma: f64,
    /// How the critics combine into one Q: "min" or "mean".
    pub q_aggregation: QAggregation,
    /// Discounted start-state values of the policy and of random actions.
    pub value_scale: Option<ValueScale>,
    /// How a session's eps follows from its coefficient.
    pub epsilon_from_coefficient: &'static str,
    /// The plan guard of a session that asks for none.
    pub default_guard: Option<Guard>,
    pub actor: ExportedFile,
    pub critics: Vec<ExportedFile>,
    pub model: Option<ExportedFile>,
    /// `reference.safetensors`: `observation` and `action` rows, and each file's outputs on
    /// them as prac computes them, named `STEM.OUTPUT` (`actor.action`, `critic_0.q`, ...).
    pub reference: String,
}

/// Writes the ONNX files and `prac.json` of the bundle at `bundle` into the new folder `out`.
/// The bundle is checked as the server loads it; nothing is written unless everything is: the
/// files go into a sibling folder that is renamed to `out` at the end. `out` must not exist.
pub fn export_onnx(bundle: &Path, out: &Path) -> anyhow::Result<Contract> {
    let policy = std::sync::Arc::new(
        crate::bundle::load(bundle)
            .with_context(|| format!("cannot export {}", bundle.display()))?,
    );
    anyhow::ensure!(
        !out.exists(),
        "{} already exists; give a new folder to --out",
        out.display()
    );
    let partial = partial_path(out)?;
    let written = write_all(&policy, &partial);
    let contract = match written {
        Ok(contract) => contract,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&partial);
            return Err(e);
        }
    };
    std::fs::rename(&partial, out).with_context(|| {
        let _ = std::fs::remove_dir_all(&partial);
        format!("cannot move the export into {}", out.display())
    })?;
    Ok(contract)
}

/// A hidden sibling of `out` to write into first.
fn partial_path(out: &Path) -> anyhow::Result<PathBuf> {
    let name = out
        .file_name()
        .with_context(|| format!("{} names no folder", out.display()))?;
    let parent = out.parent().filter(|p| !p.as_os_str().is_empty());
    let partial = format!(".{}.partial-{}", name.to_string_lossy(), std::process::id());
    Ok(parent.map_or_else(|| PathBuf::from(&partial), |p| p.join(&partial)))
}

fn write_all(policy: &std::sync::Arc<Policy>, folder: &Path) -> anyhow::Result<Contract> {
    std::fs::create_dir_all(folder)
        .with_context(|| format!("cannot create {}", folder.display()))?;
    let write = |file: &str, graph: Graph, doc: &str, inputs: &[&str], outputs: &[&str]| {
        use prost::Message;
        let bytes = graph.into_model(doc).encode_to_vec();
        let path = folder.join(file);
        std::fs::write(&path, &bytes)
            .with_context(|| format!("cannot write {}", path.display()))?;
        anyhow::Ok(ExportedFile {
            path: file.into(),
            inputs: inputs.iter().map(|s| s.to_string()).collect(),
            outputs: outputs.iter().map(|s| s.to_string()).collect(),
            sha256: format!("sha256:{}", hex::encode(Sha256::digest(&bytes))),
        })
    };
    let (actor_graph, actor_outputs) = actor(policy);
    let actor = write(
        "actor.onnx",
        actor_graph,
        "prac actor: observation -> deterministic action within the action bounds",
        &["observation"],
        &actor_outputs,
    )?;
    let mut critics = Vec::new();
    for k in 0..policy.critics.len() {
        critics.push(write(
            &format!("critic_{k}.onnx"),
            critic(policy, k),
            "prac critic: (observation, action) -> Q",
            &["observation", "action"],
            &["q"],
        )?);
    }
    let model = match model(policy) {
        Some(graph) => Some(write(
            "model.onnx",
            graph,
            "prac dynamics model: (observation, action) -> next observation, within the bounds",
            &["observation", "action"],
            &["next_observation"],
        )?),
        None => None,
    };
    let reference = "reference.safetensors";
    std::fs::write(folder.join(reference), reference::to_bytes(policy)?)
        .with_context(|| format!("cannot write {reference}"))?;
    let m = &policy.manifest;
    let obs_bounds = m.obs_bounds.clone();
    let contract = Contract {
        contract_version: CONTRACT_VERSION,
        opset: OPSET,
        name: m.name.clone(),
        domain: m.domain.clone(),
        content_hash: policy.content_hash.clone(),
        observation: Space {
            size: m.obs_dim,
            low: obs_bounds
                .as_ref()
                .map_or_else(|| vec![None; m.obs_dim], |b| b.low.clone()),
            high: obs_bounds.map_or_else(|| vec![None; m.obs_dim], |b| b.high),
        },
        action: Space {
            size: m.act_dim,
            low: m.action_low.iter().copied().map(Some).collect(),
            high: m.action_high.iter().copied().map(Some).collect(),
        },
        action_kind: "continuous",
        control_period: crate::domains::control_period(&m.domain),
        features: policy.features(),
        gamma: m.gamma,
        q_aggregation: m.q_aggregation,
        value_scale: m.value_scale,
        epsilon_from_coefficient: "epsilon = epsilon_coef * (value_scale.v_pi - value_scale.v_rand)",
        default_guard: m.default_guard,
        actor,
        critics,
        model,
        reference: reference.into(),
    };
    let path = folder.join("prac.json");
    let text = serde_json::to_string_pretty(&contract)? + "\n";
    std::fs::write(&path, text).with_context(|| format!("cannot write {}", path.display()))?;
    Ok(contract)
}

/// The observations as the actor and critics see them: the bundle's normalisation applied,
/// `clip((s - mean) * inverse_std)` in the server's order of operations.
fn normalized_observation(g: &mut Graph, policy: &Policy, obs: &str) -> String {
    let Some(norm) = &policy.manifest.obs_normalization else {
        return obs.to_string();
    };
    let centred = g.with_row("Sub", obs, "obs_mean", &norm.mean);
    let scaled = g.with_row("Mul", &centred, "obs_inverse_std", &norm.inverse_std());
    g.clip(&scaled, -norm.clip_obs, norm.clip_obs)
}

/// Actions in the bounds mapped to [-1, 1], as the server maps them: `2 (a - low) / range - 1`.
fn squashed_action(g: &mut Graph, policy: &Policy, action: &str) -> String {
    let (low, high) = (&policy.manifest.action_low, &policy.manifest.action_high);
    let range: Vec<f32> = high.iter().zip(low).map(|(h, l)| h - l).collect();
    let shifted = g.with_row("Sub", action, "action_low", low);
    let doubled = g.with_scalar("Mul", &shifted, "two", 2.0);
    let unit = g.with_row("Div", &doubled, "action_range", &range);
    g.with_scalar("Sub", &unit, "one", 1.0)
}

fn actor(policy: &Policy) -> (Graph, Vec<&'static str>) {
    let (od, ad) = (policy.obs_dim(), policy.act_dim());
    let mut g = Graph::new("prac_actor");
    let obs = g.input("observation", od);
    let x = normalized_observation(&mut g, policy, &obs);
    let latent = g.mlp(&x, &policy.actor.trunk);
    let mu = g.dense(&latent, &policy.actor.mu);
    let log_std = policy
        .actor
        .log_std
        .as_ref()
        .map(|layer| g.dense(&latent, layer));
    let clipped = if policy.actor.mean_clip.is_finite() {
        g.clip(&mu, -policy.actor.mean_clip, policy.actor.mean_clip)
    } else {
        mu.clone()
    };
    let squashed = g.node("Tanh", &[&clipped], &[], None);
    // low + 0.5 (s + 1) range, in the server's order.
    let (low, high) = (&policy.manifest.action_low, &policy.manifest.action_high);
    let range: Vec<f32> = high.iter().zip(low).map(|(h, l)| h - l).collect();
    let plus_one = g.with_scalar("Add", &squashed, "one", 1.0);
    let half = g.with_scalar("Mul", &plus_one, "half", 0.5);
    let spread = g.with_row("Mul", &half, "action_range", &range);
    let action = g.with_row("Add", &spread, "action_low", low);
    g.output(&action, "action", ad);
    g.output(&mu, "mean", ad);
    let mut outputs = vec!["action", "mean"];
    if let Some(log_std) = log_std {
        let clamped = g.clip(&log_std, LOG_STD_MIN, LOG_STD_MAX);
        g.output(&clamped, "log_std", ad);
        outputs.push("log_std");
    }
    (g, outputs)
}

fn critic(policy: &Policy, k: usize) -> Graph {
    let (od, ad) = (policy.obs_dim(), policy.act_dim());
    let mut g = Graph::new(&format!("prac_critic_{k}"));
    let obs = g.input("observation", od);
    let action = g.input("action", ad);
    let x = normalized_observation(&mut g, policy, &obs);
    let a = squashed_action(&mut g, policy, &action);
    let input = g.node("Concat", &[&x, &a], &[Attribute::Int("axis", 1)], None);
    let q = g.mlp(&input, &policy.critics[k]);
    g.output(&q, "q", 1);
    g
}

fn model(policy: &Policy) -> Option<Graph> {
    let model = policy.model.as_ref()?;
    let (od, ad) = (policy.obs_dim(), policy.act_dim());
    let norm = &model.normalization;
    let mut g = Graph::new("prac_model");
    let obs = g.input("observation", od);
    let action = g.input("action", ad);
    let a = squashed_action(&mut g, policy, &action);
    let obs_centred = g.with_row("Sub", &obs, "model_obs_mean", &norm.obs_mean);
    let obs_in = g.with_row("Div", &obs_centred, "model_obs_std", &norm.obs_std);
    let act_centred = g.with_row("Sub", &a, "model_action_mean", &norm.action_mean);
    let act_in = g.with_row("Div", &act_centred, "model_action_std", &norm.action_std);
    let input = g.node(
        "Concat",
        &[&obs_in, &act_in],
        &[Attribute::Int("axis", 1)],
        None,
    );
    let delta = g.mlp(&input, &model.net);
    let scaled = g.with_row("Mul", &delta, "delta_std", &norm.delta_std);
    let shifted = g.with_row("Add", &scaled, "delta_mean", &norm.delta_mean);
    let mut next = g.node("Add", &[&obs, &shifted], &[], None);
    if let Some(bounds) = &policy.manifest.obs_bounds {
        let (low, high) = bounds.limits();
        next = g.with_row("Max", &next, "obs_low", &low);
        next = g.with_row("Min", &next, "obs_high", &high);
    }
    g.output(&next, "next_observation", od);
    Some(g)
}

#[cfg(test)]
mod tests;
