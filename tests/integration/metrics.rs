//! Prometheus metrics over HTTP: steps, latency histogram, open sessions and their limit, plan
//! breaks, forecast length, f_t, where steps were replanned, errors by status code, readiness and
//! the version, read from a real server's /metrics.

use crate::common;

use std::time::Duration;

use common::{OBS, Server, bundle_dir, http_get, metrics_address, sample, scrape};
use prac::proto;

/// A serving server with metrics on a free port, and the metrics address.
async fn with_metrics(bundles: &std::path::Path, args: &[&str]) -> (Server, String) {
    let args: Vec<&str> = ["--metrics-listen", "127.0.0.1:0"]
        .into_iter()
        .chain(args.iter().copied())
        .collect();
    let server = Server::start(bundles, &args);
    let addr = metrics_address(&server);
    server.wait_serving().await;
    (server, addr)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_count_steps_sessions_and_errors() {
    let bundles = bundle_dir();
    let (server, addr) = with_metrics(bundles.path(), &["--max-sessions", "7"]).await;
    let mut client = server.client().await;
    let mut ids = Vec::new();
    for _ in 0..2 {
        ids.push(common::open_default_session(&mut client, "toy").await);
    }
    let mut f_t = Vec::new();
    for k in 0..5 {
        let answer = client
            .step(proto::StepRequest {
                session_id: ids[0].clone(),
                observation: vec![0.1 * k as f32; OBS],
                new_episode: k == 0,
            })
            .await
            .unwrap()
            .into_inner();
        f_t.push(answer.f_t as f64);
    }
    client
        .close_session(proto::CloseSessionRequest {
            session_id: ids[1].clone(),
        })
        .await
        .unwrap();
    for bad in [vec![0.0; OBS + 1], vec![f32::NAN; OBS]] {
        client
            .step(proto::StepRequest {
                session_id: ids[0].clone(),
                observation: bad,
                new_episode: false,
            })
            .await
            .unwrap_err();
    }
    client
        .step(proto::StepRequest {
            session_id: "nope".into(),
            observation: vec![0.0; OBS],
            new_episode: false,
        })
        .await
        .unwrap_err();
    // OpenSession's refusals are counted too: an unknown policy and an empty resumed plan.
    for (policy, resume) in [("nope", None), ("toy", Some(proto::Plan::default()))] {
        client
            .open_session(proto::OpenSessionRequest {
                local_steps: 0,
                policy: policy.into(),
                options: None,
                resume,
            })
            .await
            .unwrap_err();
    }

    let text = scrape(&addr);
    assert_eq!(sample(&text, "prac_steps_total{policy=\"toy\"}"), 5.0);
    assert_eq!(sample(&text, "prac_step_latency_seconds_count"), 5.0);
    assert!(sample(&text, "prac_step_latency_seconds_sum") > 0.0);
    assert_eq!(sample(&text, "prac_forecast_length_count"), 5.0);
    // The plan grows by one per step while it holds, and a break starts it again.
    let forecast_sum = sample(&text, "prac_forecast_length_sum");
    assert!((5.0..=5.0 * 6.0).contains(&forecast_sum), "{forecast_sum}");
    assert!(sample(&text, "prac_plan_breaks_total") <= 4.0);
    assert_eq!(sample(&text, "prac_f_t_count"), 5.0);
    assert_eq!(sample(&text, "prac_f_t_sum"), f_t.iter().sum::<f64>());
    assert_eq!(sample(&text, "prac_open_sessions"), 1.0);
    assert_eq!(sample(&text, "prac_max_sessions"), 7.0);
    assert_eq!(sample(&text, "prac_serving"), 1.0);
    let version = format!(
        "prac_build_info{{version=\"{}\"}}",
        env!("CARGO_PKG_VERSION")
    );
    assert_eq!(sample(&text, &version), 1.0);
    assert_eq!(sample(&text, "prac_sessions_opened_total"), 2.0);
    assert_eq!(
        sample(&text, "prac_errors_total{code=\"InvalidArgument\"}"),
        3.0
    );
    assert_eq!(sample(&text, "prac_errors_total{code=\"NotFound\"}"), 2.0);
    assert_eq!(sample(&text, "prac_session_evictions_total"), 0.0);
    // One session's steps never overlap: each is replanned alone, in its handler.
    assert_eq!(sample(&text, "prac_replanned_total{by=\"handler\"}"), 5.0);
    assert!(!text.contains("prac_replanned_total{by=\"batch_worker\"}"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn readiness_is_zero_while_no_bundle_is_loaded_and_one_once_one_is() {
    let empty = tempfile::tempdir().unwrap();
    let server = Server::start(empty.path(), &["--metrics-listen", "127.0.0.1:0"]);
    let addr = metrics_address(&server);
    assert_eq!(sample(&scrape(&addr), "prac_serving"), 0.0);
    assert!(http_get(&addr, "/readyz").starts_with("HTTP/1.1 503"));
    // A bundle arrives and SIGHUP loads it.
    let bundles = bundle_dir();
    for entry in std::fs::read_dir(bundles.path()).unwrap() {
        let path = entry.unwrap().path();
        std::fs::copy(&path, empty.path().join(path.file_name().unwrap())).unwrap();
    }
    server.signal("HUP");
    server.wait_serving().await;
    assert_eq!(sample(&scrape(&addr), "prac_serving"), 1.0);
    let ready = http_get(&addr, "/readyz");
    assert!(
        ready.starts_with("HTTP/1.1 200") && ready.ends_with("SERVING\n"),
        "{ready}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_batch_window_sends_every_step_to_the_batch_workers() {
    let bundles = bundle_dir();
    let (server, addr) = with_metrics(bundles.path(), &["--batch-window", "1ms"]).await;
    let mut client = server.client().await;
    let id = common::open_default_session(&mut client, "toy").await;
    for k in 0..3 {
        client
            .step(proto::StepRequest {
                session_id: id.clone(),
                observation: vec![0.1 * k as f32; OBS],
                new_episode: k == 0,
            })
            .await
            .unwrap();
    }
    let text = scrape(&addr);
    assert_eq!(
        sample(&text, "prac_replanned_total{by=\"batch_worker\"}"),
        3.0
    );
    assert!(!text.contains("prac_replanned_total{by=\"handler\"}"));
}

/// Silent clients beyond the metrics endpoint's cap of 64 connections: each new one is admitted
/// by shedding the oldest that has sent no request, and a scraper still gets its answer.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_metrics_endpoint_sheds_silent_clients_beyond_64_and_still_answers_a_scraper() {
    let bundles = bundle_dir();
    let mut command = std::process::Command::new(env!("CARGO_BIN_EXE_prac"));
    command
        .env("RUST_LOG", "prac=debug")
        .args(["serve", "--listen", "127.0.0.1:0", "--bundles"])
        .arg(bundles.path())
        .args(["--metrics-listen", "127.0.0.1:0"]);
    let server = Server::spawn(command);
    let addr = metrics_address(&server);
    server.wait_serving().await;
    let silent: Vec<std::net::TcpStream> = (0..74)
        .map(|_| std::net::TcpStream::connect(&addr).unwrap())
        .collect();
    // Answered although 74 silent connections came first.
    let text = scrape(&addr);
    assert!(text.contains("prac_serving 1"), "{text}");
    // Ten silent ones beyond the cap, and one more for the scraper, were shed to admit the
    // newer ones (a silent connection's own deadline is logged otherwise).
    let shed = |log: &str| log.matches("metrics connection shed at the cap").count();
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    while shed(&server.stderr()) < 11 && std::time::Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(shed(&server.stderr()), 11, "{}", server.stderr());
    drop(silent);
}

/// Whether a step is worth handing to a batch worker is judged by its network FLOPs, which do
/// not depend on where it ran: robots stepping together on a trained Hopper's PrAC plans are
/// replanned together, not alternately in their handlers whenever batching had made them look
/// cheap.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_prac_steps_of_a_trained_policy_are_replanned_by_the_batch_workers() {
    const ROBOTS: usize = 4;
    const STEPS: usize = 40;
    let dir = tempfile::tempdir().unwrap();
    let shipped = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("bundles");
    std::fs::copy(
        shipped.join("hopper.safetensors"),
        dir.path().join("hopper.safetensors"),
    )
    .unwrap();
    // One batch worker: with several, a session that alone lands on its worker has nothing to
    // batch with and is replanned in its handler, as it should be, whatever the FLOPs.
    let (server, addr) = with_metrics(dir.path(), &["--batch-workers", "1"]).await;
    let mut robots = Vec::new();
    for seed in 0..ROBOTS as u64 {
        let mut client = server.client().await;
        robots.push(tokio::spawn(async move {
            let id = client
                .open_session(proto::OpenSessionRequest {
                    local_steps: 0,
                    policy: "hopper".into(),
                    options: Some(proto::SessionOptions {
                        tolerance: Some(proto::session_options::Tolerance::EpsilonCoef(0.005)),
                        ..Default::default()
                    }),
                    resume: None,
                })
                .await
                .unwrap()
                .into_inner()
                .session_id;
            let mut env = prac::domains::make("hopper").unwrap();
            let mut observation = vec![0.0; env.spec().obs_dim];
            env.reset(seed, &mut observation).unwrap();
            let mut new_episode = true;
            for _ in 0..STEPS {
                let answer = client
                    .step(proto::StepRequest {
                        session_id: id.clone(),
                        observation: observation.clone(),
                        new_episode,
                    })
                    .await
                    .unwrap()
                    .into_inner();
                let moved = env.step(&answer.action, &mut observation).unwrap();
                new_episode = moved.terminated || moved.truncated;
                if new_episode {
                    env.reset(seed, &mut observation).unwrap();
                }
            }
        }));
    }
    for robot in robots {
        robot.await.unwrap();
    }
    let text = scrape(&addr);
    let by = |place: &str| {
        let name = format!("prac_replanned_total{{by=\"{place}\"}}");
        if text.contains(&name) {
            sample(&text, &name)
        } else {
            0.0
        }
    };
    let (worker, handler) = (by("batch_worker"), by("handler"));
    assert_eq!(worker + handler, (ROBOTS * STEPS) as f64);
    assert!(
        worker >= 0.9 * (ROBOTS * STEPS) as f64,
        "{worker} steps by the batch workers, {handler} in handlers"
    );
}
