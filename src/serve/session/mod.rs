//! Per-client sessions: the imagined plan, its rng and buffers, the one pipeline that applies
//! steps to them, and the store that caps, looks up, closes and evicts them.

use std::sync::Arc;

use rand::{RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;
use smallvec::SmallVec;
use tokio::sync::watch;

use super::arrival::Arrival;
use crate::plan::{
    Commitment, NonFinite, Plan, ReplanJob, ReplanOutcome, ReplanScratch, replan_batch,
};
use crate::policy::{Evaluator, Policy};
use crate::proto;

mod settings;
mod store;
#[cfg(test)]
mod tests;

pub use settings::SessionSettings;
pub(crate) use settings::{MAX_COUNTER, guard_proto};
pub(crate) use store::{SessionError, SessionSlot, Sessions};

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
pub(crate) struct Begun {
    pub(crate) step: u64,
    pub(crate) fresh: bool,
    pub(crate) arrival: Arrival,
}

/// What one step did, for the response.
#[derive(Clone, Copy, Debug)]
pub struct StepReport {
    pub(crate) outcome: ReplanOutcome,
    pub(crate) step: u64,
    pub(crate) episode: u64,
    pub(crate) f_t: u64,
    /// The session's steps served with this one, which names it for [`Session::take_back`].
    pub(crate) served: u64,
}

pub struct Session {
    pub(crate) id: String,
    /// The caller that opened it (with auth on); only it may use the session.
    pub(crate) owner: Option<String>,
    pub(crate) policy: Arc<Policy>,
    pub(crate) settings: SessionSettings,
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
/// executed at the last step), commit each result, and answer it. A session whose step is
/// refused, or whose replan meets a non-finite value, is left exactly as it was.
///
/// `answer(i, session, report)` gets step `i`'s report, still under the session's lock. A caller
/// that holds the lock until its answer is delivered takes back ([`Session::take_back`]) a step
/// whose caller gave up meanwhile, so that nobody ever sees it applied.
///
/// The request handler applies a batch of one, which allocates nothing after the session's
/// first step; a batch worker applies many at once.
pub(crate) fn apply_steps(
    sessions: &mut [&mut Session],
    inputs: &[StepInput<'_>],
    evaluator: &mut Evaluator,
    scratch: &mut ReplanScratch,
    mut answer: impl FnMut(usize, &Session, Result<StepReport, StepError>),
) {
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
    for (i, ((session, rng), begun)) in sessions.iter_mut().zip(rngs).zip(begun).enumerate() {
        let report = begun.and_then(|begun| {
            let outcome = results.next().expect("one result per job")?;
            Ok(session.commit(&begun, outcome, rng))
        });
        answer(i, session, report);
    }
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

    pub(crate) fn steps_served(&self) -> u64 {
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
        let mut answered = None;
        apply_steps(&mut [self], &[input], evaluator, scratch, |_, _, report| {
            answered = Some(report);
        });
        answered.expect("one answer per step")
    }

    /// Checks the observation and the step's arrival, and works out the step index; changes
    /// nothing. A step that arrived before the last applied one is refused: its caller sent a
    /// later step meanwhile (it gave up on this one, or sent both at once).
    pub(crate) fn begin(
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
    pub(crate) fn job<'a>(
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
    pub(crate) fn commit(
        &mut self,
        begun: &Begun,
        outcome: ReplanOutcome,
        rng: ChaCha8Rng,
    ) -> StepReport {
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
    pub(crate) fn take_back(&mut self, served: u64) -> bool {
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
    pub(crate) fn resume(&mut self, plan: &proto::Plan) -> Result<(), String> {
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
    pub(crate) fn rng(&self) -> ChaCha8Rng {
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

    pub(crate) fn response(&self, report: &StepReport) -> proto::StepResponse {
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
    pub(crate) fn plan_proto(&self) -> proto::Plan {
        proto::Plan {
            session_id: self.id.clone(),
            episode: self.episode,
            start_step: self.step.unwrap_or(0),
            actions: self.planned_actions(),
        }
    }

    /// A receiver of every later plan change.
    pub(crate) fn watch(&self) -> watch::Receiver<Arc<proto::Plan>> {
        self.plan_updates.subscribe()
    }
}

/// A 128-bit random session id in hex, from the OS-seeded CSPRNG.
pub(crate) fn new_session_id() -> String {
    let mut bytes = [0u8; 16];
    rand::rng().fill_bytes(&mut bytes);
    hex::encode(bytes)
}
