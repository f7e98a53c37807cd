//! Replan (Algorithm 2 of the PrAC paper): one pure, seeded function over the three networks,
//! shared by the server and by training. It runs many sessions' replans in lockstep so that each
//! round evaluates the networks once over all of them (cross-session batching); a single replan
//! is a batch of one.
//!
//! Actions inside a plan are in the policy's squashed space [-1, 1]^act_dim, which is what the
//! critics and the model take; the server maps them to the action bounds only when answering.

use rand::Rng;
use rand_distr::StandardNormal;

/// The three networks Replan needs, over batches of states stored as rows (n rows of obs_dim
/// values, etc.). Implementations own their scratch buffers (hence `&mut self`), so that a step
/// does not allocate once a batch size has been seen. A row's result must not depend on the
/// other rows of its batch.
pub trait Networks {
    fn obs_dim(&self) -> usize;
    fn act_dim(&self) -> usize;
    /// The policy's actions in [-1, 1]: `tanh(mu + std * noise)` per row, `noise` standard
    /// normal, or zero for the deterministic `tanh(mu)`.
    fn act(&mut self, obs: &[f32], noise: &[f32], actions: &mut [f32]);
    /// Aggregated critic values of (obs, a) and (obs, b) per row: Replan's test compares two
    /// actions at one state.
    fn q_pair(&mut self, obs: &[f32], a: &[f32], b: &[f32], q_a: &mut [f32], q_b: &mut [f32]);
    /// The dynamics model's predictions of the next observations.
    fn predict_next(&mut self, obs: &[f32], actions: &[f32], next_obs: &mut [f32]);
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

/// One session's replan within a batch.
pub struct ReplanJob<'a, R> {
    pub config: ReplanConfig,
    /// The observed state.
    pub state: &'a [f32],
    /// The step index (within the episode) of `state`; new actions are decided at it.
    pub step: u64,
    /// What is left of the last plan (without the action already executed).
    pub old: PlanView<'a>,
    /// Receives the new plan.
    pub new: &'a mut Plan,
    pub rng: &'a mut R,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Phase {
    /// Testing old action `checked`.
    Checking,
    /// Appending policy actions, `appended` of `wanted` so far.
    Extending,
    Done,
}

#[derive(Clone, Debug)]
struct JobState {
    phase: Phase,
    checked: usize,
    limit: usize,
    broke_at: Option<usize>,
    wanted: usize,
    appended: usize,
    /// pi(s) of this round was drawn at the breaking state and opens the extension.
    have_policy_action: bool,
    error: Option<NonFinite>,
}

/// Buffers Replan reuses from step to step; they grow to the largest batch seen.
#[derive(Clone, Debug, Default)]
pub struct ReplanScratch {
    obs_dim: usize,
    act_dim: usize,
    jobs: Vec<JobState>,
    /// Per job: current (imagined) state and the policy's action there.
    states: Vec<f32>,
    policy_actions: Vec<f32>,
    /// Gathered rows of this round's network calls, and which job each row belongs to.
    act_rows: Vec<usize>,
    act_obs: Vec<f32>,
    act_noise: Vec<f32>,
    act_out: Vec<f32>,
    check_rows: Vec<usize>,
    check_obs: Vec<f32>,
    check_policy: Vec<f32>,
    check_planned: Vec<f32>,
    q_policy: Vec<f32>,
    q_planned: Vec<f32>,
    model_rows: Vec<usize>,
    model_obs: Vec<f32>,
    model_actions: Vec<f32>,
    model_next: Vec<f32>,
}

impl ReplanScratch {
    /// Scratch for one session: it fits a batch of one from the start.
    pub fn new(obs_dim: usize, act_dim: usize) -> ReplanScratch {
        ReplanScratch::with_capacity(obs_dim, act_dim, 1)
    }

    /// Scratch whose buffers fit batches of up to `jobs` sessions without growing.
    pub fn with_capacity(obs_dim: usize, act_dim: usize, jobs: usize) -> ReplanScratch {
        let obs = || Vec::with_capacity(jobs * obs_dim);
        let act = || Vec::with_capacity(jobs * act_dim);
        let one = || Vec::with_capacity(jobs);
        ReplanScratch {
            obs_dim,
            act_dim,
            jobs: Vec::with_capacity(jobs),
            states: obs(),
            policy_actions: act(),
            act_rows: one(),
            act_obs: obs(),
            act_noise: act(),
            act_out: act(),
            check_rows: one(),
            check_obs: obs(),
            check_policy: act(),
            check_planned: act(),
            q_policy: Vec::with_capacity(jobs),
            q_planned: Vec::with_capacity(jobs),
            model_rows: one(),
            model_obs: obs(),
            model_actions: act(),
            model_next: obs(),
        }
    }
}

