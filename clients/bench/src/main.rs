//! prac-bench: N concurrent sessions against `prac serve`, over StepStream or unary Step, closed
//! loop (each session waits for its answer) or open loop at a fixed request rate; reports
//! throughput, HDR latency percentiles, errors by status, mean forecast and replans.
//!
//! With no --server it starts a local `prac serve` (loopback, ephemeral port) on a Hopper-sized
//! policy with random weights and stops it at the end. It always stops by itself: after
//! --duration or --steps, and at the latest after a hard deadline.

mod common;
mod sim;

use std::collections::{BTreeMap, VecDeque};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::{Parser, ValueEnum};
use hdrhistogram::Histogram;
use prac::proto::{self, prac_client::PracClient, session_options::Tolerance};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use tokio::sync::{Mutex, mpsc};
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;

use common::LocalServer;
use prac::client::{POLICY_PATIENCE, choose_policy, connect};

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
enum Mode {
    /// One bidirectional StepStream per session.
    Stream,
    /// One unary Step call per step.
    Unary,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
enum Workload {
    /// Each session is a simulated robot of the policy's domain, the served action driving it.
    Sim,
    /// States visited by following the server's own model from random starts.
    Model,
}

/// A duration such as "10s" or "500ms", or a plain number of seconds ("10").
fn duration(text: &str) -> Result<Duration, String> {
    match text.parse::<f64>() {
        Ok(seconds) if seconds.is_finite() && seconds >= 0.0 => {
            Ok(Duration::from_secs_f64(seconds))
        }
        Ok(_) => Err(format!("{text} is not a duration")),
        Err(_) => humantime::parse_duration(text).map_err(|e| e.to_string()),
    }
}

/// Load tester for prac serve.
#[derive(Parser, Debug)]
#[command(version, about)]
struct Args {
    /// Server address (host:port or http://host:port); without it a local prac serve is started
    /// for the run.
    #[arg(long)]
    server: Option<String>,
    /// Process id of --server, for its CPU time per step (read from /proc) [default: the local
    /// server's].
    #[arg(long)]
    server_pid: Option<u32>,
    /// Policy to open sessions on [default: the only policy --server serves; hopper-bench on the
    /// local server].
    #[arg(long)]
    policy: Option<String>,
    /// What the sessions observe [default: sim when the policy's domain is one of prac's, else
    /// model; --observations replays a file instead].
    #[arg(long, value_enum)]
    workload: Option<Workload>,
    /// Open loop, per session: each robot steps at this control rate (Hz) whether or not its
    /// answer came back; a step whose answer is late executes the action the last answer
    /// committed for it. Needs --mode stream.
    #[arg(long)]
    rate_per_session: Option<f64>,
    /// Write the observations the run sent (f32 `obs` [N, obs_dim], safetensors) for
    /// --observations.
    #[arg(long)]
    save_observations: Option<PathBuf>,
    /// Concurrent sessions.
    #[arg(long, default_value_t = 1)]
    sessions: usize,
    /// How long to measure, e.g. "10s" or 10 (seconds) (ignored with --steps).
    #[arg(long, value_parser = duration, default_value = "5s")]
    duration: Duration,
    /// Total steps to measure instead of a duration.
    #[arg(long)]
    steps: Option<u64>,
    /// Unmeasured warm-up before measuring.
    #[arg(long, value_parser = duration, default_value = "500ms")]
    warmup: Duration,
    #[arg(long, value_enum, default_value_t = Mode::Stream)]
    mode: Mode,
    /// Open loop: total requests per second, spread evenly over the sessions; requests are sent
    /// on schedule (tokio's timer: about 1 ms resolution) whether or not answers came back, and
    /// latency counts from each send. 0: closed loop.
    #[arg(long, default_value_t = 0.0)]
    rate: f64,
    /// eps coefficient of the sessions (eps = coef x (V_pi - V_rand)).
    #[arg(long, default_value_t = 0.005)]
    epsilon_coef: f64,
    /// Absolute eps instead of a coefficient.
    #[arg(long)]
    epsilon: Option<f64>,
    /// Plan cap of the sessions (1 with --epsilon 0: one-step policy serving).
    #[arg(long, default_value_t = 32)]
    max_horizon: u32,
    /// Guard the sessions' plans with every critic (the session option guard.every_critic).
    #[arg(long)]
    every_critic: bool,
    /// Guard the sessions' plans with a support limit (guard.support_limit) [default: none].
    #[arg(long, value_name = "Z")]
    support_limit: Option<f64>,
    /// Observations: a safetensors file with an `obs` array [N, obs_dim] (as written by
    /// `python -m prac_client.record`). Default: states visited by running the policy on its own
    /// model (the server's predicted observations, with noise), recorded before measuring.
    #[arg(long)]
    observations: Option<PathBuf>,
    /// The prac binary for the local server [default: next to prac-bench].
    #[arg(long)]
    prac_bin: Option<PathBuf>,
    /// Extra flag for the local server, e.g. --server-arg=--batch-max=0 (repeatable).
    #[arg(long, allow_hyphen_values = true)]
    server_arg: Vec<String>,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

#[derive(Serialize)]
struct Report {
    mode: Mode,
    /// "sim", "model" or "file".
    workload: String,
    domain: String,
    sessions: usize,
    open_loop_rate: Option<f64>,
    seconds: f64,
    steps: u64,
    throughput: f64,
    latency_us: Latency,
    errors: BTreeMap<String, u64>,
    mean_forecast: f64,
    replans_per_step: f64,
    mean_plan_length: f64,
    /// Old plan actions Replan tested per step (kept ones, and the one that broke the plan).
    old_actions_tested_per_step: f64,
    /// Open loop with the sim workload: robot steps whose answer had not come back in time.
    late_steps: Option<u64>,
    late_fraction: Option<f64>,
    /// The server's CPU time (user + system, all threads) per measured step, when its process
    /// is known.
    server_cpu_us_per_step: Option<f64>,
}

#[derive(Serialize)]
struct Latency {
    p50: f64,
    p90: f64,
    p99: f64,
    p999: f64,
    max: f64,
    mean: f64,
}

/// What the sessions measured.
struct Tally {
    latency: Histogram<u64>,
    errors: BTreeMap<String, u64>,
    f_t: u64,
    replans: u64,
    plan_length: u64,
    tested: u64,
    steps: u64,
    /// Open-loop robot steps whose answer was late, and on time.
    late: u64,
    on_time: u64,
}

impl Tally {
    fn new() -> Tally {
        Tally {
            latency: common::latency_histogram(),
            errors: BTreeMap::new(),
            f_t: 0,
            replans: 0,
            plan_length: 0,
            tested: 0,
            steps: 0,
            late: 0,
            on_time: 0,
        }
    }
    fn record(&mut self, latency: Duration, result: Result<&proto::StepResponse, &tonic::Status>) {
        match result {
            Ok(r) => {
                self.steps += 1;
                common::record_latency(&mut self.latency, latency);
                self.f_t += r.f_t;
                self.replans += u64::from(r.broke_at.is_some());
                self.plan_length += r.forecast.len() as u64;
                self.tested += u64::from(r.kept) + u64::from(r.broke_at.is_some());
            }
            Err(status) => {
                *self
                    .errors
                    .entry(format!("{:?}", status.code()))
                    .or_default() += 1;
            }
        }
    }
    fn merge(&mut self, other: &Tally) {
        self.latency
            .add(&other.latency)
            .expect("same histogram bounds");
        for (k, v) in &other.errors {
            *self.errors.entry(k.clone()).or_default() += v;
        }
        self.f_t += other.f_t;
        self.replans += other.replans;
        self.plan_length += other.plan_length;
        self.tested += other.tested;
        self.steps += other.steps;
        self.late += other.late;
        self.on_time += other.on_time;
    }
}

/// When measuring stops.
#[derive(Clone)]
struct Budget {
    start: Instant,
    measure_from: Instant,
    until: Instant,
    steps_left: Option<Arc<std::sync::atomic::AtomicI64>>,
}

impl Budget {
    fn measuring(&self, now: Instant) -> bool {
        now >= self.measure_from
    }
    /// Takes one step from the budget; false when the run is over.
    fn take(&self, now: Instant) -> bool {
        if now >= self.until {
            return false;
        }
        match &self.steps_left {
            Some(left) if now >= self.measure_from => {
                left.fetch_sub(1, std::sync::atomic::Ordering::Relaxed) > 0
            }
            _ => true,
        }
    }
}

fn session_options(args: &Args) -> proto::SessionOptions {
    proto::SessionOptions {
        tolerance: Some(match args.epsilon {
            Some(e) => Tolerance::Epsilon(e),
            None => Tolerance::EpsilonCoef(args.epsilon_coef),
        }),
        growth: None,
        max_horizon: args.max_horizon,
        sampled: false,
        seed: 0,
        guard: (args.every_critic || args.support_limit.is_some()).then_some(proto::PlanGuard {
            every_critic: args.every_critic,
            support_limit: args.support_limit.unwrap_or(0.0),
            ..Default::default()
        }),
    }
}

async fn open(
    client: &mut PracClient<Channel>,
    policy: &str,
    args: &Args,
) -> anyhow::Result<String> {
    let opened = client
        .open_session(proto::OpenSessionRequest {
            local_steps: 0,
            policy: policy.to_string(),
            options: Some(session_options(args)),
            resume: None,
        })
        .await
        .context("OpenSession")?;
    Ok(opened.into_inner().session_id)
}

/// Observations to send: from a file, or recorded by following the server's predictions.
async fn observations(
    args: &Args,
    client: &mut PracClient<Channel>,
    policy: &str,
    obs_dim: usize,
) -> anyhow::Result<Vec<Vec<f32>>> {
    if let Some(path) = &args.observations {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let tensors = safetensors::SafeTensors::deserialize(&bytes)?;
        let obs = tensors.tensor("obs").context("no `obs` tensor")?;
        if obs.dtype() != safetensors::Dtype::F32
            || obs.shape().len() != 2
            || obs.shape()[1] != obs_dim
        {
            bail!(
                "`obs` must be f32 [N, {obs_dim}], is {:?} {:?}",
                obs.dtype(),
                obs.shape()
            );
        }
        let values: Vec<f32> = obs
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        return Ok(values.chunks(obs_dim).map(<[f32]>::to_vec).collect());
    }
    let session = open(client, policy, args).await?;
    let mut rng = ChaCha8Rng::seed_from_u64(args.seed);
    let mut obs: Vec<f32> = (0..obs_dim).map(|_| rng.random_range(-0.5..0.5)).collect();
    let mut visited = Vec::new();
    for i in 0..2000 {
        let r = client
            .step(proto::StepRequest {
                session_id: session.clone(),
                observation: obs.clone(),
                new_episode: i % 200 == 0,
            })
            .await?
            .into_inner();
        visited.push(obs.clone());
        obs = r.forecast[0]
            .predicted_observation
            .iter()
            .map(|v| (v + rng.random_range(-0.02..0.02)).clamp(-5.0, 5.0))
            .collect();
        if i % 200 == 199 {
            obs = (0..obs_dim).map(|_| rng.random_range(-0.5..0.5)).collect();
        }
    }
    client
        .close_session(proto::CloseSessionRequest {
            session_id: session,
        })
        .await?;
    Ok(visited)
}

/// Opens a StepStream with its first request already queued: a server may send its response
/// headers only with its first answer (grpcio does), so the request must not wait for them.
async fn open_stream(
    client: &mut PracClient<Channel>,
    first: proto::StepRequest,
) -> Result<
    (
        mpsc::Sender<proto::StepRequest>,
        tonic::Streaming<proto::StepResponse>,
    ),
    tonic::Status,
> {
    let (tx, rx) = mpsc::channel(1024);
    tx.try_send(first)
        .expect("a new channel has room for one request");
    let responses = client
        .step_stream(ReceiverStream::new(rx))
        .await?
        .into_inner();
    Ok((tx, responses))
}

fn request(session: &str, states: &[Vec<f32>], i: usize) -> proto::StepRequest {
    proto::StepRequest {
        session_id: session.to_string(),
        observation: states[i % states.len()].clone(),
        new_episode: i == 0,
    }
}

/// How a session sends its steps.
#[derive(Clone, Copy)]
struct Pace {
    mode: Mode,
    /// Open loop: time between this session's requests; None for closed loop.
    interval: Option<Duration>,
    /// Open loop: where in the interval this session's requests fall (sessions are spread out).
    phase: Duration,
}

/// One session's load; returns what it measured.
async fn run_session(
    mut client: PracClient<Channel>,
    session: String,
    states: Arc<Vec<Vec<f32>>>,
    offset: usize,
    pace: Pace,
    budget: Budget,
) -> Tally {
    let Pace {
        mode,
        interval,
        phase,
    } = pace;
    let mut tally = Tally::new();
    match (mode, interval) {
        (Mode::Unary, None) => {
            let mut i = 0;
            while budget.take(Instant::now()) {
                let sent = Instant::now();
                let r = client.step(request(&session, &states, offset + i)).await;
                if budget.measuring(sent) {
                    tally.record(sent.elapsed(), r.as_ref().map(|r| r.get_ref()));
                }
                i += 1;
            }
        }
        (Mode::Stream, None) => {
            if !budget.take(Instant::now()) {
                return tally;
            }
            let mut sent = Instant::now();
            let (tx, mut responses) =
                match open_stream(&mut client, request(&session, &states, offset)).await {
                    Ok(opened) => opened,
                    Err(status) => {
                        tally.record(Duration::ZERO, Err(&status));
                        return tally;
                    }
                };
            let mut i = 1;
            loop {
                let r = match responses.message().await {
                    Ok(Some(r)) => Ok(r),
                    Ok(None) => break,
                    Err(status) => Err(status),
                };
                if budget.measuring(sent) {
                    tally.record(sent.elapsed(), r.as_ref());
                }
                if r.is_err() || !budget.take(Instant::now()) {
                    break;
                }
                sent = Instant::now();
                if tx
                    .send(request(&session, &states, offset + i))
                    .await
                    .is_err()
                {
                    break;
                }
                i += 1;
            }
        }
        (Mode::Unary, Some(interval)) => {
            let tally = Arc::new(Mutex::new(tally));
            let mut calls = Vec::new();
            let mut next = budget.start + phase;
            let mut i = 0;
            while budget.take(next) {
                tokio::time::sleep_until(next.into()).await;
                let (mut client, session, states, tally, budget) = (
                    client.clone(),
                    session.clone(),
                    states.clone(),
                    tally.clone(),
                    budget.clone(),
                );
                calls.push(tokio::spawn(async move {
                    let sent = Instant::now();
                    let r = client.step(request(&session, &states, offset + i)).await;
                    if budget.measuring(sent) {
                        tally
                            .lock()
                            .await
                            .record(sent.elapsed(), r.as_ref().map(|r| r.get_ref()));
                    }
                }));
                next += interval;
                i += 1;
            }
            for call in calls {
                let _ = call.await;
            }
            return Arc::try_unwrap(tally)
                .map(Mutex::into_inner)
                .unwrap_or_else(|_| Tally::new());
        }
        (Mode::Stream, Some(interval)) => {
            let (tx, rx) = mpsc::channel(1024);
            let scheduled = Arc::new(Mutex::new(VecDeque::new()));
            let sender = {
                let (scheduled, budget, session, states) = (
                    scheduled.clone(),
                    budget.clone(),
                    session.clone(),
                    states.clone(),
                );
                tokio::spawn(async move {
                    let mut next = budget.start + phase;
                    let mut i = 0;
                    while budget.take(next) {
                        tokio::time::sleep_until(next.into()).await;
                        scheduled.lock().await.push_back(Instant::now());
                        if tx
                            .send(request(&session, &states, offset + i))
                            .await
                            .is_err()
                        {
                            break;
                        }
                        next += interval;
                        i += 1;
                    }
                })
            };
            // Requests flow before the response headers come (the sender is already running).
            let mut responses = match client.step_stream(ReceiverStream::new(rx)).await {
                Ok(r) => r.into_inner(),
                Err(status) => {
                    tally.record(Duration::ZERO, Err(&status));
                    let _ = sender.await;
                    return tally;
                }
            };
            loop {
                let r = match responses.message().await {
                    Ok(Some(r)) => Ok(r),
                    Ok(None) => break,
                    Err(status) => Err(status),
                };
                let Some(at) = scheduled.lock().await.pop_front() else {
                    break;
                };
                if budget.measuring(at) {
                    tally.record(at.elapsed(), r.as_ref());
                }
                if r.is_err() {
                    break;
                }
            }
            let _ = sender.await;
        }
    }
    tally
}

/// CPU time (user + system, all threads) a process has used, from /proc (Linux's clock ticks
/// are 1/100 s).
fn cpu_time(pid: u32) -> Option<Duration> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command name, which is in parentheses and may hold spaces.
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let ticks: u64 = fields.get(11)?.parse::<u64>().ok()? + fields.get(12)?.parse::<u64>().ok()?;
    Some(Duration::from_millis(ticks * 10))
}

/// Writes observations as a safetensors file with an f32 `obs` [N, obs_dim].
fn save_observations(
    path: &std::path::Path,
    rows: &[Vec<f32>],
    obs_dim: usize,
) -> anyhow::Result<()> {
    let data: Vec<u8> = rows
        .iter()
        .flatten()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let view = safetensors::tensor::TensorView::new(
        safetensors::Dtype::F32,
        vec![rows.len(), obs_dim],
        &data,
    )?;
    let bytes = safetensors::serialize([("obs", view)], None)?;
    std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))
}

