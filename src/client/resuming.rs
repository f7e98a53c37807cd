//! A client-side session that survives losing its server: it keeps the last committed plan and,
//! when the server no longer knows the session (a restart, a failover to another replica behind a
//! proxy), opens a new one with `resume` and sends the step again. The episode goes on with the
//! committed actions; no step is lost.
//!
//! With a [`Fallback`] (the bundle's file on board), a session whose servers have all failed for
//! longer than its patience goes on locally: prac's own session and Replan, in-process, resumed
//! from the plan it holds, so its answers are the ones a server resumed from that plan would give.
//! It looks for a server again every [`ResumingSession::probe_every`] and, once one answers,
//! resumes there from the local plan.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use tonic::transport::Channel;
use tonic::{Code, Request, Status};

use crate::plan::ReplanScratch;
use crate::policy::{Evaluator, Policy};
use crate::proto::{self, prac_client::PracClient};
use crate::serve::arrival::Arrival;
use crate::serve::session::{Session, SessionSettings, StepInput};

/// The server's default `--max-horizon-limit`, which a local session's options are checked
/// against as a server would.
const LOCAL_MAX_HORIZON_LIMIT: usize = 256;

/// A bundle on board: prac's own session and Replan, run in-process when no server answers.
pub struct Fallback {
    policy: Arc<Policy>,
    evaluator: Evaluator,
    scratch: ReplanScratch,
    /// The local session, from the first local step until a server answers again.
    session: Option<Session>,
}

impl Fallback {
    /// Loads the bundle file, checked as the server loads it.
    pub fn load(path: &Path) -> anyhow::Result<Fallback> {
        let policy = Arc::new(crate::bundle::load(path)?);
        Ok(Fallback {
            evaluator: Evaluator::for_sessions(policy.clone(), 1),
            scratch: ReplanScratch::new(policy.obs_dim(), policy.act_dim()),
            policy,
            session: None,
        })
    }

    /// "sha256:<hex>" of the bundle file.
    pub fn content_hash(&self) -> &str {
        &self.policy.content_hash
    }
}

/// One step's answer, and where it came from.
#[derive(Clone, Debug)]
pub struct Answer {
    pub response: proto::StepResponse,
    /// Replanned on board (no server answered), not served.
    pub local: bool,
}

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
    fallback: Option<Fallback>,
    /// Whether the session is going on locally now.
    local: bool,
    /// Steps answered locally so far.
    pub local_steps: u64,
    /// Local steps not yet reported to a server (sent with the next resume).
    unreported_local_steps: u64,
    /// While local, how often to look for a server again, and how long to wait for one.
    pub probe_every: Duration,
    pub probe_timeout: Duration,
    next_probe: tokio::time::Instant,
    /// The call looking for a server while local: whether one answered.
    reaching: Option<tokio::task::JoinHandle<bool>>,
}

