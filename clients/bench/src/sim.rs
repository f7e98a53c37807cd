//! The sim workload: each session is a simulated robot of the policy's domain (the same
//! `prac::domains` code as prac-sim). Closed loop, the served action goes into the simulator and
//! its next observation is the next request; open loop, the robot steps at its control rate and,
//! when an answer is late, executes the action its last answer committed for that step.
//! Episodes restart on termination or truncation, from a seed per session and episode.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

use prac::domains::Env;
use prac::proto::{self, prac_client::PracClient};
use tokio::sync::{Mutex, mpsc};
use tonic::transport::Channel;

use crate::{Budget, Mode, Tally, open_stream};

/// Observations a run sent, kept for --save-observations (at most this many rows).
pub const MAX_SAVED: usize = 1_000_000;

pub type Saved = Arc<std::sync::Mutex<Vec<Vec<f32>>>>;

/// Seed of a session's episode: sessions and episodes never share one.
fn episode_seed(base: u64, session: usize, episode: u64) -> u64 {
    base.wrapping_mul(1_000_003)
        .wrapping_add(session as u64 * 100_003)
        .wrapping_add(episode)
}

/// A robot and its episode bookkeeping.
struct Robot {
    env: Box<dyn Env>,
    obs: Vec<f32>,
    base_seed: u64,
    index: usize,
    episode: u64,
    new_episode: bool,
    saved: Option<Saved>,
}

impl Robot {
    fn new(mut env: Box<dyn Env>, base_seed: u64, index: usize, saved: Option<Saved>) -> Robot {
        let mut obs = vec![0.0; env.spec().obs_dim];
        env.reset(episode_seed(base_seed, index, 0), &mut obs)
            .expect("a domain resets from any seed");
        Robot {
            env,
            obs,
            base_seed,
            index,
            episode: 0,
            new_episode: true,
            saved,
        }
    }

    fn request(&mut self, session: &str) -> proto::StepRequest {
        if let Some(saved) = &self.saved {
            let mut saved = saved.lock().unwrap_or_else(|p| p.into_inner());
            if saved.len() < MAX_SAVED {
                saved.push(self.obs.clone());
            }
        }
        let request = proto::StepRequest {
            session_id: session.to_string(),
            observation: self.obs.clone(),
            new_episode: self.new_episode,
        };
        self.new_episode = false;
        request
    }

    /// Executes `action`; a new episode starts when this one ends.
    fn act(&mut self, action: &[f32]) -> Result<(), String> {
        let t = self
            .env
            .step(action, &mut self.obs)
            .map_err(|e| e.to_string())?;
        if t.terminated || t.truncated {
            self.episode += 1;
            self.env
                .reset(
                    episode_seed(self.base_seed, self.index, self.episode),
                    &mut self.obs,
                )
                .map_err(|e| e.to_string())?;
            self.new_episode = true;
        }
        Ok(())
    }
}

/// One simulated robot's closed loop: observe, ask, act.
pub async fn closed_loop(
    mut client: PracClient<Channel>,
    session: String,
    env: Box<dyn Env>,
    (base_seed, index): (u64, usize),
    mode: Mode,
    budget: Budget,
    saved: Option<Saved>,
) -> Tally {
    let mut tally = Tally::new();
    let mut robot = Robot::new(env, base_seed, index, saved);
    let mut stream: Option<(mpsc::Sender<proto::StepRequest>, tonic::Streaming<_>)> = None;
    while budget.take(Instant::now()) {
        let request = robot.request(&session);
        let sent = Instant::now();
        let answer = match mode {
            Mode::Unary => client.step(request).await.map(tonic::Response::into_inner),
            Mode::Stream => match &mut stream {
                None => match open_stream(&mut client, request).await {
                    Ok((tx, mut responses)) => {
                        let first = next_message(&mut responses).await;
                        stream = Some((tx, responses));
                        first
                    }
                    Err(status) => Err(status),
                },
                Some((tx, responses)) => {
                    if tx.send(request).await.is_err() {
                        break;
                    }
                    next_message(responses).await
                }
            },
        };
        if budget.measuring(sent) {
            tally.record(sent.elapsed(), answer.as_ref());
        }
        let Ok(response) = answer else { break };
        if let Err(e) = robot.act(&response.action) {
            *tally.errors.entry(format!("sim: {e}")).or_default() += 1;
            break;
        }
    }
    tally
}

