//! Replan (Algorithm 2 of the PrAC paper): one pure, seeded function over the three networks,
//! shared by the server and by training.
//!
//! Actions inside a plan are in the policy's squashed space [-1, 1]^act_dim, which is what the
//! critics and the model take; the server maps them to the action bounds only when answering.

use rand::Rng;
use rand_distr::StandardNormal;

/// The three networks Replan needs. Implementations own their scratch buffers (hence `&mut self`)
/// so that a step does not allocate.
pub trait Networks {
    fn obs_dim(&self) -> usize;
    fn act_dim(&self) -> usize;
    /// The policy's action at `obs`, in [-1, 1]: `tanh(mu)` when `noise` is `None`, otherwise
    /// `tanh(mu + std * noise)` with `noise` standard normal (one value per action dimension).
    fn act(&mut self, obs: &[f32], noise: Option<&[f32]>, action: &mut [f32]);
    /// The aggregated critic value Q(obs, action).
    fn q(&mut self, obs: &[f32], action: &[f32]) -> f32;
    /// Q(obs, a) and Q(obs, b) together (Replan's test compares two actions at one state);
    /// implementations may share the weight reads.
    fn q_pair(&mut self, obs: &[f32], a: &[f32], b: &[f32]) -> (f32, f32) {
        (self.q(obs, a), self.q(obs, b))
    }
    /// The dynamics model's prediction of the next observation.
    fn predict_next(&mut self, obs: &[f32], action: &[f32], next_obs: &mut [f32]);
}

/// How the plan is extended after its kept part.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Growth {
    /// Append k policy actions (the paper: k = 2, a net +1 per step while the plan holds).
    Grow(usize),
    /// Refill the plan to n actions (the prototype's fixed horizon).
    Fixed(usize),
}

impl Default for Growth {
    fn default() -> Self {
        Growth::Grow(2)
    }
}

pub const DEFAULT_MAX_HORIZON: usize = 32;

/// Per-session Replan settings, with eps already absolute.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReplanConfig {
    /// Tolerance of the test `Q(s, a) + eps < Q(s, pi(s))`; >= 0.
    pub epsilon: f32,
    pub growth: Growth,
    /// Longest plan, including the action executed now; >= 1.
    pub max_horizon: usize,
    /// Sample policy actions (training, or when asked) instead of the deterministic mean.
    pub sampled: bool,
}

impl Default for ReplanConfig {
    fn default() -> Self {
        ReplanConfig {
            epsilon: 0.0,
            growth: Growth::default(),
            max_horizon: DEFAULT_MAX_HORIZON,
            sampled: false,
        }
    }
}

/// A committed plan: actions, the model's predicted observation after each, and the step (within
/// the episode) at which each action was decided. Stored flat; capacity is reserved up front so
/// pushes within the horizon never allocate.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    obs_dim: usize,
    act_dim: usize,
    actions: Vec<f32>,
    next_obs: Vec<f32>,
    decided_at: Vec<u64>,
}

/// A borrowed run of plan entries (e.g. what is left of the last plan after its first action).
#[derive(Clone, Copy, Debug)]
pub struct PlanView<'a> {
    act_dim: usize,
    obs_dim: usize,
    actions: &'a [f32],
    next_obs: &'a [f32],
    decided_at: &'a [u64],
}

impl Plan {
    pub fn with_capacity(obs_dim: usize, act_dim: usize, capacity: usize) -> Plan {
        Plan {
            obs_dim,
            act_dim,
            actions: Vec::with_capacity(capacity * act_dim),
            next_obs: Vec::with_capacity(capacity * obs_dim),
            decided_at: Vec::with_capacity(capacity),
        }
    }
    pub fn len(&self) -> usize {
        self.decided_at.len()
    }
    pub fn is_empty(&self) -> bool {
        self.decided_at.is_empty()
    }
    pub fn act_dim(&self) -> usize {
        self.act_dim
    }
    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }
    pub fn clear(&mut self) {
        self.actions.clear();
        self.next_obs.clear();
        self.decided_at.clear();
    }
    pub fn push(&mut self, action: &[f32], next_obs: &[f32], decided_at: u64) {
        debug_assert_eq!(action.len(), self.act_dim);
        debug_assert_eq!(next_obs.len(), self.obs_dim);
        self.actions.extend_from_slice(action);
        self.next_obs.extend_from_slice(next_obs);
        self.decided_at.push(decided_at);
    }
    pub fn action(&self, i: usize) -> &[f32] {
        &self.actions[i * self.act_dim..(i + 1) * self.act_dim]
    }
    pub fn next_obs(&self, i: usize) -> &[f32] {
        &self.next_obs[i * self.obs_dim..(i + 1) * self.obs_dim]
    }
    pub fn decided_at(&self, i: usize) -> u64 {
        self.decided_at[i]
    }
    /// The entries from `start` on.
    pub fn tail(&self, start: usize) -> PlanView<'_> {
        let start = start.min(self.len());
        PlanView {
            act_dim: self.act_dim,
            obs_dim: self.obs_dim,
            actions: &self.actions[start * self.act_dim..],
            next_obs: &self.next_obs[start * self.obs_dim..],
            decided_at: &self.decided_at[start..],
        }
    }
}

