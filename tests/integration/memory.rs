//! The memory budget (`--max-memory`): what each item costs, start-up refusals, shedding of
//! never-started calls and idle watchers, and memory given back after a flood.

use std::io::Write as _;
use std::path::Path;
use std::time::{Duration, Instant};

use prac::proto;

use crate::common::{
    self, Server, bundle_dir, grpc_frame, grpc_request, h2_connect, metrics_address,
    open_default_session, rss_kib, sample, scrape, tls_files,
};

/// Opens up to `count` StepStreams on `send` that send only their HEADERS (fewer if the
/// connection stops taking streams: GOAWAY); returns them with their response futures.
async fn header_only_calls(
    send: &h2::client::SendRequest<bytes::Bytes>,
    addr: &str,
    count: usize,
) -> Vec<(h2::client::ResponseFuture, h2::SendStream<bytes::Bytes>)> {
    let mut calls = Vec::new();
    for _ in 0..count {
        let Ok(mut ready) = send.clone().ready().await else {
            break;
        };
        let Ok(call) = ready.send_request(grpc_request(addr, "/prac.v1.Prac/StepStream"), false)
        else {
            break;
        };
        calls.push(call);
    }
    calls
}

/// A raw HTTP/2 connection: its request handle and the task that holds its socket.
type RawConnection = (
    h2::client::SendRequest<bytes::Bytes>,
    tokio::task::JoinHandle<Result<(), h2::Error>>,
);

/// Closes raw HTTP/2 connections.
fn close(connections: Vec<RawConnection>) {
    for (_, task) in connections {
        task.abort();
    }
}

/// The shipped bundles, one folder each.
fn shipped(name: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let from = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("bundles/{name}.safetensors"));
    std::fs::copy(from, dir.path().join(format!("{name}.safetensors"))).unwrap();
    dir
}

const SHIPPED: [&str; 7] = [
    "pendulum", "lander", "hopper", "walker", "cheetah", "ant", "humanoid",
];

async fn settle() {
    tokio::time::sleep(Duration::from_millis(700)).await;
}

