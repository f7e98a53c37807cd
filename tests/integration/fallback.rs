//! Link loss past the held plan: a `ResumingSession` with the bundle on board goes on locally
//! while no server answers, giving the very answers a server resumed from the same plan gives
//! (prac's own session and Replan, in-process), and resumes on a server that answers again from
//! the local plan. A fallback that is not the server's bundle is refused at open.

use std::process::Command;
use std::time::Duration;

use crate::common;

use common::{OBS, Server, bundle_dir};
use prac::client::{Fallback, ResumingSession};
use prac::proto::{self, session_options::Tolerance};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tonic::Code;

fn options() -> proto::SessionOptions {
    proto::SessionOptions {
        tolerance: Some(Tolerance::Epsilon(0.05)),
        max_horizon: 12,
        ..Default::default()
    }
}

/// A server on `addr` (a fixed port, so that a restarted one is found where the first was).
fn serve_at(addr: &str, bundles: &std::path::Path) -> Server {
    let mut command = Command::new(env!("CARGO_BIN_EXE_prac"));
    command
        .args(["serve", "--listen", addr, "--metrics-listen", "127.0.0.1:0"])
        .arg("--bundles")
        .arg(bundles);
    Server::spawn(command)
}

/// A free address below the ephemeral port range: a client that keeps connecting to a port in
/// that range while nothing listens can be handed it as its own source port (a TCP
/// self-connect) and hold it against the server restarting there.
fn free_address() -> String {
    let range = std::fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range")
        .unwrap_or_else(|_| "32768 60999".into());
    let low: u16 = range
        .split_whitespace()
        .next()
        .and_then(|v| v.parse().ok())
        .unwrap_or(32768);
    let mut rng = ChaCha8Rng::seed_from_u64(u64::from(std::process::id()));
    (0..100)
        .map(|_| rng.random_range(low / 2..low))
        .find_map(|port| std::net::TcpListener::bind(("127.0.0.1", port)).ok())
        .expect("a free port below the ephemeral range")
        .local_addr()
        .unwrap()
        .to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_goes_on_locally_while_no_server_answers_and_resumes_when_one_does() {
    let bundles = bundle_dir();
    let addr = free_address();
    let mut server = serve_at(&addr, bundles.path());
    server.wait_serving().await;
    let fallback = Fallback::load(&bundles.path().join("toy.safetensors")).unwrap();
    let client = prac::client::connect(&server.addr).await.unwrap();
    let mut session =
        ResumingSession::open_with_fallback(client, "toy", Some(options()), None, fallback)
            .await
            .unwrap();
    session.patience = Duration::from_millis(300);
    session.probe_every = Duration::from_millis(200);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let observations: Vec<Vec<f32>> = (0..70)
        .map(|_| (0..OBS).map(|_| rng.random_range(-1.0..1.0)).collect())
        .collect();
    let (kill_at, restart_at) = (20, 40);
    let mut answers: Vec<prac::client::Answer> = Vec::new();
    let mut metrics = None;
    for (t, obs) in observations.iter().enumerate() {
        if t == kill_at {
            server.signal("KILL");
            server.wait_exit(Duration::from_secs(10)).unwrap();
        }
        if t == restart_at {
            server = serve_at(&addr, bundles.path());
            server.wait_serving().await;
            metrics = Some(common::metrics_address(&server));
        }
        let answer = session.step(obs, t == 0).await.unwrap();
        let r = &answer.response;
        assert_eq!(
            (r.step, r.episode),
            (t as u64, 0),
            "steps contiguous: {r:?}"
        );
        if let Some(previous) = answers.last() {
            // The action executed is the one committed for this step at the previous one.
            assert_eq!(r.action, previous.response.forecast[1].action, "step {t}");
        }
        answers.push(answer);
        // A 50 Hz control loop.
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let local: Vec<usize> = (0..answers.len()).filter(|&t| answers[t].local).collect();
    assert_eq!(
        local.first(),
        Some(&kill_at),
        "local from the first step no server answered"
    );
    let back = local.last().unwrap() + 1;
    assert!(
        (restart_at..answers.len() - 5).contains(&back),
        "served again soon after the restart: local {local:?}"
    );
    assert_eq!(local, (kill_at..back).collect::<Vec<_>>());
    assert_eq!(session.local_steps, local.len() as u64);
    assert!(!session.is_local() && session.resumes >= 1);
    // The resume reported the local steps to the server that took the session back.
    let text = common::scrape(&metrics.expect("restarted"));
    assert_eq!(
        common::sample(&text, "prac_local_steps_total{policy=\"toy\"}"),
        local.len() as f64
    );
    println!(
        "local steps {kill_at}..{back} ({} steps), served again {} steps after the restart",
        local.len(),
        back - restart_at
    );

    // The same bits: a server resumed from the plan held before the outage answers the same
    // observations exactly as the local session did.
    let reference = Server::start(bundles.path(), &[]);
    reference.wait_serving().await;
    let mut client = reference.client().await;
    let before = &answers[kill_at - 1].response;
    let id = client
        .open_session(proto::OpenSessionRequest {
            local_steps: 0,
            policy: "toy".into(),
            options: Some(options()),
            resume: Some(proto::Plan {
                session_id: String::new(),
                episode: before.episode,
                start_step: before.step,
                actions: before.forecast.clone(),
            }),
        })
        .await
        .unwrap()
        .into_inner()
        .session_id;
    for t in kill_at..back {
        let served = client
            .step(proto::StepRequest {
                session_id: id.clone(),
                observation: observations[t].clone(),
                new_episode: false,
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(
            served, answers[t].response,
            "step {t}: local and served differ"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fallback_that_is_not_the_servers_bundle_is_refused_at_open() {
    let bundles = bundle_dir();
    let server = Server::start(bundles.path(), &[]);
    server.wait_serving().await;
    let other = tempfile::tempdir().unwrap();
    let path = other.path().join("toy.safetensors");
    prac::bundle::save(&common::toy_policy("toy", 2), &path).unwrap();
    let fallback = Fallback::load(&path).unwrap();
    let refused = ResumingSession::open_with_fallback(
        server.client().await,
        "toy",
        Some(options()),
        None,
        fallback,
    )
    .await
    .err()
    .expect("refused");
    assert_eq!(refused.code(), Code::FailedPrecondition, "{refused:?}");
    assert!(
        refused.message().contains("content hash")
            || refused.message().contains("not the server's")
    );
}
