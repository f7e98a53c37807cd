//! prac-soak: a long run of session churn against `prac serve` with bad requests mixed in, plus
//! clients that stall (a StepStream and a WatchPlan nobody reads). Samples the server's resident
//! memory over time (it must stay flat), counts answers by status, and measures step latency.
//! Exits non-zero if a well-formed request failed or a bad one got the wrong status.
//!
//! With no --server it starts a local `prac serve` (loopback, ephemeral port, short session TTL)
//! on a Hopper-sized policy with random weights.

mod common;

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::Parser;
use hdrhistogram::Histogram;
use prac::proto::{self, prac_client::PracClient, session_options::Tolerance};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;
use tonic::transport::Channel;

use common::LocalServer;
use prac::client::{POLICY_PATIENCE, choose_policy, connect};

/// Soak test for prac serve.
#[derive(Parser, Debug)]
#[command(version, about)]
struct Args {
    /// How long to run, e.g. "30m".
    #[arg(long, value_parser = humantime::parse_duration, default_value = "30m")]
    duration: Duration,
    /// Server address (host:port); without it a local prac serve is started.
    #[arg(long)]
    server: Option<String>,
    /// Process id of --server, for its memory samples (read from /proc).
    #[arg(long)]
    server_pid: Option<u32>,
    /// Policy to open sessions on [default: the first the server lists].
    #[arg(long)]
    policy: Option<String>,
    /// Clients churning sessions concurrently.
    #[arg(long, default_value_t = 8)]
    clients: usize,
    /// Clients that open a StepStream and a WatchPlan and never read them.
    #[arg(long, default_value_t = 2)]
    stalled: usize,
    /// Connections that never speak (no TLS, no HTTP/2 preface), reopened whenever the server
    /// closes them: its handshake timeout must close each.
    #[arg(long, default_value_t = 4)]
    silent: usize,
    /// Share of requests that are deliberately bad.
    #[arg(long, default_value_t = 0.05)]
    bad_fraction: f64,
    /// Memory sample period.
    #[arg(long, value_parser = humantime::parse_duration, default_value = "10s")]
    sample_every: Duration,
    /// Memory samples are compared from the end of this share of the run (allocator warm-up).
    #[arg(long, default_value_t = 0.1)]
    warmup_fraction: f64,
    /// Seed of the clients' choices.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// The prac binary for the local server [default: beside this one].
    #[arg(long)]
    prac_bin: Option<PathBuf>,
    /// Write the report as JSON here too.
    #[arg(long)]
    json: Option<PathBuf>,
}

#[derive(Default)]
struct Counts {
    good: u64,
    /// Well-formed requests that failed, or bad ones with an unexpected status.
    unexpected: BTreeMap<String, u64>,
    /// Bad requests, by the status they got (as expected).
    refused: BTreeMap<String, u64>,
    sessions_opened: u64,
    sessions_abandoned: u64,
    /// Silent connections the server closed.
    silent_closed: u64,
}

struct Shared {
    counts: Mutex<Counts>,
    latency: Mutex<Histogram<u64>>,
}

impl Shared {
    fn good(&self, latency: Duration) {
        self.counts.lock().unwrap().good += 1;
        common::record_latency(&mut self.latency.lock().unwrap(), latency);
    }
    fn unexpected(&self, what: &str, status: &tonic::Status) {
        let key = format!("{what}: {:?}", status.code());
        eprintln!("unexpected: {key}: {}", status.message());
        *self
            .counts
            .lock()
            .unwrap()
            .unexpected
            .entry(key)
            .or_default() += 1;
    }
    /// A bad request's answer: `expected` is the status it must get.
    fn refused(&self, what: &str, expected: Code, result: Result<(), tonic::Status>) {
        match result {
            Err(status) if status.code() == expected => {
                *self
                    .counts
                    .lock()
                    .unwrap()
                    .refused
                    .entry(format!("{what}: {expected:?}"))
                    .or_default() += 1;
            }
            Err(status) => self.unexpected(what, &status),
            Ok(()) => self.unexpected(what, &tonic::Status::ok("accepted")),
        }
    }
}

#[derive(Serialize)]
struct Sample {
    seconds: f64,
    rss_kib: u64,
}

#[derive(Serialize)]
struct Report {
    duration_s: f64,
    good_requests: u64,
    requests_per_s: f64,
    sessions_opened: u64,
    sessions_abandoned: u64,
    silent_closed: u64,
    refused: BTreeMap<String, u64>,
    unexpected: BTreeMap<String, u64>,
    latency_us: BTreeMap<String, u64>,
    memory: Vec<Sample>,
    rss_after_warmup_kib: u64,
    rss_max_after_warmup_kib: u64,
    rss_end_kib: u64,
}