/// Not a test: the per-item costs of docs/operations.md ("Memory budget"), written to
/// `results/memory/item-costs.json`. Run with `cargo test --release --test integration
/// memory::measure_item_costs -- --ignored --nocapture`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "a measurement; writes results/memory/item-costs.json"]
async fn measure_item_costs() {
    let big = ["--max-memory", "16Gi", "--max-connections", "4000"];
    let mut report = serde_json::Map::new();
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .unwrap_or_default()
        .lines()
        .find_map(|l| {
            l.strip_prefix("model name")
                .map(|v| v.trim_start_matches([' ', '\t', ':']).to_string())
        })
        .unwrap_or_default();
    report.insert("cpu".into(), cpu.into());
    let mut put = |key: &str, value: serde_json::Value| {
        println!("{key}: {value}");
        report.insert(key.to_string(), value);
    };

    // The runtime: a server with no bundle.
    let empty = tempfile::tempdir().unwrap();
    let server = Server::start(empty.path(), &big);
    tokio::time::sleep(Duration::from_secs(1)).await;
    put("runtime_kib", rss_kib(server.child.id()).into());
    drop(server);

    // Connections, calls and watchers on the toy bundle.
    let bundles = bundle_dir();
    let server = Server::start(bundles.path(), &big);
    server.wait_serving().await;
    let pid = server.child.id();
    settle().await;
    let base = rss_kib(pid);
    let mut connections = Vec::new();
    for _ in 0..1000 {
        connections.push(h2_connect(&server.addr).await);
    }
    settle().await;
    let with_connections = rss_kib(pid);
    put(
        "connection_kib",
        ((with_connections - base) as f64 / 1000.0).into(),
    );
    let mut calls = Vec::new();
    for (send, _) in connections.iter().take(8) {
        calls.extend(header_only_calls(send, &server.addr, 250).await);
    }
    settle().await;
    let with_calls = rss_kib(pid);
    put(
        "header_only_call_kib",
        ((with_calls - with_connections) as f64 / 2000.0).into(),
    );
    drop(calls);
    close(connections);
    drop(server);

    // Watchers, on a fresh server (a heap that just freed calls would take them without
    // growing): 10,000 over 10 sessions, on 50 connections.
    let server = Server::start(bundles.path(), &big);
    server.wait_serving().await;
    let pid = server.child.id();
    let mut client = server.client().await;
    let mut sessions = Vec::new();
    for _ in 0..10 {
        sessions.push(open_default_session(&mut client, "toy").await);
    }
    let mut connections = Vec::new();
    for _ in 0..50 {
        connections.push(h2_connect(&server.addr).await);
    }
    settle().await;
    let before_watchers = rss_kib(pid);
    let mut watchers = Vec::new();
    for (i, (send, _)) in connections.iter().enumerate() {
        for _ in 0..200 {
            let mut ready = send.clone().ready().await.unwrap();
            let (response, mut body) = ready
                .send_request(grpc_request(&server.addr, "/prac.v1.Prac/WatchPlan"), false)
                .unwrap();
            let request = proto::WatchPlanRequest {
                session_id: sessions[i % sessions.len()].clone(),
            };
            body.send_data(grpc_frame(&request), true).unwrap();
            watchers.push(response);
        }
    }
    settle().await;
    put(
        "watcher_kib",
        ((rss_kib(pid) as f64 - before_watchers as f64) / 10_000.0).into(),
    );
    // Each is a live watcher: answered with its first plan, no status.
    for response in watchers.drain(..3) {
        let response = response.await.unwrap();
        assert!(
            response.headers().get("grpc-status").is_none(),
            "{response:?}"
        );
    }
    drop(watchers);
    close(connections);
    drop(server);

    // TLS connections.
    let (_, cert, key) = tls_files(bundles.path());
    let server = Server::start(
        bundles.path(),
        &[
            "--max-memory",
            "16Gi",
            "--tls-cert",
            cert.to_str().unwrap(),
            "--tls-key",
            key.to_str().unwrap(),
        ],
    );
    // A plaintext health check cannot reach a TLS port: the toy bundle loads at once.
    tokio::time::sleep(Duration::from_secs(1)).await;
    let pid = server.child.id();
    let cert_pem = std::fs::read_to_string(&cert).unwrap();
    settle().await;
    let base = rss_kib(pid);
    let mut channels = Vec::new();
    for _ in 0..300 {
        let mut client =
            prac::proto::prac_client::PracClient::new(server.tls_channel(&cert_pem).await);
        client
            .list_policies(proto::ListPoliciesRequest {})
            .await
            .unwrap();
        channels.push(client);
    }
    settle().await;
    put(
        "tls_connection_kib",
        ((rss_kib(pid) - base) as f64 / 300.0).into(),
    );
    drop(channels);
    drop(server);

    // Sessions and bundles, per shipped bundle: 1,000 sessions at max_horizon 32 kept full.
    let mut per_bundle = serde_json::Map::new();
    for name in SHIPPED {
        let dir = shipped(name);
        let empty_rss = report["runtime_kib"].as_u64().unwrap();
        let server = Server::start(dir.path(), &big);
        server.wait_serving().await;
        let pid = server.child.id();
        let mut client = server.client().await;
        let policy = client
            .list_policies(proto::ListPoliciesRequest {})
            .await
            .unwrap()
            .into_inner()
            .policies
            .remove(0);
        let obs = vec![0.0f32; policy.obs_dim as usize];
        // Every replanning thread once, so each has its workspace.
        let warm = open_session(&mut client, name).await;
        for _ in 0..64 {
            step(&mut client, &warm, &obs).await;
        }
        settle().await;
        let loaded = rss_kib(pid);
        let mut ids = Vec::new();
        for _ in 0..1000 {
            ids.push(open_session(&mut client, name).await);
        }
        for id in &ids {
            for _ in 0..33 {
                step(&mut client, id, &obs).await;
            }
        }
        settle().await;
        let with_sessions = rss_kib(pid);
        let entry = serde_json::json!({
            "obs_dim": policy.obs_dim,
            "act_dim": policy.act_dim,
            "bundle_kib": loaded.saturating_sub(empty_rss),
            "session_kib": (with_sessions - loaded) as f64 / 1000.0,
        });
        println!("{name}: {entry}");
        per_bundle.insert(name.to_string(), entry);
    }
    report.insert("bundles".into(), per_bundle.into());
    let out = Path::new(env!("CARGO_MANIFEST_DIR")).join("results/memory/item-costs.json");
    std::fs::create_dir_all(out.parent().unwrap()).unwrap();
    let mut file = std::fs::File::create(&out).unwrap();
    writeln!(
        file,
        "{}",
        serde_json::to_string_pretty(&serde_json::Value::Object(report)).unwrap()
    )
    .unwrap();
}

