//! Per-client sessions: the imagined plan, its rng and buffers, and the store that caps, looks up,
//! closes and evicts them.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, SystemTime};

// tokio's clock, so that tests can pause and advance it.
use tokio::time::Instant;

use rand::{RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;
use smallvec::SmallVec;
use tokio::sync::watch;

use super::arrival::Arrival;
use crate::plan::{
    Commitment, DEFAULT_MAX_HORIZON, Growth, NonFinite, Plan, ReplanConfig, ReplanJob,
    ReplanOutcome, ReplanScratch, replan_batch,
};
use crate::policy::{Evaluator, Policy};
use crate::proto;

/// Largest step index or episode counter a resumed plan may carry: 2^53 - 1, the largest integer
/// every client (a JSON number, a Python float) holds exactly. Counting on from it cannot wrap.
pub(crate) const MAX_COUNTER: u64 = (1 << 53) - 1;

/// Resolved per-session options.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SessionSettings {
    pub replan: ReplanConfig,
    pub seed: u64,
}

impl SessionSettings {
    /// Fills defaults into the client's options and checks them against the policy and limit.
    pub fn resolve(
        options: Option<&proto::SessionOptions>,
        policy: &Policy,
        max_horizon_limit: usize,
    ) -> Result<SessionSettings, String> {
        use proto::session_options::{Growth as G, Tolerance};
        let default = proto::SessionOptions::default();
        let options = options.unwrap_or(&default);
        let epsilon = match options.tolerance {
            None => 0.0,
            Some(Tolerance::Epsilon(e)) => {
                if !(e.is_finite() && e >= 0.0) {
                    return Err(format!("epsilon is {e}; expected a finite value >= 0"));
                }
                e
            }
            Some(Tolerance::EpsilonCoef(c)) => {
                if !(c.is_finite() && c >= 0.0) {
                    return Err(format!("epsilon_coef is {c}; expected a finite value >= 0"));
                }
                let Some(scale) = policy.manifest.value_scale else {
                    return Err(format!(
                        "epsilon_coef needs the policy's value scale, and bundle '{}' has none; \
                         give an absolute epsilon instead",
                        policy.manifest.name
                    ));
                };
                let range = scale.v_pi - scale.v_rand;
                if range <= 0.0 {
                    return Err(format!(
                        "epsilon_coef needs V_pi > V_rand, but the bundle has V_pi = {} and \
                         V_rand = {}; give an absolute epsilon instead",
                        scale.v_pi, scale.v_rand
                    ));
                }
                c * range
            }
        };
        // A finite tolerance always: coef x range can still overflow (or be 0 x inf).
        if !(epsilon.is_finite() && epsilon <= f32::MAX as f64) {
            return Err(format!(
                "epsilon {epsilon} is not a finite f32; give a smaller epsilon or epsilon_coef"
            ));
        }
        let check_count = |what: &str, n: u32| -> Result<usize, String> {
            if n == 0 || n as usize > max_horizon_limit {
                Err(format!(
                    "{what} is {n}; expected 1..={max_horizon_limit} (the server's horizon limit)"
                ))
            } else {
                Ok(n as usize)
            }
        };
        let growth = match options.growth {
            None => Growth::default(),
            Some(G::Grow(k)) => Growth::Grow(check_count("grow", k)?),
            Some(G::Fixed(n)) => Growth::Fixed(check_count("fixed", n)?),
        };
        let max_horizon = match (options.max_horizon, growth) {
            (0, Growth::Fixed(n)) => n.max(DEFAULT_MAX_HORIZON.min(max_horizon_limit)),
            (0, _) => DEFAULT_MAX_HORIZON.min(max_horizon_limit),
            (h, _) => check_count("max_horizon", h)?,
        };
        if let Growth::Fixed(n) = growth
            && n > max_horizon
        {
            return Err(format!(
                "fixed {n} is longer than max_horizon {max_horizon}; raise max_horizon or lower n"
            ));
        }
        if options.sampled && !policy.actor.samples() {
            return Err(format!(
                "sampled actions need a distribution to sample, and bundle '{}' has a {} actor, \
                 which acts deterministically; leave sampled off",
                policy.manifest.name,
                policy.manifest.actor.kind.as_str()
            ));
        }
        Ok(SessionSettings {
            replan: ReplanConfig {
                epsilon: epsilon as f32,
                growth,
                max_horizon,
                sampled: options.sampled,
            },
            seed: options.seed,
        })
    }

