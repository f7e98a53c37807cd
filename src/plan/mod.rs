//! Replan (Algorithm 2 of the PrAC paper): one pure, seeded function over the three networks,
//! shared by the server and by training. It runs many sessions' replans in lockstep so that each
//! round evaluates the networks once over all of them (cross-session batching); a single replan
//! is a batch of one.
//!
//! Actions inside a plan are in the policy's squashed space [-1, 1]^act_dim, which is what the
//! critics and the model take; the server maps them to the action bounds only when answering.
//!
//! [`reference::reference_replan`] is Algorithm 2 line by line, the version to read next to the
//! paper; [`replan_batch`] is the fast one and must match it bit for bit.

use rand::Rng;
use rand_distr::StandardNormal;

pub mod reference;

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
    /// actions at one state. Where `largest_gap` is given, also per row the largest gap any one
    /// critic sees, `max_c (Q_c(obs, a) - Q_c(obs, b))` (the guard's `every_critic`).
    fn q_pair(
        &mut self,
        obs: &[f32],
        a: &[f32],
        b: &[f32],
        q_a: &mut [f32],
        q_b: &mut [f32],
        largest_gap: Option<&mut [f32]>,
    );
    /// The dynamics model's predictions of the next observations.
    fn predict_next(&mut self, obs: &[f32], actions: &[f32], next_obs: &mut [f32]);
    /// Per row, how far `actions` lie from the policy's Gaussian at `obs`: the largest
    /// [`support_distance`] over the action's dimensions. NaN for an actor without a Gaussian.
    fn policy_distance(&mut self, obs: &[f32], actions: &[f32], distance: &mut [f32]);
    /// [`Networks::act`], and per row the [`Networks::policy_distance`] of `planned` at the same
    /// `obs`, which an actor can take from the same pass.
    fn act_and_distance(
        &mut self,
        obs: &[f32],
        noise: &[f32],
        actions: &mut [f32],
        planned: &[f32],
        distance: &mut [f32],
    ) {
        self.act(obs, noise, actions);
        self.policy_distance(obs, planned, distance);
    }
}

/// The largest squashed action magnitude whose pre-tanh value [`support_distance`] takes; both
/// the action and the mean are clamped to it, so actions at the bounds compare finitely.
const SQUASHED_LIMIT: f32 = 1.0 - f32::EPSILON;

/// How many of the policy's standard deviations the squashed action component `action` lies
/// from the Gaussian's mean `mu` before tanh: `|atanh(a) - mu'| / std` with `a` clamped to
/// +-(1 - 2^-23) and `mu'` to +-atanh(1 - 2^-23).
pub fn support_distance(action: f32, mu: f32, std: f32) -> f32 {
    let pre_limit = SQUASHED_LIMIT.atanh();
    let pre = action.clamp(-SQUASHED_LIMIT, SQUASHED_LIMIT).atanh();
    (pre - mu.clamp(-pre_limit, pre_limit)).abs() / std
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

/// Conditions that also break a plan at an old action `a`, beyond the paper's test. Algorithm 2
/// trusts the critics' aggregate at actions the policy would not take, where a critic errs most;
/// these keep an action only where the critics are on firmer ground. Off by default (the paper).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Guard {
    /// Break where any one critic rates `a` more than eps below pi(s):
    /// `max_c (Q_c(s, pi(s)) - Q_c(s, a)) > eps`.
    #[serde(default)]
    pub every_critic: bool,
    /// Break where `a` lies more than this many of the policy's standard deviations from its
    /// mean at s ([`Networks::policy_distance`]); 0 sets no limit.
    #[serde(default)]
    pub support_limit: f32,
    /// Hold the session's eps to at most this coefficient of the policy's `V_pi - V_rand`,
    /// applied when its options are resolved: past it a bundle's plans may grow no longer while
    /// its robots fall more. 0 sets no limit. Left out of a manifest where 0, so bundles without
    /// it read and hash as before.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub max_epsilon_coef: f64,
}

fn is_zero(value: &f64) -> bool {
    *value == 0.0
}

