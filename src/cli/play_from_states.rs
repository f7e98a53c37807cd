//! `prac play-from-states`: a planar walker set to given states (PyBullet's, as
//! scripts/conformance records them) plays given actions, or a policy, from each.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;

use prac::domains::{Env, Planar, PlanarState};

#[derive(Args, Debug)]
pub struct PlayFromStatesArgs {
    /// JSON: {"domain": "hopper", "cases": [{"state": {"root", "root_velocity", "joints",
    /// "joint_velocities"}, "actions": [[...], ...]}, ...]}.
    input: PathBuf,
    /// Where the steps go (JSON).
    #[arg(long)]
    out: PathBuf,
    /// Play this bundle's deterministic policy from each state (closed loop) instead of the
    /// cases' actions.
    #[arg(long)]
    policy: Option<PathBuf>,
    /// Steps the policy plays from each state (with --policy).
    #[arg(long, default_value_t = 100)]
    steps: usize,
}

impl PlayFromStatesArgs {
    pub fn run(self) -> anyhow::Result<()> {
        let closed_loop = self.policy.as_deref().map(|bundle| ClosedLoop {
            bundle,
            steps: self.steps,
        });
        play_from_states(&self.input, &self.out, closed_loop)
    }
}

/// What `prac play-from-states` reads: a planar domain and, per case, a state and the actions
/// to play from it.
#[derive(serde::Deserialize)]
struct StateCases {
    domain: String,
    cases: Vec<StateCase>,
}

#[derive(serde::Deserialize)]
struct StateCase {
    state: PlanarState,
    actions: Vec<Vec<f32>>,
}

/// One step played from a matched state.
#[derive(serde::Serialize)]
struct PlayedStep {
    /// The action played (the case's, or the policy's).
    action: Vec<f32>,
    obs: Vec<f32>,
    reward: f64,
    reward_terms: std::collections::BTreeMap<&'static str, f64>,
    terminated: bool,
}

#[derive(serde::Serialize)]
struct PlayedCase {
    /// The observation of the set state, then one row per step played (a case stops where its
    /// episode ends).
    start: Vec<f32>,
    steps: Vec<PlayedStep>,
}

/// A policy that `play-from-states` plays from each state instead of the case's actions.
struct ClosedLoop<'a> {
    bundle: &'a Path,
    steps: usize,
}

/// Plays every case of `input` (see [`StateCases`]), or the bundle's deterministic policy from
/// each case's state when `closed_loop` is given, and writes the observations and reward terms
/// to `out`.
fn play_from_states(
    input: &Path,
    out: &Path,
    closed_loop: Option<ClosedLoop>,
) -> anyhow::Result<()> {
    let text =
        std::fs::read_to_string(input).with_context(|| format!("reading {}", input.display()))?;
    let cases: StateCases =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", input.display()))?;
    let mut env = Planar::named(&cases.domain).with_context(|| {
        format!(
            "{} is not a planar walker (hopper, walker, cheetah)",
            cases.domain
        )
    })?;
    let mut policy = match &closed_loop {
        Some(c) => {
            let policy = std::sync::Arc::new(prac::bundle::load(c.bundle)?);
            anyhow::ensure!(
                policy.manifest.domain == cases.domain,
                "the bundle is for {}, the cases for {}",
                policy.manifest.domain,
                cases.domain
            );
            Some(prac::policy::Evaluator::new(policy))
        }
        None => None,
    };
    let spec = env.spec();
    let zeros = vec![0.0; spec.act_dim];
    let mut obs = vec![0.0; spec.obs_dim];
    let mut action = vec![0.0; spec.act_dim];
    let mut played = Vec::with_capacity(cases.cases.len());
    for (k, case) in cases.cases.iter().enumerate() {
        env.set_state(&case.state, &mut obs)
            .with_context(|| format!("case {k}"))?;
        let start = obs.clone();
        let length = closed_loop.as_ref().map_or(case.actions.len(), |c| c.steps);
        let mut steps = Vec::with_capacity(length);
        for i in 0..length {
            match policy.as_mut() {
                Some(p) => prac::plan::Networks::act(p, &obs, &zeros, &mut action),
                None => action.clone_from(&case.actions[i]),
            }
            let t = env
                .step(&action, &mut obs)
                .with_context(|| format!("case {k}, step {}", steps.len()))?;
            steps.push(PlayedStep {
                action: action.clone(),
                obs: obs.clone(),
                reward: t.reward,
                reward_terms: env.reward_terms().iter().copied().collect(),
                terminated: t.terminated,
            });
            if t.terminated || t.truncated {
                break;
            }
        }
        played.push(PlayedCase { start, steps });
    }
    std::fs::write(out, serde_json::to_string(&played)?)
        .with_context(|| format!("writing {}", out.display()))
}