    pub fn to_proto(self) -> proto::ResolvedOptions {
        let (mode, n) = match self.replan.growth {
            Growth::Grow(k) => ("grow", k),
            Growth::Fixed(n) => ("fixed", n),
        };
        proto::ResolvedOptions {
            epsilon: self.replan.epsilon as f64,
            growth_mode: mode.to_string(),
            growth: n as u32,
            max_horizon: self.replan.max_horizon as u32,
            sampled: self.replan.sampled,
            seed: self.seed,
        }
    }
}

/// A step request the session cannot serve; the session is unchanged.
#[derive(Debug, thiserror::Error)]
pub enum StepError {
    #[error("{0}")]
    InvalidObservation(String),
    #[error("observation could not be planned from: {0}; the session's plan is unchanged")]
    NonFinite(#[from] NonFinite),
    #[error(
        "a step of this session that reached the server after this one was applied first; \
         this one changes nothing"
    )]
    OvertakenBy,
}

/// A checked step, before its replan: its index and whether it starts an episode.
#[derive(Clone, Copy, Debug)]
pub struct Begun {
    pub step: u64,
    pub fresh: bool,
    pub arrival: Arrival,
}

/// What one step did, for the response.
#[derive(Clone, Copy, Debug)]
pub struct StepReport {
    pub outcome: ReplanOutcome,
    pub step: u64,
    pub episode: u64,
    pub f_t: u64,
    /// The session's steps served with this one, which names it for [`Session::take_back`].
    pub served: u64,
}

pub struct Session {
    pub id: String,
    /// The caller that opened it (with auth on); only it may use the session.
    pub owner: Option<String>,
    pub policy: Arc<Policy>,
    pub settings: SessionSettings,
    rng: ChaCha8Rng,
    /// The committed plan: its action(0) is the action of step `step`.
    commitment: Commitment,
    /// Step index of plan[0] within the episode; None before the session's first step.
    step: Option<u64>,
    episode: u64,
    steps_served: u64,
    plan_updates: watch::Sender<Arc<proto::Plan>>,
    /// What the last commit replaced, so a step whose answer never left the server is taken back.
    before_last_commit: Option<BeforeCommit>,
    /// The arrival of the last applied step.
    last_arrival: Arrival,
}

/// A session's counters and rng before a commit.
struct BeforeCommit {
    rng: ChaCha8Rng,
    step: Option<u64>,
    episode: u64,
    last_arrival: Arrival,
}

/// One step as its request brings it.
#[derive(Clone, Copy, Debug)]
pub struct StepInput<'a> {
    pub observation: &'a [f32],
    pub new_episode: bool,
    pub arrival: Arrival,
}

