//! The `prac.v1.Prac` gRPC service.

use std::cell::RefCell;
use std::pin::Pin;
use std::sync::{Arc, RwLock};
use std::time::Instant;

use futures::Stream;
use tokio::sync::{mpsc, oneshot};
use tokio_stream::StreamExt as _;
use tokio_stream::wrappers::ReceiverStream;
use tokio_util::sync::CancellationToken;
use tonic::{Request, Response, Status, Streaming};

use super::arrival::Arrival;
use super::auth::Caller;
use super::batch::{Answer, Batcher};
use super::deadline;
use super::intake::{MessageDue, message_overdue, message_overdue_status};
use super::memory::{Item, Shed, WatcherTicket, costs as memory_costs};
use super::metrics::{ReplannedBy, StepAnswer};
use super::registry::Registry;
use super::session::{
    Session, SessionError, SessionSettings, SessionSlot, Sessions, StepError, StepInput,
    new_session_id,
};
use super::workspace::{Workspace, Workspaces};
use crate::plan::MAX_ROWS_PER_SESSION;
use crate::policy::Policy;
use crate::proto::{self, prac_server::Prac};

/// What the handlers share.
pub(super) struct ServerState {
    /// None until the bundles are loaded.
    pub(crate) registry: RwLock<Option<Arc<Registry>>>,
    pub(crate) sessions: Arc<Sessions>,
    pub(crate) max_horizon_limit: usize,
    /// Largest message; sessions whose plans could not fit a response are refused.
    pub(crate) max_message_bytes: usize,
    /// Cancelled at shutdown: open streams end with UNAVAILABLE.
    pub(crate) shutdown: CancellationToken,
    /// Cross-session batching; None replans each step in its request handler.
    pub(crate) batcher: Option<Batcher>,
    /// Bearer tokens; None when auth is off.
    pub(crate) auth: Option<Arc<super::auth::Tokens>>,
    /// Requests in transit: their sizes, buffered bytes and timeouts.
    pub(crate) intake: Arc<super::intake::Intake>,
    /// What clients may make the server hold; the intake charges calls and request bytes to it.
    pub(crate) budget: Arc<super::memory::MemoryBudget>,
    pub(crate) metrics: Arc<super::metrics::Metrics>,
}

impl From<SessionError> for Status {
    fn from(e: SessionError) -> Status {
        let message = e.to_string();
        match e {
            SessionError::NotFound(_) | SessionError::Closed { .. } => Status::not_found(message),
            SessionError::Expired { .. } => Status::failed_precondition(message),
            SessionError::CapReached(_) => Status::resource_exhausted(message),
            SessionError::NotOwner(_) => Status::permission_denied(message),
        }
    }
}

impl From<StepError> for Status {
    fn from(e: StepError) -> Status {
        match e {
            StepError::OvertakenBy => Status::aborted(e.to_string()),
            e => Status::invalid_argument(e.to_string()),
        }
    }
}

/// A response stream's sending end. Answers travel boxed: tokio's channel reserves its slots in
/// blocks of 32 when it is made, and a slot of a pointer keeps that block at 512 bytes for each
/// stream, opened or not, where a slot of the answer itself took some 3 KB. The status a stream
/// ends with goes apart, so it reaches the client after the answers buffered before it even when
/// the buffer is full (a client that does not read still learns why its stream ended).
struct Answers<T> {
    tx: mpsc::Sender<Result<Box<T>, Status>>,
    ending: Option<oneshot::Sender<Status>>,
}

impl<T> Answers<T> {
    /// Ends the stream with `status` once the answers buffered before it are read.
    fn end_with(&mut self, status: Status) {
        if let Some(ending) = self.ending.take() {
            let _ = ending.send(status);
        }
    }

    /// Resolves when the client is gone.
    async fn closed(&self) {
        self.tx.closed().await
    }
}

