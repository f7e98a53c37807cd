//! `reference.safetensors`: states the policy visits on its own domain, actions near its own,
//! and what prac's forward passes give on them, so that any runtime can check that it runs the
//! exported files as prac does (the tests check tract and ONNX Runtime against it).

use std::collections::HashMap;
use std::sync::Arc;

use crate::plan::Networks;
use crate::policy::{Evaluator, Policy};

/// Rows of the reference.
pub const ROWS: usize = 64;

/// The reference's tensors, each [ROWS, width]: `observation`, `action` (within the bounds),
/// then each network's outputs under its file's stem (`actor.action`, `critic_0.q`, ...).
pub(super) fn tensors(policy: &Arc<Policy>) -> Vec<(String, Vec<usize>, Vec<f32>)> {
    let (od, ad) = (policy.obs_dim(), policy.act_dim());
    let states = visited_states(policy, ROWS);
    let mut evaluator = Evaluator::with_capacity(policy.clone(), ROWS);
    let mut squashed = vec![0.0; ROWS * ad];
    evaluator.act(&states, &vec![0.0; ROWS * ad], &mut squashed);
    let mut deterministic = vec![0.0; ROWS * ad];
    for (s, a) in squashed.chunks(ad).zip(deterministic.chunks_mut(ad)) {
        policy.unscale_action(s, a);
    }
    // Actions Replan asks the critics and the model about: the policy's, moved within a tenth
    // of the range, as a held plan's actions differ from pi(s).
    let mut actions = deterministic.clone();
    for (i, a) in actions.iter_mut().enumerate() {
        let k = i % ad;
        let (lo, hi) = (
            policy.manifest.action_low[k],
            policy.manifest.action_high[k],
        );
        *a = (*a + 0.1 * (hi - lo) * ((i % 7) as f32 / 7.0 - 0.5)).clamp(lo, hi);
    }
    // The files map actions in the bounds back to [-1, 1] as the server does.
    let mut back = vec![0.0; ROWS * ad];
    for (a, s) in actions.chunks(ad).zip(back.chunks_mut(ad)) {
        policy.scale_action(a, s);
    }
    let row = |name: String, width: usize, values: Vec<f32>| (name, vec![ROWS, width], values);
    let mut out = vec![
        row("observation".into(), od, states.clone()),
        row("action".into(), ad, actions),
        row("actor.action".into(), ad, deterministic),
    ];
    let (mean, log_std) = evaluator.actor_heads(&states);
    out.push(row("actor.mean".into(), ad, mean));
    if let Some(log_std) = log_std {
        out.push(row("actor.log_std".into(), ad, log_std));
    }
    for (k, q) in evaluator
        .each_critic(&states, &back)
        .into_iter()
        .enumerate()
    {
        out.push(row(format!("critic_{k}.q"), 1, q));
    }
    if policy.model.is_some() {
        let mut next = vec![0.0; ROWS * od];
        evaluator.predict_next(&states, &back, &mut next);
        out.push(row("model.next_observation".into(), od, next));
    }
    out
}

/// The reference file's bytes.
pub(super) fn to_bytes(policy: &Arc<Policy>) -> anyhow::Result<Vec<u8>> {
    let metadata = HashMap::from([
        ("format".to_string(), "prac-onnx-reference".to_string()),
        ("content_hash".to_string(), policy.content_hash.clone()),
    ]);
    Ok(crate::bundle::serialize_f32(tensors(policy), metadata)?)
}

/// `count` states the bundle's own deterministic policy visits on its domain from seed 0, new
/// episodes as they end; for a domain prac lacks, states spread over [-1, 1].
fn visited_states(policy: &Arc<Policy>, count: usize) -> Vec<f32> {
    let od = policy.obs_dim();
    let Some(mut env) = crate::domains::make(&policy.manifest.domain)
        .filter(|env| env.spec().obs_dim == od && env.spec().act_dim == policy.act_dim())
    else {
        return (0..count * od)
            .map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0)
            .collect();
    };
    let mut evaluator = Evaluator::new(policy.clone());
    let ad = policy.act_dim();
    let (mut obs, mut squashed, mut action) = (vec![0.0; od], vec![0.0; ad], vec![0.0; ad]);
    let noise = vec![0.0; ad];
    let mut episode = 0;
    let mut states = Vec::with_capacity(count * od);
    let ready = env.reset(episode, &mut obs).is_ok();
    while ready && states.len() < count * od {
        states.extend_from_slice(&obs);
        evaluator.act(&obs, &noise, &mut squashed);
        policy.unscale_action(&squashed, &mut action);
        let ended = env
            .step(&action, &mut obs)
            .map_or(true, |t| t.terminated || t.truncated);
        if ended {
            episode += 1;
            if env.reset(episode, &mut obs).is_err() {
                break;
            }
        }
    }
    // A domain that refuses (it should not) leaves spread states for the rest.
    let missing = count * od - states.len();
    states.extend((0..missing).map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0));
    states
}
