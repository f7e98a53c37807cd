//! prac-flood: the memory attack of docs/operations.md ("Memory budget"), with a well-behaved
//! client beside it. Each of --connections connections keeps --calls StepStreams open that send
//! only their HEADERS, reopening each as it ends (a connection sent GOAWAY is replaced); with
//! --watchers, that many WatchPlan watchers on sessions that never step. Meanwhile a probe opens
//! a session, steps it and closes it every --probe-every, retrying a refused call until it gets
//! its first answer, and reports how long that took. Prints a JSON report: how every flood call
//! ended (by gRPC status), the probes' worst time to a first answer, the probes that failed, and
//! the server's resident memory before, at its highest during, and after the flood (without
//! --server a local `prac serve` is started on --bundles with the --server-arg flags).

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Parser;
use prac::proto::{self, prac_client::PracClient};
use serde::Serialize;
use tokio::sync::Mutex;
use tonic::transport::{Channel, Endpoint};

#[derive(Parser, Debug)]
#[command(
    version,
    about = "Floods prac serve with never-started calls and idle watchers"
)]
struct Args {
    /// Server address (host:port); without it a local `prac serve` is started on --bundles.
    #[arg(long)]
    server: Option<String>,
    /// Process id of --server, for its resident memory (read from /proc).
    #[arg(long)]
    server_pid: Option<u32>,
    /// The local server's bundle folder.
    #[arg(long, default_value = "bundles")]
    bundles: std::path::PathBuf,
    /// Extra flag for the local server, e.g. --server-arg=--max-memory=64Mi (repeatable).
    #[arg(long, allow_hyphen_values = true)]
    server_arg: Vec<String>,
    /// How long to wait after the flood for the server to give memory back.
    #[arg(long, value_parser = humantime::parse_duration, default_value = "5s")]
    settle: Duration,
    /// Policy the probe (and the watchers' sessions) use.
    #[arg(long)]
    policy: String,
    /// Flood connections.
    #[arg(long, default_value_t = 160)]
    connections: usize,
    /// Header-only StepStreams each flood connection keeps open.
    #[arg(long, default_value_t = 250)]
    calls: usize,
    /// WatchPlan watchers on idle sessions (spread over --watched-sessions).
    #[arg(long, default_value_t = 0)]
    watchers: usize,
    /// Sessions the watchers watch (never stepped).
    #[arg(long, default_value_t = 16)]
    watched_sessions: usize,
    /// How long to flood, e.g. 30s.
    #[arg(long, value_parser = humantime::parse_duration, default_value = "30s")]
    duration: Duration,
    /// How often the probe starts a new session.
    #[arg(long, value_parser = humantime::parse_duration, default_value = "500ms")]
    probe_every: Duration,
    /// Steps each probe session takes.
    #[arg(long, default_value_t = 10)]
    probe_steps: usize,
}

/// How the flood's calls ended: by the gRPC status the server sent ("Ok" for a clean end of
/// stream), or, for calls the server never processed, "refused by GOAWAY" (opened after the
/// connection's GOAWAY: tonic reports these as INTERNAL) and "connection closed" (queued on, or
/// still sending over, a connection that closed first, or whose client task ended with the
/// flood: CANCELLED or UNKNOWN).
#[derive(Default, Serialize)]
struct Ended {
    by_code: BTreeMap<String, u64>,
    /// Status messages seen per code (the first of each), for the report.
    messages: BTreeMap<String, String>,
}

/// Whether the error under `status` is the transport's, and which.
fn transport_ending(status: &tonic::Status) -> Option<&'static str> {
    let mut source = std::error::Error::source(status);
    while let Some(error) = source {
        // Debug names the kind (hyper's DispatchGone), Display says it in words.
        let shown = format!("{error:?} {error}");
        if shown.contains("GoAway") {
            return Some("refused by GOAWAY");
        }
        if [
            "Canceled",
            "connection closed",
            "BrokenPipe",
            "broken pipe",
            "ConnectionReset",
            "connection reset",
            "dispatch task is gone",
        ]
        .iter()
        .any(|closed| shown.contains(closed))
        {
            return Some("connection closed");
        }
        source = error.source();
    }
    None
}

impl Ended {
    fn record(&mut self, status: Option<&tonic::Status>) {
        let code = match status {
            None => "Ok".to_string(),
            Some(s) => transport_ending(s).map_or_else(|| format!("{:?}", s.code()), String::from),
        };
        *self.by_code.entry(code.clone()).or_default() += 1;
        if let Some(s) = status {
            self.messages.entry(code).or_insert_with(|| {
                let mut shown = s.message().to_string();
                let mut source = std::error::Error::source(s);
                while let Some(error) = source {
                    shown = format!("{shown}: {error}");
                    source = error.source();
                }
                shown
            });
        }
    }
}