fn answers<T: Send + 'static>(buffer: usize) -> (Answers<T>, ResponseStream<T>) {
    let (tx, rx) = mpsc::channel::<Result<Box<T>, Status>>(buffer);
    let (ending, ended) = oneshot::channel::<Status>();
    let stream = ReceiverStream::new(rx)
        .map(|answer| answer.map(|boxed| *boxed))
        .chain(futures::stream::once(ended).filter_map(|status| status.ok().map(Err)));
    let ending = Some(ending);
    (Answers { tx, ending }, Box::pin(stream))
}

/// Sends on a response stream unless shutdown comes first (a client that stops reading must not
/// hold the drain). False when the stream is over.
async fn send<T>(tx: &Answers<T>, item: Result<T, Status>, shutdown: &CancellationToken) -> bool {
    tokio::select! {
        biased;
        sent = tx.tx.send(item.map(Box::new)) => sent.is_ok(),
        _ = shutdown.cancelled() => false,
    }
}

/// An upper bound on the encoded size of a response carrying a plan of `horizon` entries.
fn largest_response_bytes(horizon: usize, obs_dim: usize, act_dim: usize) -> usize {
    // Packed f32s plus per-field tags, lengths and varints, generously.
    let entry = 4 * (obs_dim + act_dim) + 32;
    (horizon + 1) * entry + 128
}

fn shutting_down() -> Status {
    Status::unavailable("the server is shutting down; reconnect and resume on a running server")
}

pub(super) fn policy_info(name: &str, policy: &Policy) -> proto::PolicyInfo {
    let (observation_features, action_features) = match policy.features() {
        Some(f) => (features_proto(f.observation), features_proto(f.action)),
        None => Default::default(),
    };
    let m = &policy.manifest;
    proto::PolicyInfo {
        name: name.to_string(),
        domain: m.domain.clone(),
        obs_dim: m.obs_dim as u32,
        act_dim: m.act_dim as u32,
        action_low: m.action_low.clone(),
        action_high: m.action_high.clone(),
        gamma: m.gamma,
        value_scale: m.value_scale.map(|v| proto::ValueScale {
            v_pi: v.v_pi,
            v_rand: v.v_rand,
        }),
        content_hash: policy.content_hash.clone(),
        q_aggregation: m.q_aggregation.as_str().to_string(),
        format_version: m.format_version,
        default_guard: Some(super::session::guard_proto(
            m.default_guard.unwrap_or_default(),
        )),
        control_period: crate::domains::control_period(&m.domain),
        observation_features,
        action_features,
    }
}

fn features_proto(entries: Vec<crate::domains::Feature>) -> Vec<proto::Feature> {
    entries
        .into_iter()
        .map(|f| proto::Feature {
            name: f.name,
            unit: f.unit,
        })
        .collect()
}

impl ServerState {
    fn registry(&self) -> Result<Arc<Registry>, Status> {
        self.registry
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
            .ok_or_else(|| Status::unavailable("the server is still loading its bundles; retry"))
    }

    /// The caller the intake attached from the call's headers (None with auth off). A call
    /// that did not come through the intake (in-process tests) has none: refused when auth is on.
    fn caller<T>(&self, request: &Request<T>) -> Result<Option<String>, Status> {
        match request.extensions().get::<Caller>() {
            Some(Caller(caller)) => Ok(caller.clone()),
            None if self.auth.is_none() => Ok(None),
            None => self.counted(Err(Status::unauthenticated(
                "the call did not pass the server's authentication",
            ))),
        }
    }

    /// Counts a handler's error in the metrics: each RPC's handler goes through it once (steps
    /// through `step`, authentication through `caller`).
    fn counted<T>(&self, result: Result<T, Status>) -> Result<T, Status> {
        result.inspect_err(|s| self.metrics.error(s))
    }

