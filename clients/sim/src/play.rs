//! Playing a domain against the server: one session and one StepStream per episode; the
//! environment runs here, the server decides (PrAC) and reports its forecast.

use std::path::Path;

use anyhow::{Context, bail};
use prac::proto::prac_client::PracClient;
use prac::proto::session_options::{Growth, Tolerance};
use prac::proto::{self, PolicyInfo};
use serde::Serialize;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;

pub type Client = PracClient<Channel>;

/// How eps is given to the server.
#[derive(Clone, Copy, Debug)]
pub enum Tol {
    Coef(f64),
    Absolute(f64),
}

/// How the session's plans grow and how long they may get; `None` / 0 leave the server's
/// defaults (grow by 2, at most 32 actions).
#[derive(Clone, Copy, Debug, Default)]
pub struct PlanShape {
    pub growth: Option<Growth>,
    pub max_horizon: u32,
    /// The session option guard (off: the policy's default_guard, or with `paper_test` the
    /// paper's test alone).
    pub every_critic: bool,
    pub support_limit: f64,
    pub max_epsilon_coef: f64,
    pub paper_test: bool,
}

impl PlanShape {
    /// The shape as `sweep.md` and `play` print it, `None` for the server's defaults.
    pub fn describe(&self) -> Option<String> {
        let growth = self.growth.map(|g| match g {
            Growth::Grow(k) => format!("grow {k}"),
            Growth::Fixed(n) => format!("fixed {n}"),
        });
        let cap = (self.max_horizon > 0).then(|| format!("max horizon {}", self.max_horizon));
        let critics = self.every_critic.then(|| "every critic".to_string());
        let support =
            (self.support_limit > 0.0).then(|| format!("support limit {}", self.support_limit));
        let tolerance = (self.max_epsilon_coef > 0.0)
            .then(|| format!("eps coefficient at most {}", self.max_epsilon_coef));
        let paper = self.paper_test.then(|| "the paper's test".to_string());
        let parts: Vec<String> = [growth, cap, critics, support, tolerance, paper]
            .into_iter()
            .flatten()
            .collect();
        (!parts.is_empty()).then(|| parts.join(", "))
    }

    /// The session option guard, where one is asked for (an empty one for the paper's test).
    pub fn guard(&self) -> Option<proto::PlanGuard> {
        (self.every_critic
            || self.support_limit > 0.0
            || self.max_epsilon_coef > 0.0
            || self.paper_test)
            .then_some(proto::PlanGuard {
                every_critic: self.every_critic,
                support_limit: self.support_limit,
                max_epsilon_coef: self.max_epsilon_coef,
            })
    }

    /// The shape with the policy's default guard written out where none is asked for, so that
    /// what is printed is what the server does.
    pub fn with_default_guard(self, info: &proto::PolicyInfo) -> PlanShape {
        match &info.default_guard {
            Some(g) if self.guard().is_none() => PlanShape {
                every_critic: g.every_critic,
                support_limit: g.support_limit,
                max_epsilon_coef: g.max_epsilon_coef,
                ..self
            },
            _ => self,
        }
    }
}

/// One played episode, as the client saw it.
#[derive(Clone, Debug, Default, Serialize)]
pub struct EpisodeResult {
    pub seed: u64,
    pub steps: u64,
    pub ret: f64,
    pub discounted: f64,
    /// The task ended it (a walker fell, the lander landed or crashed) before the step limit.
    pub terminated: bool,
    /// How far the robot moved forward, metres (walkers only).
    pub distance: Option<f64>,
    /// The eps in force, as OpenSession answered it (a guard may hold it below what was asked).
    pub epsilon: f64,
    /// Mean of the server's f_t over the episode.
    pub forecast: f64,
    /// Steps at which the old plan broke (a replan), per step.
    pub replans_per_step: f64,
    /// Steps where f_t computed from the forecast's decided_at differs from the server's f_t.
    pub accounting_mismatches: u64,
    /// Steps whose action differs from the one committed for it at the previous step although
    /// the server said it kept that action.
    pub commitment_violations: u64,
}

impl EpisodeResult {
    pub fn outcome(&self) -> prac::eval::Outcome {
        prac::eval::Outcome {
            ret: self.ret,
            discounted: self.discounted,
            steps: self.steps as f64,
            terminated: self.terminated,
            distance: self.distance,
        }
    }
}

/// A frame to draw: the state after `step` steps, and the server's forecast there: the
/// committed actions, the step each was decided at and the predicted observations as points.
pub struct Snapshot {
    pub scene: prac::domains::Scene,
    pub trace: Vec<(f64, f64)>,
    pub actions: Vec<Vec<f32>>,
    pub decided_at: Vec<u64>,
    pub action_range: (f32, f32),
    pub step: u64,
}