fn all_finite(values: &[f32]) -> bool {
    values.iter().all(|v| v.is_finite())
}

/// Algorithm 2 for one session: checks the old plan action by action from the observed `state`,
/// keeping actions while `Q(s, a) + eps >= Q(s, pi(s))` and rolling the model forward over them,
/// then extends the plan with policy actions decided at `step`. Writes the new plan into `new`;
/// reads nothing but its arguments, so the same inputs and rng state give the same plan.
///
/// The old plan is checked up to `max_horizon` actions; the new plan never exceeds `max_horizon`
/// and is never empty. A non-finite network output is an error; `new` is then unusable.
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
    let mut jobs = [ReplanJob {
        config: *config,
        state,
        step,
        old,
        new,
        rng,
    }];
    let mut results = [Ok(ReplanOutcome {
        kept: 0,
        broke_at: None,
        appended: 0,
    })];
    replan_batch(nets, &mut jobs, scratch, &mut results);
    let [result] = results;
    result
}

/// [`replan`] for many sessions of one policy at once, with the same result for each as alone:
/// every round evaluates the actor, the critics and the model once over all sessions that need
/// them. `results[i]` receives job i's outcome.
pub fn replan_batch<N: Networks, R: Rng>(
    nets: &mut N,
    jobs: &mut [ReplanJob<'_, R>],
    scratch: &mut ReplanScratch,
    results: &mut [Result<ReplanOutcome, NonFinite>],
) {
    let (od, ad) = (nets.obs_dim(), nets.act_dim());
    scratch.obs_dim = od;
    scratch.act_dim = ad;
    let n = jobs.len();
    scratch.jobs.clear();
    scratch.states.clear();
    crate::nn::resize(&mut scratch.policy_actions, n * ad);
    for job in jobs.iter_mut() {
        job.new.clear();
        scratch.states.extend_from_slice(job.state);
        let max_horizon = job.config.max_horizon.max(1);
        scratch.jobs.push(JobState {
            phase: Phase::Checking,
            checked: 0,
            limit: job.old.len().min(max_horizon),
            broke_at: None,
            wanted: 0,
            appended: 0,
            have_policy_action: false,
            error: None,
        });
    }
    loop {
        // Jobs done checking start extending: wanted is known once `kept` is.
        for (job, st) in jobs.iter().zip(scratch.jobs.iter_mut()) {
            if st.phase == Phase::Checking && st.checked >= st.limit {
                start_extending(job, st);
            }
        }
        if scratch.jobs.iter().all(|st| st.phase == Phase::Done) {
            break;
        }
        draw_policy_actions(nets, jobs, scratch);
        check_planned_actions(nets, jobs, scratch);
        roll_model(nets, jobs, scratch);
    }
    for (i, st) in scratch.jobs.iter().enumerate() {
        let kept = jobs[i].new.len() - st.appended;
        results[i] = match st.error.clone() {
            Some(e) => Err(e),
            None => Ok(ReplanOutcome {
                kept,
                broke_at: st.broke_at,
                appended: st.appended,
            }),
        };
    }
}

fn start_extending<R>(job: &ReplanJob<'_, R>, st: &mut JobState) {
    let kept = job.new.len();
    let max_horizon = job.config.max_horizon.max(1);
    let wanted = match job.config.growth {
        Growth::Grow(k) => k.max(1),
        Growth::Fixed(n) => n.max(1).saturating_sub(kept),
    };
    st.wanted = wanted.min(max_horizon - kept);
    st.phase = if st.wanted == 0 {
        Phase::Done
    } else {
        Phase::Extending
    };
}

fn fail(st: &mut JobState, what: &'static str, index: usize) {
    st.error = Some(NonFinite { what, index });
    st.phase = Phase::Done;
}

/// pi(s) for every job that needs it this round, in one actor call.
fn draw_policy_actions<N: Networks, R: Rng>(
    nets: &mut N,
    jobs: &mut [ReplanJob<'_, R>],
    s: &mut ReplanScratch,
) {
    let (od, ad) = (s.obs_dim, s.act_dim);
    s.act_rows.clear();
    s.act_obs.clear();
    s.act_noise.clear();
    for (i, (job, st)) in jobs.iter_mut().zip(&s.jobs).enumerate() {
        let needs = match st.phase {
            Phase::Checking => true,
            Phase::Extending => !(st.appended == 0 && st.have_policy_action),
            Phase::Done => false,
        };
        if !needs {
            continue;
        }
        s.act_rows.push(i);
        s.act_obs.extend_from_slice(&s.states[i * od..(i + 1) * od]);
        for _ in 0..ad {
            // The rng is drawn exactly as often, and in the same order, as one replan alone.
            let z = if job.config.sampled {
                job.rng.sample(StandardNormal)
            } else {
                0.0
            };
            s.act_noise.push(z);
        }
    }
    if s.act_rows.is_empty() {
        return;
    }
    crate::nn::resize(&mut s.act_out, s.act_rows.len() * ad);
    nets.act(&s.act_obs, &s.act_noise, &mut s.act_out);
    for (r, &i) in s.act_rows.iter().enumerate() {
        let action = &s.act_out[r * ad..(r + 1) * ad];
        let st = &mut s.jobs[i];
        if !all_finite(action) {
            let index = jobs[i].new.len();
            fail(st, "actor", index);
            continue;
        }
        s.policy_actions[i * ad..(i + 1) * ad].copy_from_slice(action);
    }
}

/// The plan-following test for every job still checking, in one critic call.
fn check_planned_actions<N: Networks, R: Rng>(
    nets: &mut N,
    jobs: &mut [ReplanJob<'_, R>],
    s: &mut ReplanScratch,
) {
    let (od, ad) = (s.obs_dim, s.act_dim);
    s.check_rows.clear();
    s.check_obs.clear();
    s.check_policy.clear();
    s.check_planned.clear();
    for (i, (job, st)) in jobs.iter().zip(&s.jobs).enumerate() {
        if st.phase != Phase::Checking {
            continue;
        }
        s.check_rows.push(i);
        s.check_obs
            .extend_from_slice(&s.states[i * od..(i + 1) * od]);
        s.check_policy
            .extend_from_slice(&s.policy_actions[i * ad..(i + 1) * ad]);
        s.check_planned
            .extend_from_slice(job.old.action(st.checked));
    }
    if s.check_rows.is_empty() {
        return;
    }
    let rows = s.check_rows.len();
    crate::nn::resize(&mut s.q_policy, rows);
    crate::nn::resize(&mut s.q_planned, rows);
    nets.q_pair(
        &s.check_obs,
        &s.check_policy,
        &s.check_planned,
        &mut s.q_policy,
        &mut s.q_planned,
    );
    for (r, &i) in s.check_rows.iter().enumerate() {
        let (q_policy, q_planned) = (s.q_policy[r], s.q_planned[r]);
        let st = &mut s.jobs[i];
        if !q_policy.is_finite() || !q_planned.is_finite() {
            fail(st, "critic", st.checked);
            continue;
        }
        if q_planned + jobs[i].config.epsilon < q_policy {
            st.broke_at = Some(st.checked);
            st.have_policy_action = true;
            start_extending(&jobs[i], st);
        }
    }
}

/// One model step for every job that keeps an old action or appends a policy action.
fn roll_model<N: Networks, R: Rng>(
    nets: &mut N,
    jobs: &mut [ReplanJob<'_, R>],
    s: &mut ReplanScratch,
) {
    let (od, ad) = (s.obs_dim, s.act_dim);
    s.model_rows.clear();
    s.model_obs.clear();
    s.model_actions.clear();
    for (i, (job, st)) in jobs.iter().zip(&s.jobs).enumerate() {
        let action = match st.phase {
            Phase::Checking => job.old.action(st.checked),
            Phase::Extending => &s.policy_actions[i * ad..(i + 1) * ad],
            Phase::Done => continue,
        };
        s.model_rows.push(i);
        s.model_obs
            .extend_from_slice(&s.states[i * od..(i + 1) * od]);
        s.model_actions.extend_from_slice(action);
    }
    if s.model_rows.is_empty() {
        return;
    }
    crate::nn::resize(&mut s.model_next, s.model_rows.len() * od);
    nets.predict_next(&s.model_obs, &s.model_actions, &mut s.model_next);
    for (r, &i) in s.model_rows.iter().enumerate() {
        let next = &s.model_next[r * od..(r + 1) * od];
        let action = &s.model_actions[r * ad..(r + 1) * ad];
        let job = &mut jobs[i];
        let st = &mut s.jobs[i];
        if !all_finite(next) {
            fail(st, "model", job.new.len());
            continue;
        }
        match st.phase {
            Phase::Checking => {
                job.new.push(action, next, job.old.decided_at(st.checked));
                st.checked += 1;
            }
            _ => {
                job.new.push(action, next, job.step);
                st.appended += 1;
                if st.appended == st.wanted {
                    st.phase = Phase::Done;
                }
            }
        }
        s.states[i * od..(i + 1) * od].copy_from_slice(next);
    }
}

#[cfg(test)]
mod tests;
