//! The `prac.v1.Prac` gRPC service.

use std::pin::Pin;
use std::sync::{Arc, RwLock};

use futures::Stream;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_util::sync::CancellationToken;
use tonic::{Request, Response, Status, Streaming};

use super::registry::Registry;
use super::session::{Session, SessionError, SessionSettings, Sessions, StepError, new_session_id};
use crate::policy::Policy;
use crate::proto::{self, prac_server::Prac};

/// What the handlers share.
pub struct ServerState {
    /// None until the bundles are loaded.
    pub registry: RwLock<Option<Arc<Registry>>>,
    pub sessions: Sessions,
    pub max_horizon_limit: usize,
    /// Cancelled at shutdown: open streams end with UNAVAILABLE.
    pub shutdown: CancellationToken,
}

impl From<SessionError> for Status {
    fn from(e: SessionError) -> Status {
        let message = e.to_string();
        match e {
            SessionError::NotFound(_) | SessionError::Closed { .. } => Status::not_found(message),
            SessionError::Expired { .. } => Status::failed_precondition(message),
            SessionError::CapReached(_) => Status::resource_exhausted(message),
        }
    }
}

impl From<StepError> for Status {
    fn from(e: StepError) -> Status {
        Status::invalid_argument(e.to_string())
    }
}

fn shutting_down() -> Status {
    Status::unavailable("the server is shutting down; reconnect and resume on a running server")
}

pub fn policy_info(name: &str, policy: &Policy) -> proto::PolicyInfo {
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
    }
}

impl ServerState {
    fn registry(&self) -> Result<Arc<Registry>, Status> {
        self.registry
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
            .ok_or_else(|| Status::unavailable("the server is still loading its bundles; retry"))
    }

    fn step(&self, request: &proto::StepRequest) -> Result<proto::StepResponse, Status> {
        let slot = self.sessions.get(&request.session_id)?;
        let mut session = slot.lock();
        let report = session.step(&request.observation, request.new_episode)?;
        Ok(session.response(&report))
    }
}

#[derive(Clone)]
pub struct PracService {
    pub state: Arc<ServerState>,
}

type ResponseStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

/// Responses buffered per stream; a client that stops reading stalls its own stream, not the server.
const STREAM_BUFFER: usize = 8;

#[tonic::async_trait]
impl Prac for PracService {
    async fn list_policies(
        &self,
        _request: Request<proto::ListPoliciesRequest>,
    ) -> Result<Response<proto::ListPoliciesResponse>, Status> {
        let registry = self.state.registry()?;
        let policies = registry.iter().map(|(n, p)| policy_info(n, p)).collect();
        Ok(Response::new(proto::ListPoliciesResponse { policies }))
    }

    async fn open_session(
        &self,
        request: Request<proto::OpenSessionRequest>,
    ) -> Result<Response<proto::OpenSessionResponse>, Status> {
        let request = request.into_inner();
        let registry = self.state.registry()?;
        let Some(policy) = registry.get(&request.policy) else {
            return Err(Status::not_found(format!(
                "unknown policy '{}'; this server has: {}",
                request.policy.chars().take(64).collect::<String>(),
                registry.names().join(", ")
            )));
        };
        let settings = SessionSettings::resolve(
            request.options.as_ref(),
            policy,
            self.state.max_horizon_limit,
        )
        .map_err(|e| Status::invalid_argument(format!("bad session options: {e}")))?;
        let id = new_session_id();
        self.state
            .sessions
            .insert(Session::new(id.clone(), policy.clone(), settings))?;
        tracing::debug!(session = %id, policy = %request.policy, "session opened");
        Ok(Response::new(proto::OpenSessionResponse {
            session_id: id,
            policy: Some(policy_info(&request.policy, policy)),
            options: Some(settings.to_proto()),
        }))
    }

    async fn close_session(
        &self,
        request: Request<proto::CloseSessionRequest>,
    ) -> Result<Response<proto::CloseSessionResponse>, Status> {
        let slot = self.state.sessions.close(&request.get_ref().session_id)?;
        let steps = slot.lock().steps_served();
        Ok(Response::new(proto::CloseSessionResponse { steps }))
    }

    async fn step(
        &self,
        request: Request<proto::StepRequest>,
    ) -> Result<Response<proto::StepResponse>, Status> {
        self.state.step(request.get_ref()).map(Response::new)
    }

    type StepStreamStream = ResponseStream<proto::StepResponse>;

    async fn step_stream(
        &self,
        request: Request<Streaming<proto::StepRequest>>,
    ) -> Result<Response<Self::StepStreamStream>, Status> {
        let mut inbound = request.into_inner();
        let (tx, rx) = mpsc::channel(STREAM_BUFFER);
        let state = self.state.clone();
        tokio::spawn(async move {
            loop {
                tokio::select! {
                    biased;
                    _ = state.shutdown.cancelled() => {
                        let _ = tx.send(Err(shutting_down())).await;
                        break;
                    }
                    message = inbound.message() => {
                        let request = match message {
                            Ok(Some(request)) => request,
                            Ok(None) => break,
                            Err(status) => {
                                let _ = tx.send(Err(status)).await;
                                break;
                            }
                        };
                        let response = state.step(&request);
                        let failed = response.is_err();
                        // The first error ends the stream (gRPC carries a status only at the end).
                        if tx.send(response).await.is_err() || failed {
                            break;
                        }
                    }
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }

    async fn get_plan(
        &self,
        request: Request<proto::GetPlanRequest>,
    ) -> Result<Response<proto::Plan>, Status> {
        let slot = self.state.sessions.get(&request.get_ref().session_id)?;
        let plan = slot.lock().plan_proto();
        Ok(Response::new(plan))
    }

    type WatchPlanStream = ResponseStream<proto::Plan>;

    async fn watch_plan(
        &self,
        request: Request<proto::WatchPlanRequest>,
    ) -> Result<Response<Self::WatchPlanStream>, Status> {
        let slot = self.state.sessions.get(&request.get_ref().session_id)?;
        let (current, mut updates) = {
            let session = slot.lock();
            (session.plan_proto(), session.watch())
        };
        drop(slot);
        let (tx, rx) = mpsc::channel(STREAM_BUFFER);
        let shutdown = self.state.shutdown.clone();
        tokio::spawn(async move {
            if tx.send(Ok(current)).await.is_err() {
                return;
            }
            loop {
                tokio::select! {
                    biased;
                    _ = shutdown.cancelled() => {
                        let _ = tx.send(Err(shutting_down())).await;
                        break;
                    }
                    changed = updates.changed() => {
                        // The session ended (closed or evicted): end the stream.
                        if changed.is_err() {
                            break;
                        }
                        let plan = updates.borrow_and_update().as_ref().clone();
                        if tx.send(Ok(plan)).await.is_err() {
                            break;
                        }
                    }
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }
}