/// Algorithm 1, lines 4-10 as a server, for one step of each of `sessions` (all of one policy,
/// each session once): check each step ([`Session::begin`]), replan the plans of those that pass
/// together in one `replan_batch` on the observed states (each old plan minus the action
/// executed at the last step), and commit each result. A session whose step is refused, or
/// whose replan meets a non-finite value, is left exactly as it was.
///
/// The request handler applies a batch of one, which allocates nothing after the session's
/// first step; a batch worker applies many at once.
pub(crate) fn apply_steps(
    sessions: &mut [&mut Session],
    inputs: &[StepInput<'_>],
    evaluator: &mut Evaluator,
    scratch: &mut ReplanScratch,
) -> SmallVec<[Result<StepReport, StepError>; 1]> {
    debug_assert_eq!(sessions.len(), inputs.len());
    debug_assert!(
        sessions
            .iter()
            .all(|s| Arc::ptr_eq(evaluator.policy(), &s.policy))
    );
    let begun: SmallVec<[Result<Begun, StepError>; 1]> = sessions
        .iter()
        .zip(inputs)
        .map(|(s, input)| s.begin(input.observation, input.new_episode, input.arrival))
        .collect();
    // Copies: a failed replan must not advance a session's rng either.
    let mut rngs: SmallVec<[ChaCha8Rng; 1]> = sessions.iter().map(|s| s.rng()).collect();
    let mut results: SmallVec<[Result<ReplanOutcome, NonFinite>; 1]> = SmallVec::new();
    {
        let mut jobs: SmallVec<[ReplanJob<'_, ChaCha8Rng>; 1]> = SmallVec::new();
        for (((session, rng), input), begun) in
            sessions.iter_mut().zip(&mut rngs).zip(inputs).zip(&begun)
        {
            if let Ok(begun) = begun {
                jobs.push(session.job(input.observation, begun, rng));
            }
        }
        results.resize(jobs.len(), Err(NonFinite { what: "", index: 0 }));
        replan_batch(evaluator, &mut jobs, scratch, &mut results);
    }
    let mut results = results.into_iter();
    sessions
        .iter_mut()
        .zip(rngs)
        .zip(begun)
        .map(|((session, rng), begun)| {
            let begun = begun?;
            let outcome = results.next().expect("one result per job")?;
            Ok(session.commit(&begun, outcome, rng))
        })
        .collect()
}

impl Session {
    pub fn new(id: String, policy: Arc<Policy>, settings: SessionSettings) -> Session {
        let (obs, act) = (policy.obs_dim(), policy.act_dim());
        let capacity = settings.replan.max_horizon + 1;
        let (plan_updates, _) = watch::channel(Arc::new(proto::Plan {
            session_id: id.clone(),
            ..Default::default()
        }));
        Session {
            rng: ChaCha8Rng::seed_from_u64(settings.seed),
            commitment: Commitment::with_capacity(obs, act, capacity),
            step: None,
            episode: 0,
            steps_served: 0,
            owner: None,
            id,
            policy,
            settings,
            plan_updates,
            before_last_commit: None,
            last_arrival: Arrival::default(),
        }
    }

    pub fn steps_served(&self) -> u64 {
        self.steps_served
    }

    /// Applies one step (see [`apply_steps`]): the request handler's batch of one. `evaluator`
    /// (for this session's policy) and `scratch` may be shared by sessions served from one
    /// thread; sized with [`Evaluator::for_sessions`] they never grow.
    pub fn apply_step(
        &mut self,
        evaluator: &mut Evaluator,
        scratch: &mut ReplanScratch,
        input: StepInput<'_>,
    ) -> Result<StepReport, StepError> {
        apply_steps(&mut [self], &[input], evaluator, scratch)
            .pop()
            .expect("one result per session")
    }

    /// Checks the observation and the step's arrival, and works out the step index; changes
    /// nothing. A step that arrived before the last applied one is refused: its caller sent a
    /// later step meanwhile (it gave up on this one, or sent both at once).
    pub fn begin(
        &self,
        observation: &[f32],
        new_episode: bool,
        arrival: Arrival,
    ) -> Result<Begun, StepError> {
        if arrival < self.last_arrival {
            return Err(StepError::OvertakenBy);
        }
        let obs_dim = self.policy.obs_dim();
        if observation.len() != obs_dim {
            return Err(StepError::InvalidObservation(format!(
                "observation has {} values; policy '{}' expects obs_dim = {obs_dim}",
                observation.len(),
                self.policy.manifest.name
            )));
        }
        if let Some(i) = observation.iter().position(|v| !v.is_finite()) {
            return Err(StepError::InvalidObservation(format!(
                "observation[{i}] is {}; every value must be finite",
                observation[i]
            )));
        }
        let fresh = new_episode || self.step.is_none();
        let step = match self.step {
            // Resumed counters are bounded by MAX_COUNTER, so this cannot wrap.
            Some(prev) if !fresh => prev + 1,
            _ => 0,
        };
        Ok(Begun {
            step,
            fresh,
            arrival,
        })
    }

    /// The Replan job of this step: the new plan goes to the spare buffer, so a failed replan
    /// leaves the committed plan as it was. `rng` is a copy of the session's, kept on commit.
    pub fn job<'a>(
        &'a mut self,
        observation: &'a [f32],
        begun: &Begun,
        rng: &'a mut ChaCha8Rng,
    ) -> ReplanJob<'a, ChaCha8Rng> {
        let (old, new) = self.commitment.next_replan(begun.fresh);
        ReplanJob {
            config: self.settings.replan,
            state: observation,
            step: begun.step,
            old,
            new,
            rng,
        }
    }

    /// Makes the replanned plan the committed one.
    pub fn commit(&mut self, begun: &Begun, outcome: ReplanOutcome, rng: ChaCha8Rng) -> StepReport {
        self.before_last_commit = Some(BeforeCommit {
            rng: std::mem::replace(&mut self.rng, rng),
            step: self.step,
            episode: self.episode,
            last_arrival: self.last_arrival,
        });
        self.last_arrival = begun.arrival;
        self.commitment.commit();
        // The client sees its plan in the action bounds: the plan keeps only actions that come
        // back from there unchanged, so a plan resumed from what the client holds is this one.
        self.policy
            .make_actions_round_trip(self.commitment.plan_mut().actions_mut());
        if begun.fresh && self.step.is_some() {
            self.episode += 1;
        }
        let t = begun.step;
        self.step = Some(t);
        self.steps_served += 1;
        if self.plan_updates.receiver_count() > 0 {
            self.plan_updates.send_replace(Arc::new(self.plan_proto()));
        }
        StepReport {
            outcome,
            step: t,
            episode: self.episode,
            f_t: self.commitment.forecast(t),
            served: self.steps_served,
        }
    }

    /// Takes back the step that made `steps_served` reach `served`, if it is still the last one:
    /// its answer never reached the client (the caller gave up or its stream is gone), and a
    /// step the client was not answered must change nothing.
    pub fn take_back(&mut self, served: u64) -> bool {
        if self.steps_served != served {
            return false;
        }
        let Some(before) = self.before_last_commit.take() else {
            return false;
        };
        self.commitment.uncommit();
        self.rng = before.rng;
        self.step = before.step;
        self.episode = before.episode;
        self.last_arrival = before.last_arrival;
        self.steps_served -= 1;
        if self.plan_updates.receiver_count() > 0 {
            self.plan_updates.send_replace(Arc::new(self.plan_proto()));
        }
        true
    }

    /// Takes over a plan committed elsewhere (`OpenSession` with `resume`): `plan.actions[0]` was
    /// executed at step `plan.start_step` and the rest is the commitment. Checked here for shape
    /// and sanity only; whether each action is still worth keeping is Replan's test at the next
    /// step. Predicted observations are not trusted: Replan rolls the model again.
    pub fn resume(&mut self, plan: &proto::Plan) -> Result<(), String> {
        let (od, ad) = (self.policy.obs_dim(), self.policy.act_dim());
        let limit = self.settings.replan.max_horizon;
        if plan.actions.is_empty() {
            return Err("the resumed plan has no actions; omit resume to start afresh".into());
        }
        for (field, value) in [("start_step", plan.start_step), ("episode", plan.episode)] {
            if value > MAX_COUNTER {
                return Err(format!(
                    "resume.{field} is {value}; a resumed counter is at most {MAX_COUNTER} (2^53 \
                     - 1), so that steps and episodes never wrap"
                ));
            }
        }
        if plan.actions.len() > limit {
            return Err(format!(
                "the resumed plan has {} actions; the session's max_horizon is {limit}",
                plan.actions.len()
            ));
        }
        let (lo, hi) = (
            &self.policy.manifest.action_low,
            &self.policy.manifest.action_high,
        );
        let mut squashed = vec![0.0; ad];
        let mut resumed = Plan::with_capacity(od, ad, limit + 1);
        for (j, entry) in plan.actions.iter().enumerate() {
            if entry.action.len() != ad {
                return Err(format!(
                    "resume.actions[{j}] has {} values; policy '{}' expects act_dim = {ad}",
                    entry.action.len(),
                    self.policy.manifest.name
                ));
            }
            for (i, &a) in entry.action.iter().enumerate() {
                if !(a.is_finite() && a >= lo[i] && a <= hi[i]) {
                    return Err(format!(
                        "resume.actions[{j}].action[{i}] is {a}; expected a finite value in [{}, {}]",
                        lo[i], hi[i]
                    ));
                }
            }
            if entry.decided_at > plan.start_step {
                return Err(format!(
                    "resume.actions[{j}] was decided at step {}, after the plan's start_step {}",
                    entry.decided_at, plan.start_step
                ));
            }
            self.policy.scale_action(&entry.action, &mut squashed);
            for v in &mut squashed {
                *v = v.clamp(-1.0, 1.0);
            }
            resumed.push(&squashed, &vec![f32::NAN; od], entry.decided_at);
        }
        // Keep the spare's capacity for the allocation-free steps that follow.
        self.commitment.replace(resumed);
        self.before_last_commit = None;
        self.step = Some(plan.start_step);
        self.episode = plan.episode;
        Ok(())
    }

    /// A copy of the session's rng, for a job (kept only if the step commits).
    pub fn rng(&self) -> ChaCha8Rng {
        self.rng.clone()
    }

    fn planned_actions(&self) -> Vec<proto::PlannedAction> {
        let plan = self.commitment.plan();
        (0..plan.len())
            .map(|j| {
                let mut action = vec![0.0; self.policy.act_dim()];
                self.policy.unscale_action(plan.action(j), &mut action);
                proto::PlannedAction {
                    action,
                    // Unknown (empty) for a resumed plan until its first replan.
                    predicted_observation: if plan.next_obs(j).iter().all(|v| v.is_finite()) {
                        plan.next_obs(j).to_vec()
                    } else {
                        Vec::new()
                    },
                    decided_at: plan.decided_at(j),
                }
            })
            .collect()
    }

    pub fn response(&self, report: &StepReport) -> proto::StepResponse {
        let forecast = self.planned_actions();
        proto::StepResponse {
            action: forecast[0].action.clone(),
            forecast,
            kept: report.outcome.kept as u32,
            broke_at: report.outcome.broke_at.map(|i| i as u32),
            f_t: report.f_t,
            step: report.step,
            episode: report.episode,
        }
    }

    /// The committed plan (empty before the first step).
    pub fn plan_proto(&self) -> proto::Plan {
        proto::Plan {
            session_id: self.id.clone(),
            episode: self.episode,
            start_step: self.step.unwrap_or(0),
            actions: self.planned_actions(),
        }
    }

    /// A receiver of every later plan change.
    pub fn watch(&self) -> watch::Receiver<Arc<proto::Plan>> {
        self.plan_updates.subscribe()
    }
}