async fn run(args: Args) -> anyhow::Result<Report> {
    let (addr, local) = match &args.server {
        Some(addr) => {
            let addr = addr
                .strip_prefix("http://")
                .unwrap_or(addr)
                .trim_end_matches('/');
            (addr.to_string(), None)
        }
        None => {
            let server = LocalServer::start(args.prac_bin.as_deref(), &args.server_arg).await?;
            (server.server.addr.clone(), Some(server))
        }
    };
    let server_pid = args
        .server_pid
        .or(local.as_ref().and_then(|l| l.server.pid()));
    let mut client = connect(&addr).await?;
    // The local server serves only hopper-bench.
    let wanted = args
        .policy
        .as_deref()
        .or(local.is_some().then_some("hopper-bench"));
    let info = choose_policy(&mut client, wanted, POLICY_PATIENCE)
        .await
        .with_context(|| format!("choosing a policy at {addr}"))?;
    let policy = info.name.clone();
    let ours = prac::domains::make(&info.domain).is_some();
    let workload = match (args.workload, &args.observations) {
        (Some(_), Some(_)) => bail!("--observations replays a file; it takes no --workload"),
        (Some(Workload::Sim), None) if !ours => bail!(
            "--workload sim needs a policy of one of prac's domains (lander, hopper, walker, \
             cheetah, ant, humanoid, pendulum); '{policy}' is for '{}'; use --workload model or \
             --observations FILE",
            info.domain
        ),
        (Some(w), None) => Some(w),
        (None, Some(_)) => None,
        (None, None) if ours => Some(Workload::Sim),
        (None, None) => Some(Workload::Model),
    };
    if args.rate_per_session.is_some() && args.rate > 0.0 {
        bail!("give --rate (all sessions) or --rate-per-session (each robot), not both");
    }
    if let Some(hz) = args.rate_per_session {
        if !(hz.is_finite() && hz > 0.0) {
            bail!("--rate-per-session must be a positive rate in Hz, got {hz}");
        }
        if workload != Some(Workload::Sim) {
            bail!("--rate-per-session drives simulated robots: it needs --workload sim");
        }
    }
    let open_loop = args.rate > 0.0 || args.rate_per_session.is_some();
    if open_loop && workload == Some(Workload::Sim) && args.mode != Mode::Stream {
        bail!("simulated robots run open loop over one StepStream each: use --mode stream");
    }
    let obs_dim = info.obs_dim as usize;
    let states = Arc::new(match workload {
        Some(Workload::Sim) => Vec::new(),
        _ => observations(&args, &mut client, &policy, obs_dim).await?,
    });
    let saved: Option<sim::Saved> = args.save_observations.as_ref().map(|_| Arc::default());

    // Sessions the server refuses (e.g. over its session cap) are counted as errors, not fatal.
    let mut total = Tally::new();
    let mut sessions = Vec::new();
    for _ in 0..args.sessions {
        let mut client = connect(&addr).await?;
        let opened = client
            .open_session(proto::OpenSessionRequest {
                local_steps: 0,
                policy: policy.clone(),
                options: Some(session_options(&args)),
                resume: None,
            })
            .await;
        match opened {
            Ok(opened) => sessions.push((client, opened.into_inner().session_id)),
            Err(status) => {
                *total
                    .errors
                    .entry(format!("OpenSession {:?}", status.code()))
                    .or_default() += 1;
            }
        }
    }
    let start = Instant::now();
    let measure_from = start + args.warmup;
    let until = match args.steps {
        // A hard deadline even when counting steps: the run always stops by itself.
        Some(_) => measure_from + Duration::from_secs(600),
        None => measure_from + args.duration,
    };
    let budget = Budget {
        start,
        measure_from,
        until,
        steps_left: args
            .steps
            .map(|n| Arc::new(std::sync::atomic::AtomicI64::new(n as i64))),
    };
    let interval = match args.rate_per_session {
        Some(hz) => Some(Duration::from_secs_f64(1.0 / hz)),
        None => {
            (args.rate > 0.0).then(|| Duration::from_secs_f64(args.sessions as f64 / args.rate))
        }
    };
    let mut tasks = Vec::new();
    for (k, (client, id)) in sessions.iter().enumerate() {
        let phase = interval.map_or(Duration::ZERO, |i| {
            i.mul_f64(k as f64 / args.sessions as f64)
        });
        let task = match workload {
            Some(Workload::Sim) => {
                let env = prac::domains::make(&info.domain).expect("checked above");
                match interval {
                    Some(interval) => tokio::spawn(sim::open_loop(
                        client.clone(),
                        id.clone(),
                        env,
                        (args.seed, k),
                        (interval, phase),
                        budget.clone(),
                        saved.clone(),
                    )),
                    None => tokio::spawn(sim::closed_loop(
                        client.clone(),
                        id.clone(),
                        env,
                        (args.seed, k),
                        args.mode,
                        budget.clone(),
                        saved.clone(),
                    )),
                }
            }
            _ => tokio::spawn(run_session(
                client.clone(),
                id.clone(),
                states.clone(),
                k * 997,
                Pace {
                    mode: args.mode,
                    interval,
                    phase,
                },
                budget.clone(),
            )),
        };
        tasks.push(task);
    }
    // The server's CPU over the measured window.
    let cpu_at = |pid: Option<u32>| pid.and_then(cpu_time);
    tokio::time::sleep_until(measure_from.into()).await;
    let cpu_start = cpu_at(server_pid);
    for task in tasks {
        total.merge(&task.await?);
    }
    let cpu_end = cpu_at(server_pid);
    let seconds = measure_from.elapsed().as_secs_f64().min(
        until
            .saturating_duration_since(measure_from)
            .as_secs_f64()
            .max(f64::MIN_POSITIVE),
    );
    for (mut client, id) in sessions {
        let _ = client
            .close_session(proto::CloseSessionRequest { session_id: id })
            .await;
    }
    if let Some(local) = local {
        local.server.stop().await;
    }
    if let (Some(path), Some(saved)) = (&args.save_observations, &saved) {
        let rows = saved.lock().unwrap_or_else(|p| p.into_inner());
        save_observations(path, &rows, obs_dim)?;
    }
    let steps = total.steps.max(1) as f64;
    let q = |p: f64| total.latency.value_at_quantile(p) as f64;
    let robot_steps = total.late + total.on_time;
    let open_loop_sim = workload == Some(Workload::Sim) && interval.is_some();
    Ok(Report {
        mode: args.mode,
        workload: match workload {
            Some(Workload::Sim) => "sim",
            Some(Workload::Model) => "model",
            None => "file",
        }
        .to_string(),
        domain: info.domain.clone(),
        sessions: args.sessions,
        open_loop_rate: interval.map(|i| args.sessions as f64 / i.as_secs_f64()),
        seconds,
        steps: total.steps,
        throughput: total.steps as f64 / seconds,
        latency_us: Latency {
            p50: q(0.5),
            p90: q(0.9),
            p99: q(0.99),
            p999: q(0.999),
            max: total.latency.max() as f64,
            mean: total.latency.mean(),
        },
        errors: total.errors,
        mean_forecast: total.f_t as f64 / steps,
        replans_per_step: total.replans as f64 / steps,
        mean_plan_length: total.plan_length as f64 / steps,
        old_actions_tested_per_step: total.tested as f64 / steps,
        late_steps: open_loop_sim.then_some(total.late),
        late_fraction: open_loop_sim.then(|| total.late as f64 / robot_steps.max(1) as f64),
        server_cpu_us_per_step: cpu_start
            .zip(cpu_end)
            .map(|(a, b)| (b - a).as_secs_f64() * 1e6 / steps),
    })
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    let json = args.json;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime");
    match runtime.block_on(run(args)) {
        Ok(report) if json => {
            println!(
                "{}",
                serde_json::to_string_pretty(&report).expect("report serialises")
            );
            std::process::ExitCode::SUCCESS
        }
        Ok(r) => {
            let loop_kind = match r.open_loop_rate {
                Some(rate) => format!("open loop at {rate} req/s"),
                None => "closed loop".to_string(),
            };
            println!(
                "{} sessions, {:?}, {} workload ({}), {loop_kind}: {} steps in {:.2} s",
                r.sessions, r.mode, r.workload, r.domain, r.steps, r.seconds
            );
            println!("throughput   {:.0} steps/s", r.throughput);
            let l = &r.latency_us;
            println!(
                "latency us   p50 {:.0}  p90 {:.0}  p99 {:.0}  p99.9 {:.0}  max {:.0}  mean {:.0}",
                l.p50, l.p90, l.p99, l.p999, l.max, l.mean
            );
            println!(
                "forecast     mean f_t {:.2}, plan length {:.2}, replans per step {:.3}, old actions tested per step {:.2}",
                r.mean_forecast,
                r.mean_plan_length,
                r.replans_per_step,
                r.old_actions_tested_per_step
            );
            if let (Some(late), Some(fraction)) = (r.late_steps, r.late_fraction) {
                println!(
                    "late steps   {late} ({:.2}% of robot steps)",
                    100.0 * fraction
                );
            }
            if let Some(cpu) = r.server_cpu_us_per_step {
                println!("server CPU   {cpu:.0} us per step (user + system, /proc)");
            }
            if r.errors.is_empty() {
                println!("errors       none");
            } else {
                println!("errors       {:?}", r.errors);
            }
            std::process::ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