async fn next_message(
    responses: &mut tonic::Streaming<proto::StepResponse>,
) -> Result<proto::StepResponse, tonic::Status> {
    match responses.message().await {
        Ok(Some(r)) => Ok(r),
        Ok(None) => Err(tonic::Status::unavailable("the server ended the stream")),
        Err(status) => Err(status),
    }
}

/// What the last answer committed, for a robot that must act before the next answer arrives.
#[derive(Default)]
struct Latest {
    /// Index of the request it answered.
    answered: Option<u64>,
    /// Its committed actions from that step on.
    forecast: Vec<Vec<f32>>,
}

/// One simulated robot in open loop, over one StepStream: every `interval` it executes the
/// action for this step (its last request's answer, or, if that is late, what the latest answer
/// committed for this step) and sends its new observation.
pub async fn open_loop(
    mut client: PracClient<Channel>,
    session: String,
    env: Box<dyn Env>,
    (base_seed, index): (u64, usize),
    (interval, phase): (Duration, Duration),
    budget: Budget,
    saved: Option<Saved>,
) -> Tally {
    let tally = Arc::new(Mutex::new(Tally::new()));
    let mut robot = Robot::new(env, base_seed, index, saved);
    let latest = Arc::new(Mutex::new(Latest::default()));
    let sent_at: Arc<Mutex<VecDeque<Instant>>> = Arc::default();
    let mut next = budget.start + phase;
    if !budget.take(next) {
        return Tally::new();
    }
    tokio::time::sleep_until(next.into()).await;
    sent_at.lock().await.push_back(Instant::now());
    let (tx, mut responses) = match open_stream(&mut client, robot.request(&session)).await {
        Ok(opened) => opened,
        Err(status) => {
            let mut tally = Tally::new();
            tally.record(Duration::ZERO, Err(&status));
            return tally;
        }
    };
    let reader = {
        let (tally, latest, sent_at, budget) = (
            tally.clone(),
            latest.clone(),
            sent_at.clone(),
            budget.clone(),
        );
        tokio::spawn(async move {
            let mut index = 0u64;
            loop {
                let answer = next_message(&mut responses).await;
                let Some(at) = sent_at.lock().await.pop_front() else {
                    break;
                };
                if budget.measuring(at) {
                    tally.lock().await.record(at.elapsed(), answer.as_ref());
                }
                let Ok(response) = answer else { break };
                let mut latest = latest.lock().await;
                latest.answered = Some(index);
                latest.forecast = response.forecast.into_iter().map(|p| p.action).collect();
                index += 1;
            }
        })
    };
    // Requests sent so far; the first went with the stream.
    let mut sent = 1u64;
    let (mut late, mut on_time) = (0u64, 0u64);
    let mut held: Vec<f32> = vec![0.0; robot.env.spec().act_dim];
    loop {
        next += interval;
        if !budget.take(next) {
            break;
        }
        tokio::time::sleep_until(next.into()).await;
        // This tick executes the action for the step of the last request sent.
        let due = sent - 1;
        {
            let latest = latest.lock().await;
            match latest.answered {
                Some(answered) if answered == due => {
                    on_time += 1;
                    held.clone_from(&latest.forecast[0]);
                }
                Some(answered) => {
                    late += 1;
                    // The commitment: the action the latest answer planned for this step.
                    let ahead = (due - answered) as usize;
                    if let Some(action) = latest.forecast.get(ahead) {
                        held.clone_from(action);
                    }
                }
                None => late += 1,
            }
        }
        if let Err(e) = robot.act(&held) {
            *tally
                .lock()
                .await
                .errors
                .entry(format!("sim: {e}"))
                .or_default() += 1;
            break;
        }
        sent_at.lock().await.push_back(Instant::now());
        if tx.send(robot.request(&session)).await.is_err() {
            break;
        }
        sent += 1;
    }
    drop(tx);
    let _ = tokio::time::timeout(Duration::from_secs(5), reader).await;
    let mut tally = Arc::try_unwrap(tally)
        .map(Mutex::into_inner)
        .unwrap_or_else(|_| Tally::new());
    tally.late += late;
    tally.on_time += on_time;
    tally
}