/// A 128-bit random session id in hex, from the OS-seeded CSPRNG.
pub(crate) fn new_session_id() -> String {
    let mut bytes = [0u8; 16];
    rand::rng().fill_bytes(&mut bytes);
    hex::encode(bytes)
}

/// Why a session lookup failed.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    #[error("unknown session '{0}'; open one with OpenSession")]
    NotFound(String),
    #[error("session '{id}' was closed at {at}; open a new one with OpenSession")]
    Closed { id: String, at: String },
    #[error(
        "session '{id}' expired at {at} after {idle_secs:.1} s idle (the server's session TTL is \
         {ttl}); open a new one with OpenSession"
    )]
    Expired {
        id: String,
        at: String,
        idle_secs: f64,
        ttl: String,
    },
    #[error("the server holds its maximum of {0} sessions; close one or retry later")]
    CapReached(usize),
    #[error("session '{0}' belongs to another client")]
    NotOwner(String),
}

pub(crate) struct SessionSlot {
    /// The session's policy (also in the session), readable without the lock.
    pub policy: Arc<Policy>,
    pub owner: Option<String>,
    /// Its policy's step counter in the metrics.
    pub steps_served: prometheus_client::metrics::counter::Counter,
    session: Mutex<Session>,
    /// When the session was last used (ms since the store's epoch); idle time starts here.
    last_used_ms: AtomicU64,
    /// Requests using the session now: a session with one in flight never expires.
    in_use: AtomicU64,
}