#[derive(Serialize)]
struct Report {
    connections_made: u64,
    calls_opened: u64,
    calls_ended: Ended,
    watchers_opened: u64,
    watchers_ended: Ended,
    probes: u64,
    probes_failed: u64,
    probe_failures: Vec<String>,
    probe_first_answer_ms_max: f64,
    probe_first_answer_ms_p50: f64,
    probes_over_1s: u64,
    /// The server's VmRSS (KiB), when its process can be read.
    server_rss_before_kib: Option<u64>,
    server_rss_max_kib: Option<u64>,
    server_rss_after_kib: Option<u64>,
    /// Whether the server was still answering after the flood.
    server_alive_after: bool,
}

fn rss_kib(pid: Option<u32>) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{}/status", pid?)).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
}

struct Shared {
    stop: AtomicBool,
    connections_made: AtomicU64,
    calls_opened: AtomicU64,
    watchers_opened: AtomicU64,
    calls_ended: Mutex<Ended>,
    watchers_ended: Mutex<Ended>,
}

async fn channel(addr: &str) -> anyhow::Result<Channel> {
    Ok(Endpoint::from_shared(format!("http://{addr}"))?
        .connect_timeout(Duration::from_secs(5))
        .connect()
        .await?)
}

/// One flood connection: keeps `calls` header-only StepStreams open until stop, replacing the
/// connection when it stops taking calls (GOAWAY, or closed).
async fn flood_connection(addr: String, calls: usize, shared: Arc<Shared>) {
    while !shared.stop.load(Ordering::Relaxed) {
        let Ok(channel) = channel(&addr).await else {
            tokio::time::sleep(Duration::from_millis(50)).await;
            continue;
        };
        shared.connections_made.fetch_add(1, Ordering::Relaxed);
        let dead = Arc::new(AtomicBool::new(false));
        let mut tasks = Vec::new();
        for _ in 0..calls {
            let (channel, shared, dead) = (channel.clone(), shared.clone(), dead.clone());
            tasks.push(tokio::spawn(async move {
                let mut client = PracClient::new(channel);
                while !shared.stop.load(Ordering::Relaxed) && !dead.load(Ordering::Relaxed) {
                    shared.calls_opened.fetch_add(1, Ordering::Relaxed);
                    // HEADERS, then nothing: the request stream yields nothing until this task
                    // ends and drops `_open`, which ends it.
                    let (_open, requests) = tokio::sync::mpsc::channel::<proto::StepRequest>(1);
                    let requests = tokio_stream::wrappers::ReceiverStream::new(requests);
                    let call = client.step_stream(requests);
                    let answered = tokio::select! {
                        answered = call => answered,
                        _ = wait_stop(&shared) => return,
                    };
                    let ended = match answered {
                        Ok(response) => {
                            let mut inbound = response.into_inner();
                            loop {
                                tokio::select! {
                                    message = inbound.message() => match message {
                                        Ok(Some(_)) => continue,
                                        Ok(None) => break None,
                                        Err(status) => break Some(status),
                                    },
                                    _ = wait_stop(&shared) => return,
                                }
                            }
                        }
                        Err(status) => Some(status),
                    };
                    // A transport error (GOAWAY, a closed connection): this connection is done.
                    if ended.as_ref().is_some_and(|s| {
                        s.code() == tonic::Code::Unavailable || s.code() == tonic::Code::Unknown
                    }) {
                        dead.store(true, Ordering::Relaxed);
                    }
                    shared.calls_ended.lock().await.record(ended.as_ref());
                }
            }));
        }
        for task in tasks {
            let _ = task.await;
        }
    }
}