    /// Opens a session for `owner`; errors are counted by the caller.
    fn open_session(
        &self,
        owner: Option<String>,
        request: proto::OpenSessionRequest,
    ) -> Result<proto::OpenSessionResponse, Status> {
        let registry = self.registry()?;
        let Some(policy) = registry.get(&request.policy) else {
            return Err(Status::not_found(registry.not_served(&request.policy)));
        };
        let settings =
            SessionSettings::resolve(request.options.as_ref(), policy, self.max_horizon_limit)
                .map_err(|e| Status::invalid_argument(format!("bad session options: {e}")))?;
        let largest = largest_response_bytes(
            settings.replan.max_horizon,
            policy.obs_dim(),
            policy.act_dim(),
        );
        if largest > self.max_message_bytes {
            return Err(Status::invalid_argument(format!(
                "bad session options: a plan of max_horizon {} may need {largest} bytes per \
                 response, over the server's max message size of {} bytes; lower max_horizon",
                settings.replan.max_horizon, self.max_message_bytes
            )));
        }
        // Charged at its largest plan; sessions are never shed, so one that does not fit is
        // refused now.
        let memory = self.budget.try_charge(
            Item::Session,
            memory_costs::session(policy, settings.replan.max_horizon),
            Shed::SessionRefused,
        )?;
        let id = new_session_id();
        let mut session = Session::new(id.clone(), policy.clone(), settings);
        session.owner = owner;
        let resumed_actions = match &request.resume {
            Some(plan) => {
                session
                    .resume(plan)
                    .map_err(|e| Status::invalid_argument(format!("cannot resume: {e}")))?;
                plan.actions.len() as u32
            }
            None => 0,
        };
        let steps_served = self.metrics.policy_steps(&policy.manifest.name);
        self.sessions
            .insert(session, steps_served, Some(memory))
            .map_err(Status::from)?;
        self.metrics.session_opened();
        if request.resume.is_some() {
            self.metrics
                .local_steps(&policy.manifest.name, request.local_steps);
        }
        tracing::debug!(session = %id, policy = %request.policy, "session opened");
        Ok(proto::OpenSessionResponse {
            session_id: id,
            policy: Some(policy_info(&request.policy, policy)),
            options: Some(settings.to_proto()),
            resumed_actions,
        })
    }

    /// One step, counted in the metrics (latency, forecast length, plan breaks, errors). A step
    /// not applied by `deadline` is answered DEADLINE_EXCEEDED and changes nothing.
    async fn serve_step(
        &self,
        request: proto::StepRequest,
        caller: Option<&str>,
        deadline: Option<Instant>,
        arrival: Arrival,
    ) -> Result<Answered, Status> {
        let start = Instant::now();
        let slot = match self.sessions.get(&request.session_id, caller) {
            Ok(slot) => slot,
            Err(e) => {
                let status = Status::from(e);
                self.metrics.error(&status);
                return Err(status);
            }
        };
        let result = self
            .apply_or_submit(&slot, request, deadline, arrival)
            .await;
        match &result {
            Ok((response, _)) => self.metrics.step_answered(
                &slot.steps_served,
                start.elapsed(),
                &StepAnswer {
                    forecast_length: response.forecast.len(),
                    f_t: response.f_t,
                    broke: response.broke_at.is_some(),
                },
            ),
            Err(status) => self.metrics.error(status),
        }
        result.map(|(response, served)| Answered {
            response,
            undo: TakeBack {
                slot: Arc::clone(&slot),
                served,
            },
        })
    }

    async fn apply_or_submit(
        &self,
        slot: &Arc<SessionSlot>,
        request: proto::StepRequest,
        deadline: Option<Instant>,
        arrival: Arrival,
    ) -> Answer {
        if deadline::passed(deadline) {
            return Err(deadline::exceeded());
        }
        let _alone = match &self.batcher {
            Some(batcher) => match batcher.claim_alone(slot) {
                Some(alone) => Some(alone),
                None => {
                    let answer = batcher
                        .submit(slot.clone(), request, deadline, arrival)
                        .await;
                    if answer.is_ok() {
                        self.metrics.replanned(ReplannedBy::BatchWorker);
                    }
                    return answer;
                }
            },
            None => None,
        };
        // Alone or without batching, each thread keeps one workspace per policy for the sessions
        // it serves.
        thread_local! {
            static INLINE: RefCell<Workspaces> = RefCell::new(Workspaces::new(MAX_ROWS_PER_SESSION, 1));
        }
        INLINE.with_borrow_mut(|inline| {
            let Workspace { evaluator, scratch } = inline.get(&slot.policy);
            let mut session = slot.lock();
            let input = StepInput {
                observation: &request.observation,
                new_episode: request.new_episode,
                arrival,
            };
            let report = session.apply_step(evaluator, scratch, input);
            let flops = evaluator.take_flops();
            let report = report?;
            if let Some(batcher) = &self.batcher {
                batcher.note_alone_cost(flops);
            }
            self.metrics.replanned(ReplannedBy::Handler);
            Ok((session.response(&report), report.served))
        })
    }
}