/// A session whose plan always holds 32 actions (an eps no plan fails, fixed growth).
async fn open_session(
    client: &mut prac::proto::prac_client::PracClient<tonic::transport::Channel>,
    policy: &str,
) -> String {
    client
        .open_session(proto::OpenSessionRequest {
            local_steps: 0,
            policy: policy.into(),
            options: Some(proto::SessionOptions {
                tolerance: Some(proto::session_options::Tolerance::Epsilon(1e9)),
                growth: Some(proto::session_options::Growth::Fixed(32)),
                ..Default::default()
            }),
            resume: None,
        })
        .await
        .unwrap()
        .into_inner()
        .session_id
}

async fn step(
    client: &mut prac::proto::prac_client::PracClient<tonic::transport::Channel>,
    id: &str,
    obs: &[f32],
) {
    client
        .step(proto::StepRequest {
            session_id: id.to_string(),
            observation: obs.to_vec(),
            new_episode: false,
        })
        .await
        .unwrap();
}

/// The grpc-status a call ended with (headers of a trailers-only answer, else its trailers),
/// or what ended it instead.
async fn ending(response: h2::client::ResponseFuture) -> String {
    let response = match response.await {
        Ok(response) => response,
        Err(e) => {
            return match e.reason() {
                Some(reason) => format!("reset {reason:?}"),
                None if e.is_go_away() => "goaway".into(),
                None => format!("transport: {e}"),
            };
        }
    };
    if let Some(status) = response.headers().get("grpc-status") {
        return status.to_str().unwrap().to_string();
    }
    let mut body = response.into_body();
    while let Some(chunk) = body.data().await {
        match chunk {
            Ok(chunk) => {
                let _ = body.flow_control().release_capacity(chunk.len());
            }
            Err(e) => return format!("reset {:?}", e.reason()),
        }
    }
    match body.trailers().await {
        Ok(Some(trailers)) => trailers
            .get("grpc-status")
            .map_or("no status".into(), |v| v.to_str().unwrap().to_string()),
        Ok(None) => "no trailers".into(),
        Err(e) => format!("reset {:?}", e.reason()),
    }
}

#[test]
fn start_up_refuses_a_budget_that_cannot_hold_the_bundles_or_the_sessions() {
    let hopper = shipped("humanoid");
    let run = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_prac"))
            .args(["serve", "--listen", "127.0.0.1:0", "--bundles"])
            .arg(hopper.path())
            .args(args)
            .output()
            .unwrap();
        (out.status, String::from_utf8_lossy(&out.stderr).to_string())
    };
    // Below what the runtime and the bundle need.
    let (status, stderr) = run(&["--max-memory", "24Mi"]);
    assert!(!status.success(), "{stderr}");
    assert!(
        stderr.contains("raise --max-memory") && stderr.contains("24.0 MiB"),
        "{stderr}"
    );
    // Sessions that alone exceed the clients' budget: both numbers and the flags are named.
    let (status, stderr) = run(&["--max-memory", "96Mi", "--max-sessions", "100000"]);
    assert!(!status.success(), "{stderr}");
    assert!(
        stderr.contains("--max-sessions 100000")
            && stderr.contains("lower --max-sessions to at most")
            && stderr.contains("raise --max-memory"),
        "{stderr}"
    );
    // Bad sizes: named, never taken as unlimited.
    for bad in ["0", "-5Mi", "lots"] {
        let (status, stderr) = run(&[&format!("--max-memory={bad}")]);
        assert!(!status.success(), "{bad}: {stderr}");
        assert!(stderr.contains("--max-memory"), "{bad}: {stderr}");
    }
}