async fn wait_stop(shared: &Shared) {
    while !shared.stop.load(Ordering::Relaxed) {
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

async fn open_session(
    client: &mut PracClient<Channel>,
    policy: &str,
) -> Result<String, tonic::Status> {
    let response = client
        .open_session(proto::OpenSessionRequest {
            policy: policy.to_string(),
            ..Default::default()
        })
        .await?;
    Ok(response.into_inner().session_id)
}

/// Watchers on sessions that never step, each reopened as it ends, until stop.
async fn flood_watchers(
    addr: String,
    policy: String,
    watchers: usize,
    sessions: usize,
    shared: Arc<Shared>,
) -> anyhow::Result<()> {
    let channel = channel(&addr).await?;
    let mut client = PracClient::new(channel.clone());
    let mut ids = Vec::new();
    for _ in 0..sessions.max(1) {
        ids.push(open_session(&mut client, &policy).await?);
    }
    // Several connections: a connection carries at most its streams' cap.
    let mut channels = Vec::new();
    for _ in 0..watchers.div_ceil(200).max(1) {
        channels.push(crate::channel(&addr).await?);
    }
    let mut tasks = Vec::new();
    for w in 0..watchers {
        let mut client = PracClient::new(channels[w % channels.len()].clone());
        let (id, shared) = (ids[w % ids.len()].clone(), shared.clone());
        tasks.push(tokio::spawn(async move {
            while !shared.stop.load(Ordering::Relaxed) {
                shared.watchers_opened.fetch_add(1, Ordering::Relaxed);
                let request = proto::WatchPlanRequest {
                    session_id: id.clone(),
                };
                let answered = tokio::select! {
                    answered = client.watch_plan(request) => answered,
                    _ = wait_stop(&shared) => return,
                };
                let ended = match answered {
                    Ok(response) => {
                        let mut plans = response.into_inner();
                        loop {
                            tokio::select! {
                                plan = plans.message() => match plan {
                                    Ok(Some(_)) => continue,
                                    Ok(None) => break None,
                                    Err(status) => break Some(status),
                                },
                                _ = wait_stop(&shared) => return,
                            }
                        }
                    }
                    Err(status) => Some(status),
                };
                shared.watchers_ended.lock().await.record(ended.as_ref());
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        }));
    }
    for task in tasks {
        let _ = task.await;
    }
    Ok(())
}

fn refused_for_room(status: &tonic::Status) -> bool {
    matches!(
        status.code(),
        tonic::Code::ResourceExhausted | tonic::Code::Unavailable
    )
}

/// Retries `call` while it is refused for want of room (RESOURCE_EXHAUSTED or UNAVAILABLE),
/// for at most 10 s.
async fn patiently<T, F, Fut>(mut call: F) -> Result<T, tonic::Status>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Result<T, tonic::Status>>,
{
    let give_up = Instant::now() + Duration::from_secs(10);
    loop {
        match call().await {
            Err(s) if refused_for_room(&s) && Instant::now() < give_up => {
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
            other => return other,
        }
    }
}

/// One probe: a session opened, `steps` steps over a StepStream, closed. Returns the time from
/// its start to its first answer.
async fn probe(
    client: &mut PracClient<Channel>,
    policy: &str,
    obs_dim: usize,
    steps: usize,
) -> anyhow::Result<Duration> {
    let start = Instant::now();
    let id = patiently(|| {
        let mut client = client.clone();
        async move { open_session(&mut client, policy).await }
    })
    .await
    .context("OpenSession")?;
    let mut first = None;
    let mut served = 0;
    while served < steps {
        let mut answers = loop {
            let (tx, rx) = tokio::sync::mpsc::channel(steps);
            for t in served..steps {
                tx.send(proto::StepRequest {
                    session_id: id.clone(),
                    observation: vec![0.01 * t as f32; obs_dim],
                    new_episode: t == 0,
                })
                .await?;
            }
            drop(tx);
            let requests = tokio_stream::wrappers::ReceiverStream::new(rx);
            match client.step_stream(requests).await {
                Ok(answers) => break answers.into_inner(),
                Err(s) if refused_for_room(&s) && start.elapsed() < Duration::from_secs(10) => {
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
                Err(s) => anyhow::bail!("StepStream: {s}"),
            }
        };
        loop {
            match answers.message().await {
                Ok(Some(_)) => {
                    first.get_or_insert_with(|| start.elapsed());
                    served += 1;
                }
                Ok(None) => break,
                // A stream reset before its first message was read: go on from where it stopped.
                Err(s) if s.code() == tonic::Code::ResourceExhausted => break,
                Err(s) => anyhow::bail!("StepStream: {s}"),
            }
        }
        if served < steps && start.elapsed() > Duration::from_secs(10) {
            anyhow::bail!("only {served} of {steps} steps answered in 10 s");
        }
    }
    let _ = client
        .close_session(proto::CloseSessionRequest { session_id: id })
        .await;
    first.context("no answer")
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let local = match &args.server {
        Some(_) => None,
        None => {
            let bin = prac::client::local::prac_binary(None)?;
            Some(
                prac::client::local::LocalServer::start(&bin, &args.bundles, &args.server_arg)
                    .await?,
            )
        }
    };
    let server = match (&args.server, &local) {
        (Some(addr), _) => addr.clone(),
        (None, Some(local)) => local.addr.clone(),
        (None, None) => unreachable!("a local server is started without --server"),
    };
    let pid = args
        .server_pid
        .or_else(|| local.as_ref().and_then(|l| l.pid()));
    let shared = Arc::new(Shared {
        stop: AtomicBool::new(false),
        connections_made: AtomicU64::new(0),
        calls_opened: AtomicU64::new(0),
        watchers_opened: AtomicU64::new(0),
        calls_ended: Mutex::new(Ended::default()),
        watchers_ended: Mutex::new(Ended::default()),
    });
    let mut probe_client = PracClient::new(channel(&server).await?);
    // Waits for a starting server's bundles.
    let obs_dim = prac::client::choose_policy(
        &mut probe_client,
        Some(&args.policy),
        prac::client::POLICY_PATIENCE,
    )
    .await?
    .obs_dim as usize;

    let rss_before = rss_kib(pid);
    let rss_max = Arc::new(AtomicU64::new(rss_before.unwrap_or(0)));
    let sampler = {
        let (rss_max, shared) = (rss_max.clone(), shared.clone());
        tokio::spawn(async move {
            while !shared.stop.load(Ordering::Relaxed) {
                if let Some(rss) = rss_kib(pid) {
                    rss_max.fetch_max(rss, Ordering::Relaxed);
                }
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        })
    };
    let mut flood = Vec::new();
    for _ in 0..args.connections {
        flood.push(tokio::spawn(flood_connection(
            server.clone(),
            args.calls,
            shared.clone(),
        )));
    }
    if args.watchers > 0 {
        let (addr, policy, shared) = (server.clone(), args.policy.clone(), shared.clone());
        let (watchers, sessions) = (args.watchers, args.watched_sessions);
        flood.push(tokio::spawn(async move {
            if let Err(e) = flood_watchers(addr, policy, watchers, sessions, shared).await {
                eprintln!("watchers: {e:#}");
            }
        }));
    }

    // The probe runs on a thread and runtime of its own, so that the flood's thousands of tasks
    // in this process do not queue ahead of it: its times are the server's.
    let end = Instant::now() + args.duration;
    let probing = {
        let (server, policy) = (server.clone(), args.policy.clone());
        let (every, steps) = (args.probe_every, args.probe_steps);
        std::thread::spawn(
            move || -> anyhow::Result<(u64, Vec<String>, Vec<Duration>)> {
                let runtime = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()?;
                runtime.block_on(async move {
                    let mut client = PracClient::new(channel(&server).await?);
                    let (mut probes, mut failures, mut firsts) = (0, Vec::new(), Vec::new());
                    let mut tick = tokio::time::interval(every);
                    while Instant::now() < end {
                        tick.tick().await;
                        probes += 1;
                        match probe(&mut client, &policy, obs_dim, steps).await {
                            Ok(first) => firsts.push(first),
                            Err(e) => failures.push(format!("{e:#}")),
                        }
                    }
                    Ok((probes, failures, firsts))
                })
            },
        )
    };
    let (probes, failures, mut firsts) = tokio::task::spawn_blocking(move || probing.join())
        .await?
        .map_err(|_| anyhow::anyhow!("the probe thread panicked"))??;
    shared.stop.store(true, Ordering::Relaxed);
    // Every flood call and connection ends here, so that the memory measured after is the
    // server's own.
    for mut task in flood {
        if tokio::time::timeout(Duration::from_secs(10), &mut task)
            .await
            .is_err()
        {
            task.abort();
        }
    }
    let _ = sampler.await;
    tokio::time::sleep(args.settle).await;
    let server_alive_after = probe_client
        .list_policies(proto::ListPoliciesRequest {})
        .await
        .is_ok();
    firsts.sort();
    let ms = |d: Option<&Duration>| d.map_or(0.0, |d| d.as_secs_f64() * 1e3);
    let report = Report {
        connections_made: shared.connections_made.load(Ordering::Relaxed),
        calls_opened: shared.calls_opened.load(Ordering::Relaxed),
        calls_ended: std::mem::take(&mut *shared.calls_ended.lock().await),
        watchers_opened: shared.watchers_opened.load(Ordering::Relaxed),
        watchers_ended: std::mem::take(&mut *shared.watchers_ended.lock().await),
        probes,
        probes_failed: failures.len() as u64,
        probe_failures: failures,
        probe_first_answer_ms_max: ms(firsts.last()),
        probe_first_answer_ms_p50: ms(firsts.get(firsts.len() / 2)),
        probes_over_1s: firsts
            .iter()
            .filter(|d| **d > Duration::from_secs(1))
            .count() as u64,
        server_rss_before_kib: rss_before,
        server_rss_max_kib: pid.map(|_| rss_max.load(Ordering::Relaxed)),
        server_rss_after_kib: rss_kib(pid),
        server_alive_after,
    };
    println!("{}", serde_json::to_string_pretty(&report)?);
    if let Some(local) = local {
        local.stop().await;
    }
    Ok(())
}