/// Marks a session in use from [`Sessions::get`] until dropped; then its idle time starts.
pub(crate) struct InUse {
    slot: Arc<SessionSlot>,
    epoch: Instant,
}

impl std::ops::Deref for InUse {
    type Target = Arc<SessionSlot>;
    fn deref(&self) -> &Arc<SessionSlot> {
        &self.slot
    }
}

impl Drop for InUse {
    fn drop(&mut self) {
        // Stamp before releasing, so the evictor never sees it free with an old stamp.
        self.slot
            .last_used_ms
            .store(self.epoch.elapsed().as_millis() as u64, Ordering::SeqCst);
        self.slot.in_use.fetch_sub(1, Ordering::SeqCst);
    }
}

impl SessionSlot {
    /// Locks the session (a panic elsewhere cannot wedge it: poisoning is ignored).
    pub(crate) fn lock(&self) -> MutexGuard<'_, Session> {
        self.session.lock().unwrap_or_else(|p| p.into_inner())
    }
}

#[derive(Clone, Debug)]
enum Ended {
    Closed { at: SystemTime },
    Expired { at: SystemTime, idle: Duration },
}

/// Ids of ended sessions, remembered (up to a bound) so that a late request learns why.
struct Tombstones {
    order: VecDeque<String>,
    ended: HashMap<String, Ended>,
}

/// Ended sessions remembered (about 200 bytes each). Beyond, the oldest is forgotten and a late
/// request for it gets a plain NOT_FOUND. With 65,536, prac-soak's churn (20 sessions/s) grew the
/// server by about 0.5 MB a minute towards a 13 MB plateau; 4,096 reaches its plateau in minutes.
const MAX_TOMBSTONES: usize = 4_096;

/// Stops the evictor of [`Sessions::start`] when dropped, with its store.
struct Evictor(tokio::task::JoinHandle<()>);

impl Drop for Evictor {
    fn drop(&mut self) {
        self.0.abort();
    }
}

pub(crate) struct Sessions {
    slots: Mutex<HashMap<String, Arc<SessionSlot>>>,
    tombstones: Mutex<Tombstones>,
    max_sessions: usize,
    ttl: Duration,
    epoch: Instant,
    /// Set by [`Sessions::start`]: the store's own evictor, which ends when the store does.
    evictor: std::sync::OnceLock<Evictor>,
}

fn rfc3339(t: SystemTime) -> String {
    humantime::format_rfc3339_millis(t).to_string()
}

/// Shortens a client-supplied id for error messages.
fn shown(id: &str) -> String {
    id.chars().take(64).collect()
}

