//! A client-side session that survives losing its server: it keeps the last committed plan and,
//! when the server no longer knows the session (a restart, a failover to another replica behind a
//! proxy), opens a new one with `resume` and sends the step again. The episode goes on with the
//! committed actions; no step is lost.

use std::time::Duration;

use tonic::transport::Channel;
use tonic::{Code, Request, Status};

use crate::proto::{self, prac_client::PracClient};

/// Metadata key a proxy can hash on to keep a client's calls on one replica (docs/operations.md).
pub const AFFINITY_HEADER: &str = "x-prac-affinity";

pub struct ResumingSession {
    client: PracClient<Channel>,
    policy: String,
    options: Option<proto::SessionOptions>,
    affinity: Option<String>,
    session_id: String,
    /// The plan held from the last answer: what a new server resumes from.
    held: Option<proto::Plan>,
    /// Sessions re-opened with `resume` so far.
    pub resumes: u32,
    /// How long to keep retrying while no server answers (UNAVAILABLE).
    pub patience: Duration,
}

fn lost(status: &Status) -> bool {
    // NOT_FOUND / FAILED_PRECONDITION: the server does not know (or evicted) the session;
    // UNAVAILABLE: no server answered.
    matches!(
        status.code(),
        Code::NotFound | Code::FailedPrecondition | Code::Unavailable
    )
}

impl ResumingSession {
    /// Opens a session; `affinity` (e.g. the controller's name) goes with every call as
    /// `x-prac-affinity` metadata.
    pub async fn open(
        client: PracClient<Channel>,
        policy: &str,
        options: Option<proto::SessionOptions>,
        affinity: Option<&str>,
    ) -> Result<ResumingSession, Status> {
        let mut session = ResumingSession {
            client,
            policy: policy.to_string(),
            options,
            affinity: affinity.map(str::to_string),
            session_id: String::new(),
            held: None,
            resumes: 0,
            patience: Duration::from_secs(10),
        };
        session.session_id = session.open_remote(None).await?;
        Ok(session)
    }

    pub fn session_id(&self) -> &str {
        &self.session_id
    }

    fn request<T>(&self, message: T) -> Result<Request<T>, Status> {
        let mut request = Request::new(message);
        if let Some(key) = &self.affinity {
            let value = key
                .parse()
                .map_err(|_| Status::invalid_argument("the affinity key is not valid metadata"))?;
            request.metadata_mut().insert(AFFINITY_HEADER, value);
        }
        Ok(request)
    }

    async fn open_remote(&mut self, resume: Option<proto::Plan>) -> Result<String, Status> {
        let request = self.request(proto::OpenSessionRequest {
            policy: self.policy.clone(),
            options: self.options,
            resume,
        })?;
        Ok(self
            .client
            .open_session(request)
            .await?
            .into_inner()
            .session_id)
    }

    /// One step; if the session was lost, resumes it (with the held plan) and steps again.
    pub async fn step(
        &mut self,
        observation: &[f32],
        new_episode: bool,
    ) -> Result<proto::StepResponse, Status> {
        let give_up = tokio::time::Instant::now() + self.patience;
        loop {
            let request = self.request(proto::StepRequest {
                session_id: self.session_id.clone(),
                observation: observation.to_vec(),
                new_episode,
            })?;
            match self.client.step(request).await {
                Ok(response) => {
                    let response = response.into_inner();
                    self.held = Some(proto::Plan {
                        session_id: String::new(),
                        episode: response.episode,
                        start_step: response.step,
                        actions: response.forecast.clone(),
                    });
                    return Ok(response);
                }
                Err(status) if lost(&status) && tokio::time::Instant::now() < give_up => {
                    tracing::warn!(%status, "session lost; resuming it");
                    match self.open_remote(self.held.clone()).await {
                        Ok(id) => {
                            self.session_id = id;
                            self.resumes += 1;
                        }
                        Err(status) if lost(&status) => {
                            tokio::time::sleep(Duration::from_millis(100)).await;
                        }
                        Err(status) => return Err(status),
                    }
                }
                Err(status) => return Err(status),
            }
        }
    }
}