/// 40 connections x 250 header-only StepStreams against a 48 MiB budget: the server stays under
/// it, every flood call ends with a clean RESOURCE_EXHAUSTED (or is refused by GOAWAY), a real
/// client opens a session and steps within a second throughout, and the memory comes back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_never_started_calls_is_shed_and_a_real_client_still_steps() {
    let bundles = bundle_dir();
    let limit_kib = 48 * 1024;
    let server = Server::start(
        bundles.path(),
        &["--max-memory", "48Mi", "--metrics-listen", "127.0.0.1:0"],
    );
    server.wait_serving().await;
    let metrics = metrics_address(&server);
    let pid = server.child.id();
    let mut client = server.client().await;
    // One session stepping before the flood: kept throughout.
    let kept = open_default_session(&mut client, "toy").await;
    step_toy(&mut client, &kept, true).await.unwrap();
    settle().await;
    let before = rss_kib(pid);

    let mut connections = Vec::new();
    let mut endings = Vec::new();
    let mut peak = before;
    let started = Instant::now();
    let mut worst_probe = Duration::ZERO;
    for round in 0..40 {
        let (send, task) = h2_connect(&server.addr).await;
        for (response, body) in header_only_calls(&send, &server.addr, 250).await {
            endings.push(tokio::spawn(async move {
                let _body = body;
                ending(response).await
            }));
        }
        connections.push((send, task));
        peak = peak.max(rss_kib(pid));
        if round % 4 == 3 {
            // A real client: a new session and its first step, and the kept session's step.
            let probe = Instant::now();
            let id = open_default_session(&mut client, "toy").await;
            step_toy(&mut client, &id, true).await.unwrap();
            worst_probe = worst_probe.max(probe.elapsed());
            step_toy(&mut client, &kept, false).await.unwrap();
        }
    }
    for _ in 0..20 {
        peak = peak.max(rss_kib(pid));
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let text = scrape(&metrics);
    let reset = sample(&text, "prac_memory_shed_total{action=\"call_reset\"}");
    let goaway = sample(&text, "prac_memory_shed_total{action=\"goaway\"}");
    eprintln!(
        "flood of 10,000 calls in {:?}: RSS {before} KiB before, peak {peak} KiB; {reset} reset, \
         {goaway} GOAWAY; worst probe {worst_probe:?}",
        started.elapsed()
    );
    assert!(reset > 0.0 && goaway > 0.0, "{text}");
    assert!(
        peak < limit_kib,
        "the server reached {peak} KiB under a 48 MiB budget"
    );
    assert!(
        worst_probe < Duration::from_secs(1),
        "a real client waited {worst_probe:?}"
    );

    // Every flood call ended cleanly: RESOURCE_EXHAUSTED (8), refused by its connection's
    // GOAWAY, or still waiting on a connection that never needed shedding.
    close(connections);
    let mut by_ending = std::collections::BTreeMap::<String, usize>::new();
    for ending in endings {
        let ended = tokio::time::timeout(Duration::from_secs(10), ending)
            .await
            .expect("every call ends once its connection closes")
            .unwrap();
        *by_ending.entry(ended).or_default() += 1;
    }
    eprintln!("flood calls by ending: {by_ending:?}");
    assert!(by_ending.get("8").is_some_and(|n| *n > 0), "{by_ending:?}");
    // "reset None": still waiting when this client closed its connection (never shed); "reset
    // NO_ERROR": the server's RST_STREAM after an answered call whose request was still open,
    // read by h2 before the answer's trailers (RFC 9113, 8.1).
    for ended in by_ending.keys() {
        assert!(
            [
                "8",
                "goaway",
                "reset None",
                "reset NO_ERROR",
                "reset Some(REFUSED_STREAM)"
            ]
            .contains(&ended.as_str()),
            "a flood call ended with {ended}: {by_ending:?}"
        );
    }

    // Memory comes back once the connections are gone, and the kept session still steps.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let after = rss_kib(pid);
    eprintln!("RSS after the flood: {after} KiB ({before} KiB before)");
    assert!(
        after < before + 6 * 1024,
        "the server held {after} KiB after the flood, {before} KiB before"
    );
    step_toy(&mut client, &kept, false).await.unwrap();
}

