//! Algorithm 2 of the PrAC paper written the plain way: one old action and one network call at a
//! time, with a comment per step. It is the reading copy of [`super::replan_batch`], which must
//! give the same plans, outcomes and rng draws (src/plan/tests.rs checks it case by case); the
//! fast version batches sessions and tests old actions in chunks, and is otherwise this loop.

use rand::Rng;
use rand_distr::StandardNormal;

use super::{Growth, Networks, NonFinite, ReplanJob, ReplanOutcome};

/// Replan for one session, as the paper writes it. Allocates; use `replan` to serve.
pub fn reference_replan<N: Networks, R: Rng>(
    nets: &mut N,
    job: ReplanJob<'_, R>,
) -> Result<ReplanOutcome, NonFinite> {
    let ReplanJob {
        config,
        state,
        step,
        old,
        new,
        rng,
    } = job;
    let (obs_dim, act_dim) = (nets.obs_dim(), nets.act_dim());
    let failed = |what, index| Err(NonFinite { what, index });
    // The policy's noise: drawn only when sampling, so the deterministic mean draws nothing.
    let mut draw = |noise: &mut [f32]| {
        for z in noise.iter_mut() {
            *z = if config.sampled {
                rng.sample(StandardNormal)
            } else {
                0.0
            };
        }
    };
    // Line 1: an empty new plan.
    new.clear();
    let mut s = state.to_vec();
    let mut next = vec![0.0; obs_dim];
    let mut pi = vec![0.0; act_dim];
    let mut noise = vec![0.0; act_dim];
    let (mut q_pi, mut q_a, mut gap, mut distance) = ([0.0], [0.0], [0.0], [0.0]);
    let mut broke_at = None;
    // Lines 2-7: walk the old plan from the observed state while its actions stay good enough.
    for j in 0..old.len().min(config.max_horizon) {
        draw(&mut noise);
        nets.act(&s, &noise, &mut pi);
        if !pi.iter().all(|v| v.is_finite()) {
            return failed("actor", j);
        }
        nets.q_pair(&s, &pi, old.action(j), &mut q_pi, &mut q_a, Some(&mut gap));
        if !q_pi[0].is_finite() || !q_a[0].is_finite() {
            return failed("critic", j);
        }
        // The guard (off in the paper): any one critic's gap above eps, or an action the
        // policy's Gaussian puts too far from its mean, also breaks the plan.
        let guard = config.guard;
        if guard.every_critic && !gap[0].is_finite() {
            return failed("critic", j);
        }
        if guard.support_limit > 0.0 {
            nets.policy_distance(&s, old.action(j), &mut distance);
            if !distance[0].is_finite() {
                return failed("actor", j);
            }
        }
        // Lines 4-5: Q(s, a) + eps < Q(s, pi(s)) breaks the plan here.
        if q_a[0] + config.epsilon < q_pi[0]
            || (guard.every_critic && gap[0] > config.epsilon)
            || (guard.support_limit > 0.0 && distance[0] > guard.support_limit)
        {
            broke_at = Some(j);
            break;
        }
        // Lines 6-7: keep the old action and imagine where it leads with the model.
        nets.predict_next(&s, old.action(j), &mut next);
        if !next.iter().all(|v| v.is_finite()) {
            return failed("model", j);
        }
        new.push(old.action(j), &next, old.decided_at(j));
        s.copy_from_slice(&next);
    }
    // Lines 8-11: extend the plan with policy actions decided now, rolling the model on. The paper
    // appends 2; `Growth` also allows k or a refill to a fixed length.
    let kept = new.len();
    let wanted = match config.growth {
        Growth::Grow(k) => k,
        Growth::Fixed(n) => n.saturating_sub(kept),
    }
    .min(config.max_horizon - kept);
    for m in 0..wanted {
        // At a break, pi(s) at that state was drawn by the test and opens the extension.
        if !(m == 0 && broke_at.is_some()) {
            draw(&mut noise);
            nets.act(&s, &noise, &mut pi);
            if !pi.iter().all(|v| v.is_finite()) {
                return failed("actor", kept + m);
            }
        }
        nets.predict_next(&s, &pi, &mut next);
        if !next.iter().all(|v| v.is_finite()) {
            return failed("model", kept + m);
        }
        new.push(&pi, &next, step);
        s.copy_from_slice(&next);
    }
    Ok(ReplanOutcome {
        kept,
        broke_at,
        appended: wanted,
    })
}
