//! `prac inspect FILE [--json]`: the manifest of a bundle and one forward pass.

use std::path::{Path, PathBuf};

use clap::Args;
use std::sync::Arc;

use prac::bundle;
use prac::plan::Networks;
use prac::policy::Evaluator;

#[derive(Args, Debug)]
pub struct InspectArgs {
    file: PathBuf,
    /// Print only the manifest, as JSON.
    #[arg(long)]
    json: bool,
}

impl InspectArgs {
    pub fn run(self) -> anyhow::Result<()> {
        print!("{}", describe(&self.file, self.json)?);
        Ok(())
    }
}

/// Loads the bundle (with full validation) and describes it; with `json`, prints only the
/// manifest as JSON.
fn describe(path: &Path, json: bool) -> anyhow::Result<String> {
    let policy = Arc::new(bundle::load(path)?);
    let m = &policy.manifest;
    if json {
        return Ok(serde_json::to_string_pretty(m)? + "\n");
    }
    let mut out = String::new();
    let mut line = |s: String| {
        out.push_str(&s);
        out.push('\n');
    };
    line(format!("bundle       {}", path.display()));
    line(format!("content      {}", policy.content_hash));
    line(format!("format       v{}", m.format_version));
    line(format!("name         {}", m.name));
    line(format!("domain       {}", m.domain));
    line(format!("obs_dim      {}", m.obs_dim));
    line(format!("act_dim      {}", m.act_dim));
    line(format!("action_low   {:?}", m.action_low));
    line(format!("action_high  {:?}", m.action_high));
    line(format!("gamma        {}", m.gamma));
    let clip = m
        .actor
        .mean_clip
        .map(|c| format!(", mean clipped to +-{c}"))
        .unwrap_or_default();
    line(format!(
        "actor        {}, hidden {:?} {:?}{clip}",
        m.actor.kind.as_str(),
        m.actor.hidden,
        m.actor.activation
    ));
    if let Some(n) = &m.obs_normalization {
        line(format!(
            "observations normalised for the actor and critics: clip((s - mean) / sqrt(var + {}), +-{})",
            n.epsilon, n.clip_obs
        ));
    }
    line(format!(
        "critics      {} x hidden {:?} {:?}, Q = {} of critics",
        m.critic.n_critics,
        m.critic.hidden,
        m.critic.activation,
        m.q_aggregation.as_str()
    ));
    match &m.model {
        Some(model) => line(format!(
            "model        hidden {:?} {:?}, predicts normalised s' - s",
            model.hidden, model.activation
        )),
        None => line("model        none (add one with prac fit-model; serving needs it)".into()),
    }
    match m.value_scale {
        Some(v) => line(format!(
            "value scale  V_pi(s0) = {}, V_rand(s0) = {} (eps = coef x {})",
            v.v_pi,
            v.v_rand,
            v.v_pi - v.v_rand
        )),
        None => line("value scale  none (absolute eps only)".to_string()),
    }
    line(format!(
        "guard        {} (sessions that set none)",
        m.default_guard.unwrap_or_default()
    ));
    let p = &m.provenance;
    line(format!(
        "provenance   {} | {} steps | seed {} | {}",
        p.trainer, p.steps, p.seed, p.date
    ));

    // One forward pass at the model's mean observation (a state of the training distribution),
    // or at zeros without a model.
    let (obs, at) = match &m.model {
        Some(model) => (
            model.normalization.obs_mean.clone(),
            "model.normalization.obs_mean",
        ),
        None => (vec![0.0; m.obs_dim], "0"),
    };
    let mut eval = Evaluator::new(policy.clone());
    let mut squashed = vec![0.0; m.act_dim];
    eval.act(&obs, &vec![0.0; m.act_dim], &mut squashed);
    let (mut q, mut same) = ([0.0], [0.0]);
    eval.q_pair(&obs, &squashed, &squashed, &mut q, &mut same, None);
    let q = q[0];
    let mut action = vec![0.0; m.act_dim];
    policy.unscale_action(&squashed, &mut action);
    line(format!("forward pass at s = {at}:"));
    line(format!("  pi(s)      {action:?}"));
    line(format!("  Q(s,pi(s)) {q}"));
    if policy.model.is_some() {
        let mut next = vec![0.0; m.obs_dim];
        eval.predict_next(&obs, &squashed, &mut next);
        line(format!("  P(s,pi(s)) {next:?}"));
    }
    Ok(out)
}