async fn step_toy(
    client: &mut prac::proto::prac_client::PracClient<tonic::transport::Channel>,
    id: &str,
    new_episode: bool,
) -> Result<(), tonic::Status> {
    client
        .step(proto::StepRequest {
            session_id: id.to_string(),
            observation: vec![0.1; common::OBS],
            new_episode,
        })
        .await
        .map(|_| ())
}

/// Watchers of sessions that never step are ended to make room; the watcher of a stepping
/// session is kept, and a new session can still be opened.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_watchers_are_shed_before_stepping_sessions() {
    let bundles = bundle_dir();
    let server = Server::start(
        bundles.path(),
        &["--max-memory", "48Mi", "--metrics-listen", "127.0.0.1:0"],
    );
    server.wait_serving().await;
    let metrics = metrics_address(&server);
    let mut client = server.client().await;
    let stepping = open_default_session(&mut client, "toy").await;
    step_toy(&mut client, &stepping, true).await.unwrap();
    let mut watched = client
        .watch_plan(proto::WatchPlanRequest {
            session_id: stepping.clone(),
        })
        .await
        .unwrap()
        .into_inner();
    watched.message().await.unwrap().unwrap();
    let idle = open_default_session(&mut client, "toy").await;

    // Watchers of the idle session, on 40 connections, until the budget sheds them.
    let mut endings = Vec::new();
    let mut connections = Vec::new();
    for _ in 0..40 {
        let (send, task) = h2_connect(&server.addr).await;
        for _ in 0..250 {
            let Ok(mut ready) = send.clone().ready().await else {
                break;
            };
            let Ok((response, mut body)) =
                ready.send_request(grpc_request(&server.addr, "/prac.v1.Prac/WatchPlan"), false)
            else {
                break;
            };
            let request = proto::WatchPlanRequest {
                session_id: idle.clone(),
            };
            let _ = body.send_data(grpc_frame(&request), true);
            endings.push(tokio::spawn(ending(response)));
        }
        connections.push((send, task));
        // The stepping session steps on: its watcher is never idle.
        step_toy(&mut client, &stepping, false).await.unwrap();
        watched.message().await.unwrap().unwrap();
    }
    // The 10,000 calls reach the server over seconds when other tests share the cores.
    let give_up = std::time::Instant::now() + Duration::from_secs(30);
    loop {
        tokio::time::sleep(Duration::from_millis(500)).await;
        let text = scrape(&metrics);
        let shed = sample(&text, "prac_memory_shed_total{action=\"watcher_reset\"}")
            + sample(&text, "prac_memory_shed_total{action=\"watcher_refused\"}")
            + sample(&text, "prac_memory_shed_total{action=\"call_refused\"}");
        if shed > 0.0 {
            break;
        }
        assert!(std::time::Instant::now() < give_up, "nothing shed: {text}");
    }
    // The stepping session's watcher still gets each new plan, and sessions still open.
    step_toy(&mut client, &stepping, false).await.unwrap();
    tokio::time::timeout(Duration::from_secs(2), watched.message())
        .await
        .expect("the stepping session's watcher is kept")
        .unwrap()
        .unwrap();
    open_default_session(&mut client, "toy").await;
    close(connections);
    let mut resource_exhausted = 0;
    for ending in endings {
        if tokio::time::timeout(Duration::from_secs(10), ending)
            .await
            .unwrap()
            .unwrap()
            == "8"
        {
            resource_exhausted += 1;
        }
    }
    assert!(resource_exhausted > 0);
    // The watchers whose clients went away end with them, though their session never steps:
    // only the stepping session's watcher is still charged.
    let watcher = "prac_memory_charged_bytes{item=\"watcher\"}";
    let deadline = Instant::now() + Duration::from_secs(5);
    while sample(&scrape(&metrics), watcher) > 1024.0 {
        assert!(
            Instant::now() < deadline,
            "watchers of gone clients still held: {}",
            scrape(&metrics)
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}