impl Sessions {
    pub(crate) fn new(max_sessions: usize, ttl: Duration) -> Sessions {
        Sessions {
            slots: Mutex::new(HashMap::new()),
            tombstones: Mutex::new(Tombstones {
                order: VecDeque::new(),
                ended: HashMap::new(),
            }),
            max_sessions,
            ttl,
            epoch: Instant::now(),
            evictor: std::sync::OnceLock::new(),
        }
    }

    /// A store that evicts its idle sessions every quarter of the TTL (10 ms to 1 s) for as long
    /// as it lives, telling `on_evicted` how many went each time. Needs a tokio runtime.
    pub(crate) fn start(
        max_sessions: usize,
        ttl: Duration,
        on_evicted: impl Fn(usize) + Send + 'static,
    ) -> Arc<Sessions> {
        let sessions = Arc::new(Sessions::new(max_sessions, ttl));
        let store = Arc::downgrade(&sessions);
        let period = (ttl / 4).clamp(Duration::from_millis(10), Duration::from_secs(1));
        let evictor = Evictor(tokio::spawn(async move {
            let mut tick = tokio::time::interval(period);
            loop {
                tick.tick().await;
                let Some(sessions) = store.upgrade() else {
                    return;
                };
                on_evicted(sessions.evict_idle());
            }
        }));
        let _ = sessions.evictor.set(evictor);
        sessions
    }

    fn now_ms(&self) -> u64 {
        self.epoch.elapsed().as_millis() as u64
    }