/// Plays one episode from `seed`; when `snapshot_at` is set, captures that step's frame.
pub async fn play_episode(
    client: &mut Client,
    info: &PolicyInfo,
    tol: Tol,
    plan: PlanShape,
    seed: u64,
    snapshot_at: Option<u64>,
) -> anyhow::Result<(EpisodeResult, Option<Snapshot>)> {
    let Some(mut env) = prac::domains::make(&info.domain) else {
        bail!(
            "policy '{}' is for domain '{}', which this client cannot play",
            info.name,
            info.domain
        );
    };
    let spec = env.spec().clone();
    if spec.obs_dim != info.obs_dim as usize || spec.act_dim != info.act_dim as usize {
        bail!(
            "policy '{}' has dims {}/{}, domain '{}' has {}/{}",
            info.name,
            info.obs_dim,
            info.act_dim,
            spec.name,
            spec.obs_dim,
            spec.act_dim
        );
    }
    let options = proto::SessionOptions {
        tolerance: Some(match tol {
            Tol::Coef(c) => Tolerance::EpsilonCoef(c),
            Tol::Absolute(e) => Tolerance::Epsilon(e),
        }),
        growth: plan.growth,
        max_horizon: plan.max_horizon,
        seed,
        guard: plan.guard(),
        ..Default::default()
    };
    let opened = client
        .open_session(proto::OpenSessionRequest {
            local_steps: 0,
            policy: info.name.clone(),
            options: Some(options),
            resume: None,
        })
        .await
        .map_err(|s| anyhow::anyhow!("OpenSession: {}", s.message()))?
        .into_inner();
    let session = opened.session_id;
    let epsilon = opened.options.map_or(0.0, |o| o.epsilon);
    let (tx, rx) = mpsc::channel(2);
    let mut responses = client
        .step_stream(ReceiverStream::new(rx))
        .await
        .map_err(|s| anyhow::anyhow!("StepStream: {}", s.message()))?
        .into_inner();

    let mut obs = vec![0.0; spec.obs_dim];
    env.reset(seed, &mut obs)?;
    let start = env.forward_position();
    let mut result = EpisodeResult {
        seed,
        epsilon,
        ..EpisodeResult::default()
    };
    let mut totals = prac::domains::EpisodeTotals::new(info.gamma);
    let mut replans = 0u64;
    let mut committed_next: Option<Vec<f32>> = None;
    let mut snapshot = None;
    loop {
        tx.send(proto::StepRequest {
            session_id: session.clone(),
            observation: obs.clone(),
            new_episode: totals.steps == 0,
        })
        .await
        .context("the step stream closed")?;
        let response = responses
            .message()
            .await
            .map_err(|s| {
                anyhow::anyhow!("step {}: {} ({:?})", totals.steps, s.message(), s.code())
            })?
            .context("the server ended the step stream")?;
        let first = response
            .forecast
            .first()
            .context("a response without a forecast")?;
        if response.step + 1 - first.decided_at != response.f_t {
            result.accounting_mismatches += 1;
        }
        if response.broke_at.is_some() {
            replans += 1;
        }
        if let Some(expected) = &committed_next
            && response.kept > 0
            && *expected != response.action
        {
            result.commitment_violations += 1;
        }
        committed_next = response.forecast.get(1).map(|p| p.action.clone());
        if snapshot_at == Some(totals.steps) {
            let predicted: Vec<f32> = response
                .forecast
                .iter()
                .flat_map(|p| p.predicted_observation.iter().copied())
                .collect();
            snapshot = Some(Snapshot {
                scene: env.scene(),
                trace: env.trace(&predicted),
                actions: response.forecast.iter().map(|p| p.action.clone()).collect(),
                decided_at: response.forecast.iter().map(|p| p.decided_at).collect(),
                action_range: spec.action_range(),
                step: totals.steps,
            });
        }
        let step = env.step(&response.action, &mut obs)?;
        if totals.record(&step, response.f_t) {
            result.distance = prac::domains::forward_distance(start, &*env);
            break;
        }
    }
    drop(tx);
    let _ = client
        .close_session(proto::CloseSessionRequest {
            session_id: session,
        })
        .await;
    result.steps = totals.steps;
    result.ret = totals.ret;
    result.discounted = totals.discounted;
    result.terminated = totals.terminated;
    result.forecast = totals.forecast();
    result.replans_per_step = replans as f64 / totals.steps as f64;
    Ok((result, snapshot))
}

/// Draws a snapshot with the server's forecast.
pub fn render(snapshot: &Snapshot, title: &str, out: &Path) -> anyhow::Result<()> {
    let forecast = prac::render::Forecast {
        trace: &snapshot.trace,
        actions: &snapshot.actions,
        decided_at: &snapshot.decided_at,
        step: snapshot.step,
        action_range: snapshot.action_range,
    };
    prac::render::render_scene(&snapshot.scene, Some(&forecast), title, out, (800, 640))
}