/// An applied step: its response, and what takes it back if the response cannot be delivered.
struct Answered {
    response: proto::StepResponse,
    undo: TakeBack,
}

/// Names an applied step of a session.
struct TakeBack {
    slot: Arc<SessionSlot>,
    served: u64,
}

impl TakeBack {
    /// The step's response could not be handed to the client: it changes nothing after all.
    fn take_back(&self) {
        self.slot.lock().take_back(self.served);
    }
}

#[derive(Clone)]
pub(super) struct PracService {
    pub(crate) state: Arc<ServerState>,
}

type ResponseStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

/// Responses buffered per stream; a client that stops reading stalls its own stream, not the server.
const STREAM_BUFFER: usize = 8;

#[tonic::async_trait]
impl Prac for PracService {
    async fn list_policies(
        &self,
        request: Request<proto::ListPoliciesRequest>,
    ) -> Result<Response<proto::ListPoliciesResponse>, Status> {
        self.state.caller(&request)?;
        let registry = self.state.counted(self.state.registry())?;
        let policies = registry.iter().map(|(n, p)| policy_info(n, p)).collect();
        Ok(Response::new(proto::ListPoliciesResponse { policies }))
    }

    async fn open_session(
        &self,
        request: Request<proto::OpenSessionRequest>,
    ) -> Result<Response<proto::OpenSessionResponse>, Status> {
        let owner = self.state.caller(&request)?;
        self.state
            .counted(self.state.open_session(owner, request.into_inner()))
            .map(Response::new)
    }

    async fn close_session(
        &self,
        request: Request<proto::CloseSessionRequest>,
    ) -> Result<Response<proto::CloseSessionResponse>, Status> {
        let caller = self.state.caller(&request)?;
        let slot = self.state.counted(
            self.state
                .sessions
                .close(&request.get_ref().session_id, caller.as_deref())
                .map_err(Status::from),
        )?;
        let steps = slot.lock().steps_served();
        Ok(Response::new(proto::CloseSessionResponse { steps }))
    }

    async fn step(
        &self,
        request: Request<proto::StepRequest>,
    ) -> Result<Response<proto::StepResponse>, Status> {
        let deadline = deadline::of(request.metadata(), Instant::now());
        let arrival = Arrival::of(request.extensions());
        let caller = self.state.caller(&request)?;
        // Returned at once, so the response reaches the transport: the step stays applied.
        self.state
            .serve_step(request.into_inner(), caller.as_deref(), deadline, arrival)
            .await
            .map(|answered| Response::new(answered.response))
    }

    type StepStreamStream = ResponseStream<proto::StepResponse>;