impl std::fmt::Display for Guard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match (self.every_critic, self.support_limit > 0.0) {
            (true, true) => write!(f, "every critic, support limit {}", self.support_limit)?,
            (true, false) => write!(f, "every critic")?,
            (false, true) => write!(f, "support limit {}", self.support_limit)?,
            (false, false) => write!(f, "the paper's test")?,
        }
        if self.max_epsilon_coef > 0.0 {
            write!(f, ", eps coefficient at most {}", self.max_epsilon_coef)?;
        }
        Ok(())
    }
}

/// Per-session Replan settings, with eps already absolute.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReplanConfig {
    /// Tolerance of the test `Q(s, a) + eps < Q(s, pi(s))`; >= 0.
    pub epsilon: f32,
    pub guard: Guard,
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
            guard: Guard::default(),
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

/// A committed plan and the buffer its next replan writes into, so a failed replan leaves the
/// commitment as it was: the bookkeeping the server's sessions, training-with-PrAC and
/// `prac render` share.
#[derive(Clone, Debug)]
pub(crate) struct Commitment {
    plan: Plan,
    spare: Plan,
}

impl Commitment {
    pub(crate) fn with_capacity(obs_dim: usize, act_dim: usize, capacity: usize) -> Commitment {
        Commitment {
            plan: Plan::with_capacity(obs_dim, act_dim, capacity),
            spare: Plan::with_capacity(obs_dim, act_dim, capacity),
        }
    }

    /// The committed plan: action(0) is the action of the last replanned step.
    pub(crate) fn plan(&self) -> &Plan {
        &self.plan
    }

    /// The committed plan, to adjust in place after a commit.
    pub(crate) fn plan_mut(&mut self) -> &mut Plan {
        &mut self.plan
    }

    /// Takes over a plan committed elsewhere (a resumed session).
    pub(crate) fn replace(&mut self, plan: Plan) {
        self.plan = plan;
    }

    /// Forgets the commitment (a new episode starts from nothing).
    pub(crate) fn clear(&mut self) {
        self.plan.clear();
    }

    /// What the next step's replan checks and where it writes: the commitment after its first
    /// (executed) action, or nothing when `fresh` (an episode's first step), and the spare plan.
    pub(crate) fn next_replan(&mut self, fresh: bool) -> (PlanView<'_>, &mut Plan) {
        let old = if fresh || self.plan.is_empty() {
            PlanView::empty()
        } else {
            self.plan.tail(1)
        };
        (old, &mut self.spare)
    }

    /// Makes the plan the last replan wrote the commitment.
    pub(crate) fn commit(&mut self) {
        std::mem::swap(&mut self.plan, &mut self.spare);
    }

    /// Takes back the last [`Commitment::commit`] (before any other replan): the commitment is
    /// the plan it replaced.
    pub(crate) fn uncommit(&mut self) {
        std::mem::swap(&mut self.plan, &mut self.spare);
    }

    /// The paper's forecast `f_t = t + 1 - i` of the committed first action, executed at step
    /// `t` and decided at step `i`.
    pub(crate) fn forecast(&self, t: u64) -> u64 {
        t + 1 - self.plan.decided_at(0)
    }
}

/// One session's PrAC without a server: a commitment replanned at each observed state, with its
/// settings, buffers and rng. Training-with-PrAC, `prac render` and `prac bench-replan` drive
/// their robots with it; the server's sessions add what serving needs around a `Commitment`.
#[derive(Clone, Debug)]
pub struct Planner<R> {
    pub(crate) config: ReplanConfig,
    commitment: Commitment,
    scratch: ReplanScratch,
    rng: R,
}

impl<R: Rng + Clone> Planner<R> {
    pub fn new(config: ReplanConfig, obs_dim: usize, act_dim: usize, rng: R) -> Planner<R> {
        Planner {
            config,
            commitment: Commitment::with_capacity(obs_dim, act_dim, config.max_horizon + 1),
            scratch: ReplanScratch::new(obs_dim, act_dim),
            rng,
        }
    }

    /// Replans at `state`, observed at `step` of the episode (0 starts a new one), and commits
    /// the new plan; on an error the commitment stays as it was. The action to execute is the
    /// plan's first.
    pub fn replan<N: Networks>(
        &mut self,
        nets: &mut N,
        state: &[f32],
        step: u64,
    ) -> Result<ReplanOutcome, NonFinite> {
        let (old, new) = self.commitment.next_replan(step == 0);
        let job = ReplanJob {
            config: self.config,
            state,
            step,
            old,
            new,
            rng: &mut self.rng,
        };
        let outcome = replan(nets, job, &mut self.scratch)?;
        self.commitment.commit();
        Ok(outcome)
    }