fn rss_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
}

fn options(rng: &mut ChaCha8Rng) -> proto::SessionOptions {
    proto::SessionOptions {
        tolerance: Some(Tolerance::Epsilon(rng.random_range(0.0..2.0))),
        max_horizon: rng.random_range(1..=64),
        guard: rng.random_bool(0.5).then(|| proto::PlanGuard {
            every_critic: rng.random_bool(0.5),
            support_limit: rng.random_range(0.0..4.0),
            ..Default::default()
        }),
        ..Default::default()
    }
}

fn observation(rng: &mut ChaCha8Rng, obs_dim: usize) -> Vec<f32> {
    (0..obs_dim).map(|_| rng.random_range(-1.0..1.0)).collect()
}

fn step(session: &str, observation: Vec<f32>, new_episode: bool) -> proto::StepRequest {
    proto::StepRequest {
        session_id: session.to_string(),
        observation,
        new_episode,
    }
}

/// One churning client: sessions opened, stepped (unary or streamed), closed or abandoned, with
/// bad requests mixed in.
async fn churn(
    mut client: PracClient<Channel>,
    policy: String,
    obs_dim: usize,
    args: Arc<Args>,
    seed: u64,
    until: Instant,
    shared: Arc<Shared>,
) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let bad = args.bad_fraction;
    while Instant::now() < until {
        if rng.random_bool(bad) {
            let result = client
                .open_session(proto::OpenSessionRequest {
                    local_steps: 0,
                    policy: policy.clone(),
                    options: Some(proto::SessionOptions {
                        max_horizon: 1_000_000,
                        ..Default::default()
                    }),
                    resume: None,
                })
                .await
                .map(drop);
            shared.refused("open with bad options", Code::InvalidArgument, result);
            let result = client
                .open_session(proto::OpenSessionRequest {
                    local_steps: 0,
                    policy: "no-such-policy".into(),
                    options: None,
                    resume: None,
                })
                .await
                .map(drop);
            shared.refused("open unknown policy", Code::NotFound, result);
        }
        let id = match client
            .open_session(proto::OpenSessionRequest {
                local_steps: 0,
                policy: policy.clone(),
                options: Some(options(&mut rng)),
                resume: None,
            })
            .await
        {
            Ok(r) => r.into_inner().session_id,
            Err(status) => {
                shared.unexpected("open", &status);
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        shared.counts.lock().unwrap().sessions_opened += 1;
        let steps = rng.random_range(1..200);
        if rng.random_bool(0.5) {
            // Unary, with bad requests between good ones.
            let mut last_step: Option<u64> = None;
            // Whether a step since the last answered one may have been applied unseen (the
            // client gave up on it by itself while its answer was on the way).
            let mut unknown = false;
            for k in 0..steps {
                if k > 0 && rng.random_bool(bad) {
                    // A deadline too tight to meet: the server answers DEADLINE_EXCEEDED and
                    // applies nothing, or tonic gives up first (CANCELLED).
                    let mut request =
                        tonic::Request::new(step(&id, observation(&mut rng, obs_dim), false));
                    request.set_timeout(Duration::from_micros(rng.random_range(1..300)));
                    match client.step(request).await {
                        Ok(response) => last_step = Some(response.into_inner().step),
                        Err(status) if status.code() == Code::DeadlineExceeded => {
                            shared.refused("tight deadline", Code::DeadlineExceeded, Err(status));
                        }
                        Err(status) if status.code() == Code::Cancelled => {
                            shared.refused("tight deadline", Code::Cancelled, Err(status));
                            unknown = true;
                        }
                        Err(status) => shared.unexpected("tight deadline", &status),
                    }
                }
                if rng.random_bool(bad) {
                    let (what, request, code) = match rng.random_range(0..3) {
                        0 => (
                            "wrong obs length",
                            step(&id, vec![0.0; obs_dim + 1], false),
                            Code::InvalidArgument,
                        ),
                        1 => (
                            "NaN observation",
                            step(&id, vec![f32::NAN; obs_dim], false),
                            Code::InvalidArgument,
                        ),
                        _ => (
                            "unknown session",
                            step("0123456789abcdef", vec![0.0; obs_dim], false),
                            Code::NotFound,
                        ),
                    };
                    let result = client.step(request).await.map(drop);
                    shared.refused(what, code, result);
                }
                let start = Instant::now();
                match client
                    .step(step(&id, observation(&mut rng, obs_dim), k == 0))
                    .await
                {
                    Ok(response) => {
                        shared.good(start.elapsed());
                        let now = response.into_inner().step;
                        if let Some(last) = last_step
                            && !unknown
                            && now != last + 1
                        {
                            // A step the server refused moved the session on.
                            shared.unexpected(
                                "step continuity",
                                &tonic::Status::internal(format!("step {now} after {last}")),
                            );
                        }
                        last_step = Some(now);
                        unknown = false;
                    }
                    Err(status) => shared.unexpected("unary step", &status),
                }
            }
        } else {
            let (tx, rx) = mpsc::channel(1);
            match client.step_stream(ReceiverStream::new(rx)).await {
                Ok(response) => {
                    let mut inbound = response.into_inner();
                    for k in 0..steps {
                        let start = Instant::now();
                        if tx
                            .send(step(&id, observation(&mut rng, obs_dim), k == 0))
                            .await
                            .is_err()
                        {
                            break;
                        }
                        match inbound.message().await {
                            Ok(Some(_)) => shared.good(start.elapsed()),
                            Ok(None) => break,
                            Err(status) => {
                                shared.unexpected("stream step", &status);
                                break;
                            }
                        }
                    }
                }
                Err(status) => shared.unexpected("open stream", &status),
            }
        }
        if rng.random_bool(0.2) {
            // Left open: the server must evict it after its TTL.
            shared.counts.lock().unwrap().sessions_abandoned += 1;
        } else {
            if let Err(status) = client
                .close_session(proto::CloseSessionRequest {
                    session_id: id.clone(),
                })
                .await
            {
                shared.unexpected("close", &status);
            }
            if rng.random_bool(bad) {
                let result = client
                    .step(step(&id, vec![0.0; obs_dim], false))
                    .await
                    .map(drop);
                shared.refused("step on a closed session", Code::NotFound, result);
            }
        }
    }
}

/// A client that keeps one session's stream and plan watch open and never reads either: the
/// server must not buffer for it without bound.
async fn stall(
    mut client: PracClient<Channel>,
    policy: String,
    obs_dim: usize,
    until: Instant,
    shared: Arc<Shared>,
) {
    let id = match client
        .open_session(proto::OpenSessionRequest {
            local_steps: 0,
            policy,
            options: None,
            resume: None,
        })
        .await
    {
        Ok(r) => r.into_inner().session_id,
        Err(status) => return shared.unexpected("stalled open", &status),
    };
    let watch = client
        .watch_plan(proto::WatchPlanRequest {
            session_id: id.clone(),
        })
        .await;
    let (tx, rx) = mpsc::channel(1);
    let stream = client.step_stream(ReceiverStream::new(rx)).await;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    // Keeps sending until flow control stops it (a send then waits), never reading.
    while Instant::now() < until {
        let request = step(&id, observation(&mut rng, obs_dim), false);
        if tokio::time::timeout(Duration::from_secs(1), tx.send(request))
            .await
            .is_ok_and(|sent| sent.is_err())
        {
            break;
        }
    }
    drop((watch, stream));
}

/// A client that connects and never speaks, again each time the server closes it.
async fn silent(addr: String, until: Instant, shared: Arc<Shared>) {
    use tokio::io::AsyncReadExt;
    while Instant::now() < until {
        let Ok(mut tcp) = tokio::net::TcpStream::connect(&addr).await else {
            tokio::time::sleep(Duration::from_millis(100)).await;
            continue;
        };
        let mut buf = [0u8; 1024];
        // Whatever the server sends (SETTINGS, GOAWAY) is read; it must close the connection.
        loop {
            match tokio::time::timeout_at(until.into(), tcp.read(&mut buf)).await {
                Err(_) => return,
                Ok(Ok(0)) | Ok(Err(_)) => {
                    shared.counts.lock().unwrap().silent_closed += 1;
                    break;
                }
                Ok(Ok(_)) => {}
            }
        }
    }
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime");
    match runtime.block_on(run(args)) {
        Ok(report) if report.unexpected.is_empty() => std::process::ExitCode::SUCCESS,
        Ok(_) => {
            eprintln!("prac-soak: some requests got an unexpected answer (see above)");
            std::process::ExitCode::FAILURE
        }
        Err(e) => {
            eprintln!("prac-soak: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

async fn run(args: Args) -> anyhow::Result<Report> {
    let args = Arc::new(args);
    let mut _local = None;
    let args_prac_bin = args.prac_bin.clone();
    let (addr, pid) = match &args.server {
        Some(addr) => (addr.clone(), args.server_pid),
        None => {
            let args: Vec<String> = [
                "--session-ttl",
                "2s",
                "--max-sessions",
                "4096",
                "--handshake-timeout",
                "2s",
            ]
            .iter()
            .map(|s| s.to_string())
            .collect();
            let local = LocalServer::start(args_prac_bin.as_deref(), &args).await?;
            let found = (local.server.addr.clone(), local.server.pid());
            _local = Some(local);
            found
        }
    };
    let mut client = connect(&addr).await.context("connecting")?;
    let info = choose_policy(&mut client, args.policy.as_deref(), POLICY_PATIENCE).await?;
    let obs_dim = info.obs_dim as usize;

    let shared = Arc::new(Shared {
        counts: Mutex::new(Counts::default()),
        latency: Mutex::new(common::latency_histogram()),
    });
    let start = Instant::now();
    let until = start + args.duration;
    let mut tasks = Vec::new();
    for k in 0..args.clients {
        tasks.push(tokio::spawn(churn(
            connect(&addr).await?,
            info.name.clone(),
            obs_dim,
            args.clone(),
            args.seed.wrapping_mul(1000) + k as u64,
            until,
            shared.clone(),
        )));
    }
    for _ in 0..args.silent {
        tasks.push(tokio::spawn(silent(addr.clone(), until, shared.clone())));
    }
    for _ in 0..args.stalled {
        tasks.push(tokio::spawn(stall(
            connect(&addr).await?,
            info.name.clone(),
            obs_dim,
            until,
            shared.clone(),
        )));
    }

    let mut memory = Vec::new();
    loop {
        let seconds = start.elapsed().as_secs_f64();
        if let Some(rss_kib) = pid.and_then(rss_kib) {
            let c = shared.counts.lock().unwrap();
            println!(
                "{seconds:8.1} s  rss {:8} KiB  requests {:10}  sessions {:8}  refused {:6}  unexpected {}",
                rss_kib,
                c.good,
                c.sessions_opened,
                c.refused.values().sum::<u64>(),
                c.unexpected.values().sum::<u64>()
            );
            memory.push(Sample { seconds, rss_kib });
        }
        if Instant::now() >= until {
            break;
        }
        let next = (Instant::now() + args.sample_every).min(until);
        tokio::time::sleep_until(next.into()).await;
    }
    for task in tasks {
        if tokio::time::timeout(Duration::from_secs(30), task)
            .await
            .is_err()
        {
            bail!("a client did not finish within 30 s of the end");
        }
    }
    let duration = start.elapsed().as_secs_f64();
    let mut counts = std::mem::take(&mut *shared.counts.lock().unwrap());
    // The server's handshake timeout is at most 30 s unless set otherwise.
    if args.silent > 0 && duration > 35.0 && counts.silent_closed == 0 {
        counts.unexpected.insert(
            "silent connections: none closed by the server (is its --handshake-timeout over 30 s?)"
                .into(),
            1,
        );
    }
    let latency = shared.latency.lock().unwrap().clone();
    let warm = args.duration.as_secs_f64() * args.warmup_fraction;
    let after: Vec<u64> = memory
        .iter()
        .filter(|s| s.seconds >= warm)
        .map(|s| s.rss_kib)
        .collect();
    let report = Report {
        duration_s: duration,
        good_requests: counts.good,
        requests_per_s: counts.good as f64 / duration,
        sessions_opened: counts.sessions_opened,
        sessions_abandoned: counts.sessions_abandoned,
        silent_closed: counts.silent_closed,
        refused: counts.refused,
        unexpected: counts.unexpected,
        latency_us: [50.0, 99.0, 99.9, 100.0]
            .iter()
            .map(|&q| (format!("p{q}"), latency.value_at_quantile(q / 100.0)))
            .collect(),
        rss_after_warmup_kib: after.first().copied().unwrap_or(0),
        rss_max_after_warmup_kib: after.iter().copied().max().unwrap_or(0),
        rss_end_kib: memory.last().map_or(0, |s| s.rss_kib),
        memory,
    };
    println!("{}", serde_json::to_string_pretty(&report)?);
    if let Some(path) = &args.json {
        std::fs::write(path, serde_json::to_string_pretty(&report)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(report)
}