    async fn step_stream(
        &self,
        request: Request<Streaming<proto::StepRequest>>,
    ) -> Result<Response<Self::StepStreamStream>, Status> {
        // The stream's deadline bounds each of its steps.
        let deadline = deadline::of(request.metadata(), Instant::now());
        let caller = self.state.caller(&request)?;
        let message_due = request.extensions().get::<MessageDue>().cloned();
        let mut inbound = request.into_inner();
        let (mut tx, stream) = answers(STREAM_BUFFER);
        let state = self.state.clone();
        tokio::spawn(async move {
            loop {
                tokio::select! {
                    biased;
                    _ = state.shutdown.cancelled() => {
                        tx.end_with(shutting_down());
                        break;
                    }
                    message = inbound.message() => {
                        let request = match message {
                            Ok(Some(request)) => request,
                            Ok(None) => break,
                            Err(status) => {
                                state.metrics.error(&status);
                                send(&tx, Err(status), &state.shutdown).await;
                                break;
                            }
                        };
                        // A stream's messages arrive in order: each is stamped as it is read.
                        let arrival = Arrival::next();
                        let answered = state
                            .serve_step(request, caller.as_deref(), deadline, arrival)
                            .await;
                        let failed = answered.is_err();
                        let (response, applied) = match answered {
                            Ok(answered) => (Ok(answered.response), Some(answered.undo)),
                            Err(status) => (Err(status), None),
                        };
                        // While the client does not read its answers, a message it has begun
                        // still must complete in time: past that, the stream ends.
                        let handed = tokio::select! {
                            biased;
                            handed = send(&tx, response, &state.shutdown) => handed.then_some(()).ok_or_else(shutting_down),
                            _ = message_overdue(message_due.as_ref()) => Err(message_overdue_status()),
                        };
                        if let Err(status) = handed {
                            // Not handed to the stream: the client never sees this step.
                            if let Some(applied) = applied {
                                applied.take_back();
                            }
                            state.metrics.error(&status);
                            tx.end_with(status);
                            break;
                        }
                        // The first error ends the stream (gRPC carries a status only at the end).
                        if failed {
                            break;
                        }
                    }
                }
            }
        });
        Ok(Response::new(stream))
    }

    async fn get_plan(
        &self,
        request: Request<proto::GetPlanRequest>,
    ) -> Result<Response<proto::Plan>, Status> {
        let caller = self.state.caller(&request)?;
        let slot = self.state.counted(
            self.state
                .sessions
                .get(&request.get_ref().session_id, caller.as_deref())
                .map_err(Status::from),
        )?;
        let plan = slot.lock().plan_proto();
        Ok(Response::new(plan))
    }

    type WatchPlanStream = ResponseStream<proto::Plan>;

    async fn watch_plan(
        &self,
        request: Request<proto::WatchPlanRequest>,
    ) -> Result<Response<Self::WatchPlanStream>, Status> {
        let caller = self.state.caller(&request)?;
        let id = request.into_inner().session_id;
        let slot = self.state.counted(
            self.state
                .sessions
                .get(&id, caller.as_deref())
                .map_err(Status::from),
        )?;
        let ticket = self.state.counted(self.state.budget.admit_watcher())?;
        let shed = ticket.reset();
        let (current, mut updates) = {
            let session = slot.lock();
            (session.plan_proto(), session.watch())
        };
        drop(slot);
        // One slot: while a watcher is slow, the watch channel keeps only the newest plan.
        let (mut tx, stream) = answers(1);
        let state = self.state.clone();
        tokio::spawn(async move {
            let shutdown = &state.shutdown;
            if !send(&tx, Ok(current), shutdown).await {
                tx.end_with(shutting_down());
                return;
            }
            loop {
                tokio::select! {
                    biased;
                    _ = shutdown.cancelled() => {
                        tx.end_with(shutting_down());
                        break;
                    }
                    // The client is gone (its call cancelled or its connection closed): a watcher
                    // of a session that never steps would otherwise wait for it to end.
                    _ = tx.closed() => break,
                    // Its session idle while memory is short: ended to make room.
                    _ = shed.cancelled() => {
                        let status = WatcherTicket::shed_status();
                        state.metrics.error(&status);
                        tx.end_with(status);
                        break;
                    }
                    changed = updates.changed() => {
                        if changed.is_err() {
                            // The session ended: say how (closed, expired).
                            let why = state.sessions.get(&id, caller.as_deref()).err().map(Status::from);
                            if let Some(status) = why {
                                state.metrics.error(&status);
                                send(&tx, Err(status), shutdown).await;
                            }
                            break;
                        }
                        ticket.active();
                        let plan = updates.borrow_and_update().as_ref().clone();
                        if !send(&tx, Ok(plan), shutdown).await {
                            tx.end_with(shutting_down());
                            break;
                        }
                    }
                }
            }
        });
        Ok(Response::new(stream))
    }
}