fn lost(status: &Status) -> bool {
    // NOT_FOUND / FAILED_PRECONDITION: the server does not know (or evicted) the session;
    // UNAVAILABLE: no server answered; a transport error (tonic's UNKNOWN): the connection
    // broke under the call, as when the server is killed.
    let broken = || {
        std::error::Error::source(status)
            .is_some_and(|e| e.downcast_ref::<tonic::transport::Error>().is_some())
    };
    matches!(
        status.code(),
        Code::NotFound | Code::FailedPrecondition | Code::Unavailable
    ) || (status.code() == Code::Unknown && broken())
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
            fallback: None,
            local: false,
            local_steps: 0,
            unreported_local_steps: 0,
            probe_every: Duration::from_secs(1),
            probe_timeout: Duration::from_millis(200),
            next_probe: tokio::time::Instant::now(),
            reaching: None,
        };
        session.session_id = session.open_remote(None).await?;
        Ok(session)
    }

    /// [`ResumingSession::open`], going on locally with `fallback` when every server has failed
    /// past the patience. The server's bundle must be the fallback's (the same content hash):
    /// checked here, at open, not at the first outage.
    pub async fn open_with_fallback(
        mut client: PracClient<Channel>,
        policy: &str,
        options: Option<proto::SessionOptions>,
        affinity: Option<&str>,
        fallback: Fallback,
    ) -> Result<ResumingSession, Status> {
        let listed = client
            .list_policies(proto::ListPoliciesRequest {})
            .await?
            .into_inner();
        let served = listed
            .policies
            .iter()
            .find(|p| p.name == policy)
            .ok_or_else(|| Status::not_found(format!("the server serves no policy '{policy}'")))?;
        if served.content_hash != fallback.content_hash() {
            return Err(Status::failed_precondition(format!(
                "the fallback bundle ({}) is not the server's '{policy}' ({}); give the same file",
                fallback.content_hash(),
                served.content_hash
            )));
        }
        let mut session = ResumingSession::open(client, policy, options, affinity).await?;
        session.fallback = Some(fallback);
        Ok(session)
    }

    /// Whether the session is going on locally now.
    pub fn is_local(&self) -> bool {
        self.local
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
        let local_steps = if resume.is_some() {
            self.unreported_local_steps
        } else {
            0
        };
        let request = self.request(proto::OpenSessionRequest {
            policy: self.policy.clone(),
            options: self.options,
            resume,
            local_steps,
        })?;
        let id = self
            .client
            .open_session(request)
            .await?
            .into_inner()
            .session_id;
        self.unreported_local_steps -= local_steps;
        Ok(id)
    }

    /// Keeps the answer's plan: what a new server, or the fallback, resumes from.
    fn hold(&mut self, response: &proto::StepResponse) {
        self.held = Some(proto::Plan {
            session_id: String::new(),
            episode: response.episode,
            start_step: response.step,
            actions: response.forecast.clone(),
        });
    }

    /// While local: every `probe_every` a ListPolicies that the steps do not wait for asks
    /// whether a server answers (a silent link must not hold up a control loop); once one did,
    /// the session is re-opened there from the local plan, waiting at most `probe_timeout`.
    async fn look_for_a_server(&mut self) {
        if self.reaching.as_ref().is_some_and(|r| r.is_finished()) {
            let reaching = self.reaching.take().expect("checked above");
            if matches!(reaching.await, Ok(true)) {
                let held = self.held.clone();
                if let Ok(Ok(id)) =
                    tokio::time::timeout(self.probe_timeout, self.open_remote(held)).await
                {
                    tracing::info!(
                        local_steps = self.local_steps,
                        "a server answers again; resumed there"
                    );
                    self.session_id = id;
                    self.resumes += 1;
                    self.local = false;
                    if let Some(fallback) = &mut self.fallback {
                        fallback.session = None;
                    }
                    return;
                }
            }
        }
        if self.reaching.is_none() && tokio::time::Instant::now() >= self.next_probe {
            self.next_probe = tokio::time::Instant::now() + self.probe_every;
            let mut client = self.client.clone();
            let timeout = self.probe_timeout;
            let request = self.request(proto::ListPoliciesRequest {});
            self.reaching = Some(tokio::spawn(async move {
                match request {
                    Ok(request) => matches!(
                        tokio::time::timeout(timeout, client.list_policies(request)).await,
                        Ok(Ok(_))
                    ),
                    Err(_) => false,
                }
            }));
        }
    }

    /// One step; if the session was lost, resumes it (with the held plan) and steps again. With
    /// a fallback, a session no server has answered for the patience goes on locally.
    pub async fn step(&mut self, observation: &[f32], new_episode: bool) -> Result<Answer, Status> {
        if self.local {
            self.look_for_a_server().await;
        }
        if self.local {
            return self.step_local(observation, new_episode);
        }
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
                    self.hold(&response);
                    return Ok(Answer {
                        response,
                        local: false,
                    });
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
                Err(status) if lost(&status) && self.fallback.is_some() => {
                    tracing::warn!(%status, "no server answers; going on locally from the held plan");
                    self.local = true;
                    self.next_probe = tokio::time::Instant::now() + self.probe_every;
                    return self.step_local(observation, new_episode);
                }
                Err(status) => return Err(status),
            }
        }
    }

    /// One step on board: the fallback's session, resumed from the held plan at its first step.
    fn step_local(&mut self, observation: &[f32], new_episode: bool) -> Result<Answer, Status> {
        let fallback = self
            .fallback
            .as_mut()
            .ok_or_else(|| Status::unavailable("no server answers and there is no fallback"))?;
        if fallback.session.is_none() {
            let settings = SessionSettings::resolve(
                self.options.as_ref(),
                &fallback.policy,
                LOCAL_MAX_HORIZON_LIMIT,
            )
            .map_err(Status::invalid_argument)?;
            let mut session = Session::new("local".into(), fallback.policy.clone(), settings);
            if let Some(plan) = &self.held {
                session.resume(plan).map_err(Status::failed_precondition)?;
            }
            fallback.session = Some(session);
        }
        let session = fallback.session.as_mut().expect("made above");
        let report = session
            .apply_step(
                &mut fallback.evaluator,
                &mut fallback.scratch,
                StepInput {
                    observation,
                    new_episode,
                    arrival: Arrival::default(),
                },
            )
            .map_err(|e| Status::invalid_argument(e.to_string()))?;
        let response = session.response(&report);
        self.hold(&response);
        self.local_steps += 1;
        self.unreported_local_steps += 1;
        Ok(Answer {
            response,
            local: true,
        })
    }
}