impl<'a> PlanView<'a> {
    pub fn empty() -> PlanView<'static> {
        PlanView {
            act_dim: 0,
            obs_dim: 0,
            actions: &[],
            next_obs: &[],
            decided_at: &[],
        }
    }
    pub fn len(&self) -> usize {
        self.decided_at.len()
    }
    pub fn is_empty(&self) -> bool {
        self.decided_at.is_empty()
    }
    pub fn action(&self, i: usize) -> &'a [f32] {
        &self.actions[i * self.act_dim..(i + 1) * self.act_dim]
    }
    pub fn next_obs(&self, i: usize) -> &'a [f32] {
        &self.next_obs[i * self.obs_dim..(i + 1) * self.obs_dim]
    }
    pub fn decided_at(&self, i: usize) -> u64 {
        self.decided_at[i]
    }
}

/// What Replan did with the old plan.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ReplanOutcome {
    /// Old actions that passed the test and were kept.
    pub kept: usize,
    /// Index in the old plan of the action that failed the test.
    pub broke_at: Option<usize>,
    /// New policy actions appended after the kept ones.
    pub appended: usize,
}

/// A network gave a non-finite value; the new plan is unusable and the caller keeps its old one.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("the {what} produced a non-finite value at plan index {index}")]
pub struct NonFinite {
    pub what: &'static str,
    pub index: usize,
}

/// Buffers Replan reuses from step to step.
#[derive(Clone, Debug)]
pub struct ReplanScratch {
    state: Vec<f32>,
    next: Vec<f32>,
    policy_action: Vec<f32>,
    noise: Vec<f32>,
}

impl ReplanScratch {
    pub fn new(obs_dim: usize, act_dim: usize) -> ReplanScratch {
        ReplanScratch {
            state: vec![0.0; obs_dim],
            next: vec![0.0; obs_dim],
            policy_action: vec![0.0; act_dim],
            noise: vec![0.0; act_dim],
        }
    }
}

fn all_finite(values: &[f32]) -> bool {
    values.iter().all(|v| v.is_finite())
}

/// Draws the policy's action at `state` into `scratch.policy_action`.
fn policy_action<N: Networks, R: Rng>(
    nets: &mut N,
    sampled: bool,
    state: &[f32],
    scratch_noise: &mut [f32],
    out: &mut [f32],
    rng: &mut R,
) {
    if sampled {
        for z in scratch_noise.iter_mut() {
            *z = rng.sample(StandardNormal);
        }
        nets.act(state, Some(scratch_noise), out);
    } else {
        nets.act(state, None, out);
    }
}

/// Algorithm 2. Checks the old plan action by action from the observed `state`, keeping actions
/// while `Q(s, a) + eps >= Q(s, pi(s))` and rolling the model forward over them, then extends the
/// plan with policy actions decided at `step`. Writes the new plan into `new`; reads nothing but its
/// arguments, so the same inputs and rng state give the same plan.
///
/// The old plan is checked up to `max_horizon` actions; the new plan never exceeds `max_horizon`
/// and is never empty.
#[allow(clippy::too_many_arguments)]
pub fn replan<N: Networks, R: Rng>(
    nets: &mut N,
    config: &ReplanConfig,
    state: &[f32],
    step: u64,
    old: PlanView<'_>,
    new: &mut Plan,
    scratch: &mut ReplanScratch,
    rng: &mut R,
) -> Result<ReplanOutcome, NonFinite> {
    let max_horizon = config.max_horizon.max(1);
    new.clear();
    let ReplanScratch {
        state: s,
        next,
        policy_action: pi,
        noise,
    } = scratch;
    s.copy_from_slice(state);

    let mut broke_at = None;
    // When the plan breaks, pi(s) at the breaking state is already drawn: it is a valid first new
    // action (Algorithm 2 line 9 draws from the same distribution at the same state).
    let mut have_policy_action = false;
    for j in 0..old.len().min(max_horizon) {
        let action = old.action(j);
        policy_action(nets, config.sampled, s, noise, pi, rng);
        if !all_finite(pi) {
            return Err(NonFinite {
                what: "actor",
                index: j,
            });
        }
        let (q_policy, q_planned) = nets.q_pair(s, pi, action);
        if !q_policy.is_finite() || !q_planned.is_finite() {
            return Err(NonFinite {
                what: "critic",
                index: j,
            });
        }
        if q_planned + config.epsilon < q_policy {
            broke_at = Some(j);
            have_policy_action = true;
            break;
        }
        nets.predict_next(s, action, next);
        if !all_finite(next) {
            return Err(NonFinite {
                what: "model",
                index: j,
            });
        }
        new.push(action, next, old.decided_at(j));
        std::mem::swap(s, next);
    }
    let kept = new.len();

    let wanted = match config.growth {
        Growth::Grow(k) => k.max(1),
        Growth::Fixed(n) => n.max(1).saturating_sub(kept),
    };
    let appended = wanted.min(max_horizon - kept);
    for m in 0..appended {
        if !(m == 0 && have_policy_action) {
            policy_action(nets, config.sampled, s, noise, pi, rng);
            if !all_finite(pi) {
                return Err(NonFinite {
                    what: "actor",
                    index: kept + m,
                });
            }
        }
        nets.predict_next(s, pi, next);
        if !all_finite(next) {
            return Err(NonFinite {
                what: "model",
                index: kept + m,
            });
        }
        new.push(pi, next, step);
        std::mem::swap(s, next);
    }
    Ok(ReplanOutcome {
        kept,
        broke_at,
        appended,
    })
}

#[cfg(test)]
mod tests;