    /// The committed plan: action(0) is the one to execute now.
    pub fn plan(&self) -> &Plan {
        self.commitment.plan()
    }

    /// The forecast f_t of the action executed at `step` (see `Commitment::forecast`).
    pub fn forecast(&self, step: u64) -> u64 {
        self.commitment.forecast(step)
    }

    /// Forgets the commitment.
    pub fn clear(&mut self) {
        self.commitment.clear();
    }
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
    pub(crate) fn clear(&mut self) {
        self.actions.clear();
        self.next_obs.clear();
        self.decided_at.clear();
    }
    pub(crate) fn push(&mut self, action: &[f32], next_obs: &[f32], decided_at: u64) {
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
    /// Every action of the plan, entry after entry.
    pub(crate) fn actions_mut(&mut self) -> &mut [f32] {
        &mut self.actions
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
    pub(crate) fn empty() -> PlanView<'static> {
        PlanView {
            act_dim: 0,
            obs_dim: 0,
            actions: &[],
            next_obs: &[],
            decided_at: &[],
        }
    }
    pub(crate) fn len(&self) -> usize {
        self.decided_at.len()
    }
    #[cfg(test)]
    pub(crate) fn is_empty(&self) -> bool {
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
    pub(crate) appended: usize,
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
    /// Testing old actions from `checked` on.
    Checking,
    /// Appending policy actions, `appended` of `wanted` so far.
    Extending,
    Done,
}

/// Old actions tested together in a job's first round; the chunk doubles each round. Testing
/// ahead needs only the model's rollout over the old actions, so the actor and critics see the
/// chunk as one batch; work past a break is wasted. 8 covers a trained policy's usual plan (about
/// 6 old actions per step for Hopper at coefficient 0.005) in one round.
const FIRST_CHUNK: usize = 8;
/// The largest chunk.
pub const MAX_CHUNK: usize = 32;
/// The most states one session puts in one network call: a chunk of old actions and the state
/// after it (whose pi opens the extension when the chunk is kept whole). An evaluator sized for
/// this many rows per session never grows.
pub const MAX_ROWS_PER_SESSION: usize = MAX_CHUNK + 1;

#[derive(Clone, Debug)]
struct JobState {
    phase: Phase,
    checked: usize,
    limit: usize,
    broke_at: Option<usize>,
    wanted: usize,
    appended: usize,
    /// pi(s) at the breaking state, or at the state after a plan kept whole, is drawn already
    /// and opens the extension.
    have_policy_action: bool,
    /// This round's actor call also draws pi at the state after the chunk: the chunk ends the
    /// old plan, so if every action in it is kept, that is the extension's first action.
    policy_after_chunk: bool,
    error: Option<NonFinite>,
    /// Size of the next chunk of old actions to test.
    chunk: usize,
    /// This round: old actions under test, their first row in the chunk buffers, and how many
    /// rollout states are finite (the model may fail part-way).
    testing: usize,
    first_row: usize,
    finite_states: usize,
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
    /// Per tested old action (rows grouped by job): the rollout state before it, and one more
    /// state per job after its chunk.
    chunk_states: Vec<f32>,
    chunk_policy: Vec<f32>,
    /// Gathered rows of this round's network calls, and which job (or chunk row) each is.
    rows: Vec<usize>,
    obs: Vec<f32>,
    noise: Vec<f32>,
    actions: Vec<f32>,
    out: Vec<f32>,
    q_policy: Vec<f32>,
    q_planned: Vec<f32>,
    /// Per tested old action, for guarded jobs: the largest one-critic gap; per chunk row, the
    /// old action's distance from the policy (drawn with the policy's actions), and per row of
    /// that actor call.
    largest_gap: Vec<f32>,
    chunk_distance: Vec<f32>,
    distance: Vec<f32>,
}

impl ReplanScratch {
    /// Scratch for one session: it fits a batch of one from the start.
    pub fn new(obs_dim: usize, act_dim: usize) -> ReplanScratch {
        ReplanScratch::with_capacity(obs_dim, act_dim, 1)
    }

    /// Scratch whose buffers fit batches of up to `jobs` sessions without growing.
    pub fn with_capacity(obs_dim: usize, act_dim: usize, jobs: usize) -> ReplanScratch {
        let rows = jobs * MAX_ROWS_PER_SESSION;
        ReplanScratch {
            obs_dim,
            act_dim,
            jobs: Vec::with_capacity(jobs),
            states: Vec::with_capacity(jobs * obs_dim),
            policy_actions: Vec::with_capacity(jobs * act_dim),
            chunk_states: Vec::with_capacity(rows * obs_dim),
            chunk_policy: Vec::with_capacity(rows * act_dim),
            rows: Vec::with_capacity(rows),
            obs: Vec::with_capacity(rows * obs_dim),
            noise: Vec::with_capacity(rows * act_dim),
            actions: Vec::with_capacity(rows * act_dim),
            out: Vec::with_capacity(rows * obs_dim.max(act_dim)),
            q_policy: Vec::with_capacity(rows),
            q_planned: Vec::with_capacity(rows),
            largest_gap: Vec::with_capacity(rows),
            chunk_distance: Vec::with_capacity(rows),
            distance: Vec::with_capacity(rows),
        }
    }
}

fn all_finite(values: &[f32]) -> bool {
    values.iter().all(|v| v.is_finite())
}

/// Algorithm 2 for one session: checks the old plan action by action from the observed state,
/// keeping actions while `Q(s, a) + eps >= Q(s, pi(s))` and rolling the model forward over them,
/// then extends the plan with policy actions decided at the job's step. Writes the new plan into
/// `job.new`; reads nothing but its arguments, so the same inputs and rng state give the same
/// plan. [`reference::reference_replan`] is the same algorithm written as the paper writes it.
///
/// The old plan is checked up to `max_horizon` actions; the new plan never exceeds `max_horizon`
/// and is never empty. A non-finite network output is an error; `job.new` is then unusable.
pub(crate) fn replan<N: Networks, R: Rng + Clone>(
    nets: &mut N,
    job: ReplanJob<'_, R>,
    scratch: &mut ReplanScratch,
) -> Result<ReplanOutcome, NonFinite> {
    let mut jobs = [job];
    let mut results = [Ok(ReplanOutcome {
        kept: 0,
        broke_at: None,
        appended: 0,
    })];
    replan_batch(nets, &mut jobs, scratch, &mut results);
    let [result] = results;
    result
}

/// `replan` for many sessions of one policy at once, with the same result for each as alone:
/// every round evaluates the actor, the critics and the model over all sessions that need them.
/// Old actions are tested in chunks (the model's rollout over them first, then one actor and
/// one critic evaluation for the whole chunk); the outcome, the plan and the rng draws are those
/// of testing one action at a time. `results[i]` receives job i's outcome.
pub fn replan_batch<N: Networks, R: Rng + Clone>(
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
            policy_after_chunk: false,
            error: None,
            chunk: FIRST_CHUNK,
            testing: 0,
            first_row: 0,
            finite_states: 0,
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
        roll_chunks(nets, jobs, scratch);
        draw_policy_actions(nets, jobs, scratch);
        test_chunks(nets, jobs, scratch);
        extend(nets, jobs, scratch);
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

/// How many policy actions a plan of `kept` old actions is extended by.
fn wanted_after(config: &ReplanConfig, kept: usize) -> usize {
    let max_horizon = config.max_horizon.max(1);
    let wanted = match config.growth {
        Growth::Grow(k) => k.max(1),
        Growth::Fixed(n) => n.max(1).saturating_sub(kept),
    };
    wanted.min(max_horizon.saturating_sub(kept))
}

fn start_extending<R>(job: &ReplanJob<'_, R>, st: &mut JobState) {
    st.wanted = wanted_after(&job.config, job.new.len());
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

/// The model's rollout over each checking job's next chunk of old actions, batched across jobs
/// step by step: chunk_states gets s_j, s_j+1, ..., s_j+c for the chunk's c actions.
fn roll_chunks<N: Networks, R>(nets: &mut N, jobs: &[ReplanJob<'_, R>], s: &mut ReplanScratch) {
    let od = s.obs_dim;
    let mut rows = 0;
    let mut longest = 0;
    for st in s.jobs.iter_mut() {
        st.testing = 0;
        if st.phase != Phase::Checking {
            continue;
        }
        st.testing = (st.limit - st.checked).min(st.chunk);
        st.chunk = (st.chunk * 2).min(MAX_CHUNK);
        st.first_row = rows;
        st.finite_states = st.testing + 1;
        rows += st.testing + 1;
        longest = longest.max(st.testing);
    }
    crate::nn::resize(&mut s.chunk_states, rows * od);
    for (i, st) in s.jobs.iter().enumerate() {
        if st.testing > 0 {
            let at = st.first_row * od;
            s.chunk_states[at..at + od].copy_from_slice(&s.states[i * od..(i + 1) * od]);
        }
    }
    for m in 0..longest {
        s.rows.clear();
        s.obs.clear();
        s.actions.clear();
        for (i, (job, st)) in jobs.iter().zip(&s.jobs).enumerate() {
            if m < st.testing && m + 1 < st.finite_states {
                let at = (st.first_row + m) * od;
                s.rows.push(i);
                s.obs.extend_from_slice(&s.chunk_states[at..at + od]);
                s.actions.extend_from_slice(job.old.action(st.checked + m));
            }
        }
        if s.rows.is_empty() {
            break;
        }
        crate::nn::resize(&mut s.out, s.rows.len() * od);
        nets.predict_next(&s.obs, &s.actions, &mut s.out);
        for (r, &i) in s.rows.iter().enumerate() {
            let st = &mut s.jobs[i];
            let next = &s.out[r * od..(r + 1) * od];
            if !all_finite(next) {
                // States past this one are unusable; whether that matters depends on the test.
                st.finite_states = m + 1;
                continue;
            }
            let at = (st.first_row + m + 1) * od;
            s.chunk_states[at..at + od].copy_from_slice(next);
        }
    }
    for (job, st) in jobs.iter().zip(s.jobs.iter_mut()) {
        st.policy_after_chunk = st.testing > 0
            && st.checked + st.testing == st.limit
            && st.finite_states == st.testing + 1
            && wanted_after(&job.config, job.new.len() + st.testing) > 0;
    }
}

/// Rows of the chunk whose states are finite.
fn chunk_rows(st: &JobState) -> usize {
    st.testing.min(st.finite_states)
}

/// pi(s) for every state that needs it this round, in one actor call: the chunk states of
/// checking jobs, with the state after the chunk where it ends the old plan (noise drawn from a
/// copy of the job's rng: only the draws a one-at-a-time test would make are taken from the rng
/// itself, in `test_chunks`), and the current state of extending jobs.
fn draw_policy_actions<N: Networks, R: Rng + Clone>(
    nets: &mut N,
    jobs: &mut [ReplanJob<'_, R>],
    s: &mut ReplanScratch,
) {
    let (od, ad) = (s.obs_dim, s.act_dim);
    s.rows.clear();
    s.obs.clear();
    s.noise.clear();
    // The old actions under test, whose distance from the policy a support limit needs: the
    // same actor pass gives it. Extending rows have none (zeros, their distance unused).
    let support = jobs
        .iter()
        .zip(&s.jobs)
        .any(|(job, st)| st.phase == Phase::Checking && job.config.guard.support_limit > 0.0);
    s.actions.clear();
    for (i, (job, st)) in jobs.iter_mut().zip(&s.jobs).enumerate() {
        match st.phase {
            Phase::Checking => {
                let tested = chunk_rows(st);
                let rows = tested + usize::from(st.policy_after_chunk);
                let at = st.first_row * od;
                s.obs.extend_from_slice(&s.chunk_states[at..at + rows * od]);
                if support {
                    for m in 0..tested {
                        s.actions.extend_from_slice(job.old.action(st.checked + m));
                    }
                    // The state after the chunk has no old action (its distance is unused).
                    s.actions
                        .extend(std::iter::repeat_n(0.0, (rows - tested) * ad));
                }
                let mut ahead = job.rng.clone();
                for _ in 0..rows * ad {
                    s.noise.push(if job.config.sampled {
                        ahead.sample(StandardNormal)
                    } else {
                        0.0
                    });
                }
                s.rows.extend(std::iter::repeat_n(i, rows));
            }
            Phase::Extending if !(st.appended == 0 && st.have_policy_action) => {
                s.obs.extend_from_slice(&s.states[i * od..(i + 1) * od]);
                for _ in 0..ad {
                    s.noise.push(if job.config.sampled {
                        job.rng.sample(StandardNormal)
                    } else {
                        0.0
                    });
                }
                if support {
                    s.actions.extend(std::iter::repeat_n(0.0, ad));
                }
                s.rows.push(i);
            }
            _ => {}
        }
    }
    if s.rows.is_empty() {
        return;
    }
    crate::nn::resize(&mut s.out, s.rows.len() * ad);
    if support {
        crate::nn::resize(&mut s.distance, s.rows.len());
        nets.act_and_distance(&s.obs, &s.noise, &mut s.out, &s.actions, &mut s.distance);
        crate::nn::resize(&mut s.chunk_distance, s.chunk_states.len() / od);
    } else {
        nets.act(&s.obs, &s.noise, &mut s.out);
    }
    crate::nn::resize(&mut s.chunk_policy, s.chunk_states.len() / od * ad);
    let mut r = 0;
    while r < s.rows.len() {
        let i = s.rows[r];
        let st = &mut s.jobs[i];
        if st.phase == Phase::Checking {
            let rows = chunk_rows(st) + usize::from(st.policy_after_chunk);
            let at = st.first_row * ad;
            s.chunk_policy[at..at + rows * ad].copy_from_slice(&s.out[r * ad..(r + rows) * ad]);
            if support {
                s.chunk_distance[st.first_row..st.first_row + rows]
                    .copy_from_slice(&s.distance[r..r + rows]);
            }
            r += rows;
        } else {
            let action = &s.out[r * ad..(r + 1) * ad];
            if all_finite(action) {
                s.policy_actions[i * ad..(i + 1) * ad].copy_from_slice(action);
            } else {
                let index = jobs[i].new.len();
                fail(st, "actor", index);
            }
            r += 1;
        }
    }
}

/// The plan-following test over every checking job's chunk, in one critic call; then each job
/// takes its chunk's actions in order until one fails the test (or a network value is not
/// finite), exactly as testing one at a time would.
fn test_chunks<N: Networks, R: Rng>(
    nets: &mut N,
    jobs: &mut [ReplanJob<'_, R>],
    s: &mut ReplanScratch,
) {
    let (od, ad) = (s.obs_dim, s.act_dim);
    s.obs.clear();
    s.actions.clear();
    s.noise.clear();
    let mut rows = 0;
    for (job, st) in jobs.iter().zip(&s.jobs) {
        if st.phase != Phase::Checking {
            continue;
        }
        let count = chunk_rows(st);
        s.obs
            .extend_from_slice(&s.chunk_states[st.first_row * od..(st.first_row + count) * od]);
        s.noise
            .extend_from_slice(&s.chunk_policy[st.first_row * ad..(st.first_row + count) * ad]);
        for m in 0..count {
            s.actions.extend_from_slice(job.old.action(st.checked + m));
        }
        rows += count;
    }
    if rows == 0 {
        return;
    }
    crate::nn::resize(&mut s.q_policy, rows);
    crate::nn::resize(&mut s.q_planned, rows);
    let every_critic = jobs
        .iter()
        .zip(&s.jobs)
        .any(|(job, st)| st.phase == Phase::Checking && job.config.guard.every_critic);
    // `noise` holds the policy's actions here (a reused buffer).
    if every_critic {
        crate::nn::resize(&mut s.largest_gap, rows);
    }
    nets.q_pair(
        &s.obs,
        &s.noise,
        &s.actions,
        &mut s.q_policy,
        &mut s.q_planned,
        every_critic.then_some(&mut s.largest_gap[..]),
    );
    let mut row = 0;
    for (i, (job, st)) in jobs.iter_mut().zip(s.jobs.iter_mut()).enumerate() {
        if st.phase != Phase::Checking {
            continue;
        }
        let count = chunk_rows(st);
        let base = row;
        row += count;
        let mut used = 0;
        for m in 0..st.testing {
            let j = st.checked;
            let state_row = st.first_row + m;
            used += 1;
            if m >= count {
                // The rollout failed before this state: the last kept action's model step.
                fail(st, "model", j);
                break;
            }
            let pi = &s.chunk_policy[state_row * ad..(state_row + 1) * ad];
            if !all_finite(pi) {
                fail(st, "actor", j);
                break;
            }
            let (q_policy, q_planned) = (s.q_policy[base + m], s.q_planned[base + m]);
            if !q_policy.is_finite() || !q_planned.is_finite() {
                fail(st, "critic", j);
                break;
            }
            let (guard, epsilon) = (job.config.guard, job.config.epsilon);
            let largest_gap = if guard.every_critic {
                s.largest_gap[base + m]
            } else {
                0.0
            };
            if !largest_gap.is_finite() {
                fail(st, "critic", j);
                break;
            }
            let distance = if guard.support_limit > 0.0 {
                s.chunk_distance[state_row]
            } else {
                0.0
            };
            if !distance.is_finite() {
                fail(st, "actor", j);
                break;
            }
            let state = &s.chunk_states[state_row * od..(state_row + 1) * od];
            if q_planned + epsilon < q_policy
                || (guard.every_critic && largest_gap > epsilon)
                || (guard.support_limit > 0.0 && distance > guard.support_limit)
            {
                st.broke_at = Some(j);
                st.have_policy_action = true;
                s.states[i * od..(i + 1) * od].copy_from_slice(state);
                s.policy_actions[i * ad..(i + 1) * ad].copy_from_slice(pi);
                start_extending(job, st);
                break;
            }
            let next_row = state_row + 1;
            if m + 1 >= st.finite_states {
                fail(st, "model", j);
                break;
            }
            let next = &s.chunk_states[next_row * od..(next_row + 1) * od];
            job.new.push(job.old.action(j), next, job.old.decided_at(j));
            s.states[i * od..(i + 1) * od].copy_from_slice(next);
            st.checked += 1;
        }
        if st.policy_after_chunk && st.phase == Phase::Checking && st.checked == st.limit {
            // The whole old plan was kept: pi at the state after it opens the extension, drawn
            // with the next draws, as the extension would have drawn it.
            used += 1;
            let row = st.first_row + st.testing;
            let pi = &s.chunk_policy[row * ad..(row + 1) * ad];
            if all_finite(pi) {
                st.have_policy_action = true;
                s.policy_actions[i * ad..(i + 1) * ad].copy_from_slice(pi);
                // As after a break: this round's `extend` appends it.
                start_extending(job, st);
            } else {
                fail(st, "actor", job.new.len());
            }
        }
        if job.config.sampled {
            // Take from the rng the draws one-at-a-time testing would have taken.
            for _ in 0..used * ad {
                let _: f32 = job.rng.sample(StandardNormal);
            }
        }
    }
}

/// One appended policy action for every extending job: the model's step from its state.
fn extend<N: Networks, R>(nets: &mut N, jobs: &mut [ReplanJob<'_, R>], s: &mut ReplanScratch) {
    let (od, ad) = (s.obs_dim, s.act_dim);
    s.rows.clear();
    s.obs.clear();
    s.actions.clear();
    for (i, st) in s.jobs.iter().enumerate() {
        if st.phase == Phase::Extending {
            s.rows.push(i);
            s.obs.extend_from_slice(&s.states[i * od..(i + 1) * od]);
            s.actions
                .extend_from_slice(&s.policy_actions[i * ad..(i + 1) * ad]);
        }
    }
    if s.rows.is_empty() {
        return;
    }
    crate::nn::resize(&mut s.out, s.rows.len() * od);
    nets.predict_next(&s.obs, &s.actions, &mut s.out);
    for (r, &i) in s.rows.iter().enumerate() {
        let next = &s.out[r * od..(r + 1) * od];
        let action = &s.actions[r * ad..(r + 1) * ad];
        let job = &mut jobs[i];
        let st = &mut s.jobs[i];
        if !all_finite(next) {
            fail(st, "model", job.new.len());
            continue;
        }
        job.new.push(action, next, job.step);
        st.appended += 1;
        if st.appended == st.wanted {
            st.phase = Phase::Done;
        }
        s.states[i * od..(i + 1) * od].copy_from_slice(next);
    }
}

#[cfg(test)]
mod tests;