    fn slots(&self) -> MutexGuard<'_, HashMap<String, Arc<SessionSlot>>> {
        self.slots.lock().unwrap_or_else(|p| p.into_inner())
    }

    pub(crate) fn len(&self) -> usize {
        self.slots().len()
    }

    pub(crate) fn insert(
        &self,
        session: Session,
        steps_served: prometheus_client::metrics::counter::Counter,
    ) -> Result<(), SessionError> {
        let mut slots = self.slots();
        if slots.len() >= self.max_sessions {
            return Err(SessionError::CapReached(self.max_sessions));
        }
        let id = session.id.clone();
        slots.insert(
            id,
            Arc::new(SessionSlot {
                policy: session.policy.clone(),
                owner: session.owner.clone(),
                steps_served,
                session: Mutex::new(session),
                last_used_ms: AtomicU64::new(self.now_ms()),
                in_use: AtomicU64::new(0),
            }),
        );
        Ok(())
    }

    /// The live session with this id, in use until the guard drops, if `caller` owns it.
    pub(crate) fn get(&self, id: &str, caller: Option<&str>) -> Result<InUse, SessionError> {
        // Marked in use under the map's lock, so the evictor cannot take it in between.
        let slots = self.slots();
        match slots.get(id) {
            Some(slot) if slot.owner.as_deref() != caller => Err(SessionError::NotOwner(shown(id))),
            Some(slot) => {
                slot.in_use.fetch_add(1, Ordering::SeqCst);
                slot.last_used_ms.store(self.now_ms(), Ordering::SeqCst);
                Ok(InUse {
                    slot: slot.clone(),
                    epoch: self.epoch,
                })
            }
            None => {
                drop(slots);
                Err(self.why_missing(id))
            }
        }
    }

    fn why_missing(&self, id: &str) -> SessionError {
        let tombstones = self.tombstones.lock().unwrap_or_else(|p| p.into_inner());
        match tombstones.ended.get(id) {
            Some(Ended::Closed { at }) => SessionError::Closed {
                id: shown(id),
                at: rfc3339(*at),
            },
            Some(Ended::Expired { at, idle }) => SessionError::Expired {
                id: shown(id),
                at: rfc3339(*at),
                idle_secs: idle.as_secs_f64(),
                ttl: humantime::format_duration(self.ttl).to_string(),
            },
            None => SessionError::NotFound(shown(id)),
        }
    }

    fn bury(&self, id: String, ended: Ended) {
        let mut t = self.tombstones.lock().unwrap_or_else(|p| p.into_inner());
        if t.order.len() >= MAX_TOMBSTONES
            && let Some(old) = t.order.pop_front()
        {
            t.ended.remove(&old);
        }
        t.order.push_back(id.clone());
        t.ended.insert(id, ended);
    }

    pub(crate) fn close(
        &self,
        id: &str,
        caller: Option<&str>,
    ) -> Result<Arc<SessionSlot>, SessionError> {
        let removed = {
            let mut slots = self.slots();
            match slots.get(id) {
                Some(slot) if slot.owner.as_deref() != caller => {
                    return Err(SessionError::NotOwner(shown(id)));
                }
                Some(_) => slots.remove(id),
                None => None,
            }
        };
        match removed {
            Some(slot) => {
                self.bury(
                    id.to_string(),
                    Ended::Closed {
                        at: SystemTime::now(),
                    },
                );
                Ok(slot)
            }
            None => Err(self.why_missing(id)),
        }
    }

    /// Removes every session idle for longer than the TTL; returns how many. Idle time starts
    /// when a request ends: a session with a request in flight is never idle.
    pub(crate) fn evict_idle(&self) -> usize {
        let ttl_ms = self.ttl.as_millis() as u64;
        let expired: Vec<(String, u64)> = {
            let mut slots = self.slots();
            let now = self.now_ms();
            let ids: Vec<(String, u64)> = slots
                .iter()
                .filter_map(|(id, slot)| {
                    if slot.in_use.load(Ordering::SeqCst) > 0 {
                        return None;
                    }
                    let idle = now.saturating_sub(slot.last_used_ms.load(Ordering::SeqCst));
                    (idle > ttl_ms).then(|| (id.clone(), idle))
                })
                .collect();
            for (id, _) in &ids {
                slots.remove(id);
            }
            ids
        };
        let at = SystemTime::now();
        for (id, idle_ms) in &expired {
            tracing::info!(session = %id, idle_ms, "session expired");
            self.bury(
                id.clone(),
                Ended::Expired {
                    at,
                    idle: Duration::from_millis(*idle_ms),
                },
            );
        }
        expired.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bundle::ValueScale;
    use crate::testing::test_manifest;

    fn policy() -> Arc<Policy> {
        Arc::new(crate::testing::random_policy(
            test_manifest("toy", "toy", 3, 2, &[16, 16], &[8, 8]),
            5,
        ))
    }

    fn session(policy: &Arc<Policy>, options: proto::SessionOptions) -> Session {
        let settings = SessionSettings::resolve(Some(&options), policy, 256).unwrap();
        Session::new("s".into(), policy.clone(), settings)
    }

    fn step(s: &mut Session, obs: &[f32]) -> proto::StepResponse {
        let mut evaluator = Evaluator::for_sessions(s.policy.clone(), 1);
        let mut scratch = ReplanScratch::new(3, 2);
        let report = s
            .apply_step(
                &mut evaluator,
                &mut scratch,
                StepInput {
                    observation: obs,
                    new_episode: false,
                    arrival: Arrival::next(),
                },
            )
            .unwrap();
        s.response(&report)
    }

    #[test]
    fn a_step_taken_back_changes_nothing() {
        let policy = policy();
        let options = proto::SessionOptions {
            sampled: true,
            seed: 9,
            tolerance: Some(proto::session_options::Tolerance::Epsilon(1e6)),
            ..Default::default()
        };
        let (mut a, mut b) = (session(&policy, options), session(&policy, options));
        step(&mut a, &[0.1, 0.2, 0.3]);
        step(&mut b, &[0.1, 0.2, 0.3]);
        let lost = step(&mut a, &[0.5, 0.5, 0.5]);
        assert!(a.take_back(2));
        // Only the last step, and only once.
        assert!(!a.take_back(2));
        assert!(!a.take_back(1));
        assert_eq!(a.steps_served(), 1);
        let (ra, rb) = (
            step(&mut a, &[0.4, 0.0, 0.1]),
            step(&mut b, &[0.4, 0.0, 0.1]),
        );
        assert_eq!(ra, rb, "the taken-back step left a trace");
        assert_eq!(ra.step, 1);
        assert_ne!(lost.forecast, ra.forecast);
        assert_eq!(a.plan_proto(), b.plan_proto());
    }

    #[test]
    fn a_step_overtaken_by_a_later_arrival_is_refused_and_changes_nothing() {
        let policy = policy();
        let mut s = session(&policy, proto::SessionOptions::default());
        let mut evaluator = Evaluator::for_sessions(policy.clone(), 1);
        let mut scratch = ReplanScratch::new(3, 2);
        let (early, late, later) = (Arrival::next(), Arrival::next(), Arrival::next());
        let obs = [0.1, 0.2, 0.3];
        let mut step = |s: &mut Session, arrival| {
            s.apply_step(
                &mut evaluator,
                &mut scratch,
                StepInput {
                    observation: &obs,
                    new_episode: false,
                    arrival,
                },
            )
        };
        assert_eq!(step(&mut s, late).unwrap().step, 0);
        let plan = s.plan_proto();
        assert!(matches!(step(&mut s, early), Err(StepError::OvertakenBy)));
        assert_eq!(s.plan_proto(), plan);
        assert_eq!(s.steps_served(), 1);
        // A step taken back is as if it never arrived: an earlier one may go after all.
        let served = step(&mut s, later).unwrap().served;
        assert!(s.take_back(served));
        assert_eq!(step(&mut s, late).unwrap().step, 1);
    }

    #[tokio::test(start_paused = true)]
    async fn a_session_in_use_never_expires_and_idles_from_its_last_use() {
        let sessions = Sessions::new(8, Duration::from_millis(30));
        let policy = policy();
        let s = session(&policy, Default::default());
        sessions.insert(s, Default::default()).unwrap();
        let in_use = sessions.get("s", None).unwrap();
        tokio::time::advance(Duration::from_millis(80)).await;
        assert_eq!(sessions.evict_idle(), 0, "evicted while a request used it");
        drop(in_use);
        assert_eq!(
            sessions.evict_idle(),
            0,
            "idle time must start when the request ends"
        );
        tokio::time::advance(Duration::from_millis(80)).await;
        assert_eq!(sessions.evict_idle(), 1);
        assert!(matches!(
            sessions.get("s", None),
            Err(SessionError::Expired { .. })
        ));
    }

    #[test]
    fn resumed_counters_that_could_wrap_are_refused() {
        let policy = policy();
        let plan = |start_step: u64, episode: u64, decided_at: u64| proto::Plan {
            session_id: String::new(),
            episode,
            start_step,
            actions: vec![proto::PlannedAction {
                action: vec![0.0, 0.0],
                predicted_observation: vec![],
                decided_at,
            }],
        };
        for (start, episode, decided) in [
            (u64::MAX, 0, 0),
            (u64::MAX, 0, u64::MAX),
            (0, u64::MAX, 0),
            (MAX_COUNTER + 1, 0, 0),
        ] {
            let mut s = session(&policy, Default::default());
            let e = s.resume(&plan(start, episode, decided)).unwrap_err();
            assert!(e.contains("at most 9007199254740991"), "{e}");
        }
        let mut s = session(&policy, Default::default());
        s.resume(&plan(MAX_COUNTER, MAX_COUNTER, MAX_COUNTER))
            .unwrap();
        let response = step(&mut s, &[0.0; 3]);
        assert_eq!(response.step, MAX_COUNTER + 1);
        assert_eq!(response.episode, MAX_COUNTER);
        assert!(response.f_t >= 1);
    }

    #[test]
    fn options_resolve_as_the_proto_says() {
        use proto::session_options::{Growth as G, Tolerance};
        let policy = policy();
        let resolve =
            |options: proto::SessionOptions| SessionSettings::resolve(Some(&options), &policy, 256);
        // max_horizon 0: 32, or n for fixed n > 32.
        let horizon = |growth, max_horizon| {
            resolve(proto::SessionOptions {
                growth,
                max_horizon,
                ..Default::default()
            })
            .map(|s| s.replan.max_horizon)
        };
        assert_eq!(horizon(None, 0), Ok(32));
        assert_eq!(horizon(Some(G::Fixed(8)), 0), Ok(32));
        assert_eq!(horizon(Some(G::Fixed(40)), 0), Ok(40));
        assert_eq!(horizon(Some(G::Fixed(40)), 40), Ok(40));
        assert!(
            horizon(Some(G::Fixed(40)), 32)
                .unwrap_err()
                .contains("longer than")
        );
        assert!(
            horizon(Some(G::Fixed(300)), 0)
                .unwrap_err()
                .contains("1..=256")
        );

        // A value scale that overflows f32 never yields a non-finite tolerance.
        let mut huge = (*policy).clone();
        huge.manifest.value_scale = Some(ValueScale {
            v_pi: 1.7e308,
            v_rand: -1.7e308,
        });
        for coef in [0.0, 1.0] {
            let e = SessionSettings::resolve(
                Some(&proto::SessionOptions {
                    tolerance: Some(Tolerance::EpsilonCoef(coef)),
                    ..Default::default()
                }),
                &huge,
                256,
            )
            .unwrap_err();
            assert!(e.contains("not a finite f32"), "{coef}: {e}");
        }

        // An actor without a distribution (TD3, DDPG, gSDE) cannot be sampled.
        let sampled = proto::SessionOptions {
            sampled: true,
            ..Default::default()
        };
        assert!(resolve(sampled).is_ok());
        let mut deterministic = (*policy).clone();
        deterministic.manifest.actor.kind = crate::manifest::ActorKind::Deterministic;
        deterministic.actor.log_std = None;
        let e = SessionSettings::resolve(Some(&sampled), &deterministic, 256).unwrap_err();
        assert!(
            e.contains("has a deterministic actor") && e.contains("leave sampled off"),
            "{e}"
        );
        assert!(SessionSettings::resolve(None, &deterministic, 256).is_ok());
    }
}
