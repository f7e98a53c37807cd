//! The real `prac serve` binary on an ephemeral port, driven by a tonic client.

use crate::common;

use std::time::Duration;

use common::{ACT, OBS, Server, bundle_dir, toy_policy};
use prac::proto::{self, session_options::Growth, session_options::Tolerance};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;

fn options(
    tolerance: Option<Tolerance>,
    growth: Option<Growth>,
    max_horizon: u32,
) -> proto::SessionOptions {
    proto::SessionOptions {
        tolerance,
        growth,
        max_horizon,
        sampled: false,
        seed: 0,
        guard: None,
    }
}

async fn open(
    client: &mut prac::proto::prac_client::PracClient<tonic::transport::Channel>,
    options: proto::SessionOptions,
) -> String {
    client
        .open_session(proto::OpenSessionRequest {
            local_steps: 0,
            policy: "toy".into(),
            options: Some(options),
            resume: None,
        })
        .await
        .unwrap()
        .into_inner()
        .session_id
}

fn step_request(session: &str, observation: Vec<f32>, new_episode: bool) -> proto::StepRequest {
    proto::StepRequest {
        session_id: session.to_string(),
        observation,
        new_episode,
    }
}

/// The environment of these tests: the model's own prediction plus noise, so plans sometimes hold
/// and sometimes break.
fn next_observation(response: &proto::StepResponse, rng: &mut ChaCha8Rng) -> Vec<f32> {
    response.forecast[0]
        .predicted_observation
        .iter()
        .map(|v| (v + rng.random_range(-0.05..0.05)).clamp(-3.0, 3.0))
        .collect()
}

/// Checks one response against the previous one: the committed plan was honoured.
fn check_response(
    prev: Option<&proto::StepResponse>,
    r: &proto::StepResponse,
    max_horizon: usize,
    low: &[f32],
    high: &[f32],
) {
    assert!(!r.forecast.is_empty() && r.forecast.len() <= max_horizon);
    assert_eq!(r.action, r.forecast[0].action);
    assert_eq!(r.f_t, r.step + 1 - r.forecast[0].decided_at);
    for planned in &r.forecast {
        assert_eq!(planned.action.len(), ACT);
        assert_eq!(planned.predicted_observation.len(), OBS);
        assert!(planned.decided_at <= r.step);
        for i in 0..ACT {
            assert!(planned.action[i] >= low[i] && planned.action[i] <= high[i]);
        }
    }
    let kept = r.kept as usize;
    match prev {
        Some(prev) if r.step == prev.step + 1 => {
            // The kept actions are exactly the old plan after the executed action.
            assert!(kept < prev.forecast.len());
            for j in 0..kept {
                assert_eq!(r.forecast[j].action, prev.forecast[j + 1].action);
                assert_eq!(r.forecast[j].decided_at, prev.forecast[j + 1].decided_at);
            }
            if let Some(broke) = r.broke_at {
                assert_eq!(broke as usize, kept);
            } else {
                assert!(kept == prev.forecast.len() - 1 || kept == max_horizon);
            }
            // What Replan appended was decided now.
            for planned in &r.forecast[kept..] {
                assert_eq!(planned.decided_at, r.step);
            }
        }
        _ => {
            assert_eq!((r.step, kept, r.broke_at), (0, 0, None));
            assert!(r.forecast.iter().all(|p| p.decided_at == 0));
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn list_open_stream_unary_plan_and_watch() {
    list_open_stream_unary_plan_and_watch_with(&[]).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn list_open_stream_unary_plan_and_watch_without_batching() {
    list_open_stream_unary_plan_and_watch_with(&["--batch-max", "0"]).await;
}

async fn list_open_stream_unary_plan_and_watch_with(args: &[&str]) {
    let dir = bundle_dir();
    let server = Server::start(dir.path(), args);
    server.wait_serving().await;
    let mut client = server.client().await;

    let policies = client
        .list_policies(proto::ListPoliciesRequest {})
        .await
        .unwrap()
        .into_inner()
        .policies;
    assert_eq!(policies.len(), 1);
    let toy = &policies[0];
    assert_eq!((toy.name.as_str(), toy.domain.as_str()), ("toy", "toy"));
    // No control period for a domain prac does not know.
    assert_eq!(toy.control_period, None);
    assert!(toy.observation_features.is_empty() && toy.action_features.is_empty());
    assert_eq!((toy.obs_dim, toy.act_dim), (OBS as u32, ACT as u32));
    assert_eq!(toy.action_low, vec![-2.0, 0.0]);
    assert_eq!(toy.action_high, vec![2.0, 1.0]);
    assert_eq!(toy.gamma, 0.98);
    assert_eq!(toy.q_aggregation, "min");
    let scale = toy.value_scale.unwrap();
    assert_eq!((scale.v_pi, scale.v_rand), (10.0, -10.0));
    let file = std::fs::read(dir.path().join("toy.safetensors")).unwrap();
    assert_eq!(toy.content_hash, prac::bundle::content_hash(&file));

    // eps = 0.0002 * (10 - (-10)) = 0.004.
    let opened = client
        .open_session(proto::OpenSessionRequest {
            local_steps: 0,
            policy: "toy".into(),
            options: Some(options(Some(Tolerance::EpsilonCoef(0.0002)), None, 12)),
            resume: None,
        })
        .await
        .unwrap()
        .into_inner();
    let session = opened.session_id.clone();
    assert_eq!(session.len(), 32);
    let resolved = opened.options.unwrap();
    assert!((resolved.epsilon - 0.004).abs() < 1e-6);
    assert_eq!(
        (
            resolved.growth_mode.as_str(),
            resolved.growth,
            resolved.max_horizon
        ),
        ("grow", 2, 12)
    );

    // 1000 streamed steps, an episode every 250 steps, one response per request, in order.
    let (tx, rx) = mpsc::channel(4);
    let mut responses = client
        .step_stream(ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut obs = vec![0.1f32, -0.2, 0.3];
    let mut prev: Option<proto::StepResponse> = None;
    let (mut breaks, mut holds, mut f_sum) = (0, 0, 0u64);
    for i in 0..1000u64 {
        let new_episode = i % 250 == 0;
        if new_episode {
            obs = (0..OBS).map(|_| rng.random_range(-1.0..1.0)).collect();
        }
        tx.send(step_request(&session, obs.clone(), new_episode))
            .await
            .unwrap();
        let r = responses
            .message()
            .await
            .unwrap()
            .expect("one response per request");
        assert_eq!(r.step, i % 250, "in order");
        assert_eq!(r.episode, i / 250);
        check_response(
            prev.as_ref().filter(|_| !new_episode),
            &r,
            12,
            &toy.action_low,
            &toy.action_high,
        );
        if r.broke_at.is_some() {
            breaks += 1;
        } else if r.step > 0 {
            holds += 1;
        }
        f_sum += r.f_t;
        obs = next_observation(&r, &mut rng);
        prev = Some(r);
    }
    drop(tx);
    assert!(
        responses.message().await.unwrap().is_none(),
        "stream ends with the requests"
    );
    // The noise makes this eps both keep and break plans: both paths are exercised.
    assert!(breaks > 0 && holds > 0, "breaks {breaks} holds {holds}");
    assert!(f_sum > 1000, "mean forecast above 1");

    // Unary steps continue the same episode.
    let last = prev.unwrap();
    let r = client
        .step(step_request(&session, obs.clone(), false))
        .await
        .unwrap()
        .into_inner();
    assert_eq!((r.step, r.episode), (last.step + 1, last.episode));
    check_response(Some(&last), &r, 12, &toy.action_low, &toy.action_high);

    // GetPlan returns the committed plan of the last step.
    let plan = client
        .get_plan(proto::GetPlanRequest {
            session_id: session.clone(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(plan.session_id, session);
    assert_eq!((plan.start_step, plan.episode), (r.step, r.episode));
    assert_eq!(plan.actions, r.forecast);

    // WatchPlan: the current plan, then one update per step, equal to each step's forecast.
    let mut watch = client
        .watch_plan(proto::WatchPlanRequest {
            session_id: session.clone(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(watch.message().await.unwrap().unwrap().actions, r.forecast);
    let mut obs = next_observation(&r, &mut rng);
    for _ in 0..5 {
        let r = client
            .step(step_request(&session, obs.clone(), false))
            .await
            .unwrap()
            .into_inner();
        let update = tokio::time::timeout(Duration::from_secs(5), watch.message())
            .await
            .unwrap()
            .unwrap()
            .unwrap();
        assert_eq!(
            (update.start_step, update.actions),
            (r.step, r.forecast.clone())
        );
        obs = next_observation(&r, &mut rng);
    }
    // Closing the session ends the watch stream.
    let closed = client
        .close_session(proto::CloseSessionRequest {
            session_id: session.clone(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(closed.steps, 1006);
    let end = tokio::time::timeout(Duration::from_secs(5), watch.message())
        .await
        .unwrap()
        .expect_err("the watch ends with the session's status");
    assert_eq!(end.code(), Code::NotFound);
    assert!(end.message().contains("was closed"), "{end:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sampled_sessions_are_reproducible_from_their_seed() {
    let dir = bundle_dir();
    let server = Server::start(dir.path(), &[]);
    server.wait_serving().await;
    let mut client = server.client().await;
    let mut run = async |seed: u64| -> Vec<Vec<f32>> {
        let mut o = options(Some(Tolerance::Epsilon(0.05)), Some(Growth::Fixed(6)), 0);
        o.sampled = true;
        o.seed = seed;
        let session = open(&mut client, o).await;
        let mut obs = vec![0.2f32, 0.1, -0.1];
        let mut actions = Vec::new();
        for _ in 0..50 {
            let r = client
                .step(step_request(&session, obs.clone(), false))
                .await
                .unwrap()
                .into_inner();
            assert_eq!(r.forecast.len(), 6, "fixed 6 refills to 6");
            obs = r.forecast[0].predicted_observation.clone();
            actions.push(r.action);
        }
        actions
    };
    let a = run(7).await;
    assert_eq!(a, run(7).await);
    assert_ne!(a, run(8).await);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_error_status_with_a_clear_message() {
    let dir = tempfile::tempdir().unwrap();
    prac::bundle::save(&toy_policy("toy", 1), &dir.path().join("toy.safetensors")).unwrap();
    let mut unscaled = toy_policy("unscaled", 2);
    unscaled.manifest.value_scale = None;
    prac::bundle::save(&unscaled, &dir.path().join("unscaled.safetensors")).unwrap();
    let server = Server::start(dir.path(), &["--max-message-bytes", "4096"]);
    server.wait_serving().await;
    let mut client = server.client().await;
    let session = open(&mut client, options(None, None, 0)).await;
    let good = client
        .step(step_request(&session, vec![0.0, 0.1, 0.2], false))
        .await
        .unwrap()
        .into_inner();
    let plan_before = client
        .get_plan(proto::GetPlanRequest {
            session_id: session.clone(),
        })
        .await
        .unwrap()
        .into_inner();

    let expect = |result: Result<tonic::Response<proto::StepResponse>, tonic::Status>,
                  code: Code,
                  words: &[&str]| {
        let status = result.expect_err("must fail");
        assert_eq!(status.code(), code, "{status:?}");
        for w in words {
            assert!(
                status.message().contains(w),
                "{:?} lacks {w:?}",
                status.message()
            );
        }
    };
    // Wrong observation length, NaN, infinity.
    expect(
        client
            .step(step_request(&session, vec![0.0; 4], false))
            .await,
        Code::InvalidArgument,
        &["4 values", "obs_dim = 3"],
    );
    expect(
        client
            .step(step_request(&session, vec![0.0, f32::NAN, 0.0], false))
            .await,
        Code::InvalidArgument,
        &["observation[1]", "NaN", "finite"],
    );
    expect(
        client
            .step(step_request(&session, vec![f32::INFINITY, 0.0, 0.0], false))
            .await,
        Code::InvalidArgument,
        &["observation[0]", "inf"],
    );
    // Unknown session.
    expect(
        client.step(step_request("nope", vec![0.0; 3], false)).await,
        Code::NotFound,
        &["unknown session 'nope'", "OpenSession"],
    );
    // Finite but huge: the networks overflow, the step is refused, the plan is kept.
    expect(
        client
            .step(step_request(&session, vec![3e38, -3e38, 3e38], false))
            .await,
        Code::InvalidArgument,
        &["non-finite", "plan is unchanged"],
    );
    // An oversized message is refused, and the server lives on.
    let huge = client
        .step(step_request(&session, vec![0.0; 5000], false))
        .await;
    let status = huge.expect_err("oversized message must fail");
    assert_eq!(status.code(), Code::OutOfRange, "{status:?}");
    assert!(status.message().contains("too large"), "{status:?}");

    // Bad input lost nothing: the plan is unchanged and the next step continues the episode.
    let plan_after = client
        .get_plan(proto::GetPlanRequest {
            session_id: session.clone(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(plan_before, plan_after);
    let next = client
        .step(step_request(&session, vec![0.0, 0.1, 0.2], false))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(next.step, good.step + 1);

    // Unknown policy, bad options.
    let open_status = |policy: &str, o: proto::SessionOptions| proto::OpenSessionRequest {
        local_steps: 0,
        policy: policy.to_string(),
        options: Some(o),
        resume: None,
    };
    let cases: Vec<(proto::OpenSessionRequest, Code, &[&str])> = vec![
        (
            open_status("hopper", options(None, None, 0)),
            Code::NotFound,
            &["unknown policy 'hopper'", "toy, unscaled"],
        ),
        (
            open_status("toy", options(Some(Tolerance::Epsilon(-1.0)), None, 0)),
            Code::InvalidArgument,
            &["epsilon is -1"],
        ),
        (
            open_status("toy", options(Some(Tolerance::Epsilon(f64::NAN)), None, 0)),
            Code::InvalidArgument,
            &["epsilon is NaN"],
        ),
        (
            open_status("toy", options(None, Some(Growth::Grow(0)), 0)),
            Code::InvalidArgument,
            &["grow is 0"],
        ),
        (
            open_status("toy", options(None, Some(Growth::Fixed(40)), 8)),
            Code::InvalidArgument,
            &["fixed 40", "max_horizon 8"],
        ),
        (
            open_status("toy", options(None, None, 5000)),
            Code::InvalidArgument,
            &["max_horizon is 5000", "1..=256"],
        ),
        (
            open_status(
                "toy",
                proto::SessionOptions {
                    guard: Some(proto::PlanGuard {
                        every_critic: true,
                        support_limit: -2.0,
                        ..Default::default()
                    }),
                    ..options(None, None, 0)
                },
            ),
            Code::InvalidArgument,
            &["guard.support_limit is -2", "finite value >= 0"],
        ),
        (
            open_status(
                "unscaled",
                options(Some(Tolerance::EpsilonCoef(0.01)), None, 0),
            ),
            Code::InvalidArgument,
            &["value scale", "absolute epsilon"],
        ),
        (
            open_status("toy", options(None, None, 200)),
            Code::InvalidArgument,
            &["max_horizon 200", "max message size of 4096"],
        ),
    ];
    for (request, code, words) in cases {
        let status = client.open_session(request).await.expect_err("must fail");
        assert_eq!(status.code(), code, "{status:?}");
        for w in words {
            assert!(
                status.message().contains(w),
                "{:?} lacks {w:?}",
                status.message()
            );
        }
    }

    // A closed session: NOT_FOUND saying it was closed; on the stream too, which then ends.
    client
        .close_session(proto::CloseSessionRequest {
            session_id: session.clone(),
        })
        .await
        .unwrap();
    expect(
        client
            .step(step_request(&session, vec![0.0; 3], false))
            .await,
        Code::NotFound,
        &["was closed"],
    );
    let (tx, rx) = mpsc::channel(1);
    tx.send(step_request(&session, vec![0.0; 3], false))
        .await
        .unwrap();
    let mut stream = client
        .step_stream(ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let status = stream
        .message()
        .await
        .expect_err("the stream ends with the error");
    assert_eq!(status.code(), Code::NotFound);
    for rpc in ["get_plan", "watch_plan", "close_session"] {
        let code = match rpc {
            "get_plan" => client
                .get_plan(proto::GetPlanRequest {
                    session_id: session.clone(),
                })
                .await
                .err(),
            "watch_plan" => client
                .watch_plan(proto::WatchPlanRequest {
                    session_id: session.clone(),
                })
                .await
                .err(),
            _ => client
                .close_session(proto::CloseSessionRequest {
                    session_id: session.clone(),
                })
                .await
                .err(),
        }
        .map(|s| s.code());
        assert_eq!(code, Some(Code::NotFound), "{rpc}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_session_cap_answers_resource_exhausted() {
    let dir = bundle_dir();
    let server = Server::start(dir.path(), &["--max-sessions", "3"]);
    server.wait_serving().await;
    let mut client = server.client().await;
    let mut ids = Vec::new();
    for _ in 0..3 {
        ids.push(open(&mut client, options(None, None, 0)).await);
    }
    let status = client
        .open_session(proto::OpenSessionRequest {
            local_steps: 0,
            policy: "toy".into(),
            options: None,
            resume: None,
        })
        .await
        .expect_err("over the cap");
    assert_eq!(status.code(), Code::ResourceExhausted);
    assert!(
        status.message().contains("maximum of 3 sessions"),
        "{}",
        status.message()
    );
    client
        .close_session(proto::CloseSessionRequest {
            session_id: ids.pop().unwrap(),
        })
        .await
        .unwrap();
    open(&mut client, options(None, None, 0)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_ends_open_streams_and_exits_within_the_drain_timeout() {
    drains_on("TERM").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigint_ends_open_streams_and_exits_within_the_drain_timeout() {
    drains_on("INT").await;
}

async fn drains_on(signal: &str) {
    let dir = bundle_dir();
    // A drain timeout far beyond the wait below: an open stream that held the server would keep
    // it running past the wait.
    let mut server = Server::start(dir.path(), &["--drain-timeout", "600s"]);
    server.wait_serving().await;
    let mut client = server.client().await;
    let session = open(&mut client, options(None, None, 0)).await;
    let (tx, rx) = mpsc::channel(4);
    let mut responses = client
        .step_stream(ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    for _ in 0..3 {
        tx.send(step_request(&session, vec![0.0; 3], false))
            .await
            .unwrap();
        responses.message().await.unwrap().unwrap();
    }
    let mut watch = client
        .watch_plan(proto::WatchPlanRequest {
            session_id: session.clone(),
        })
        .await
        .unwrap()
        .into_inner();
    watch.message().await.unwrap().unwrap();

    let mut health = tonic_health::pb::health_client::HealthClient::new(server.channel().await);
    let mut health_watch = health
        .watch(tonic_health::pb::HealthCheckRequest {
            service: "prac.v1.Prac".into(),
        })
        .await
        .unwrap()
        .into_inner();
    let serving = tonic_health::pb::health_check_response::ServingStatus::Serving as i32;
    assert_eq!(
        health_watch.message().await.unwrap().unwrap().status,
        serving
    );

    server.signal(signal);
    // Health turns NOT_SERVING, then its watch ends too.
    let not_serving = tonic_health::pb::health_check_response::ServingStatus::NotServing as i32;
    let update = tokio::time::timeout(Duration::from_secs(5), health_watch.message())
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    assert_eq!(update.status, not_serving);
    // Both open streams end with UNAVAILABLE, although the client keeps them open.
    let status = tokio::time::timeout(Duration::from_secs(5), responses.message())
        .await
        .expect("the stream must end")
        .expect_err("with a status");
    assert_eq!(status.code(), Code::Unavailable, "{status:?}");
    assert!(status.message().contains("shutting down"));
    let status = tokio::time::timeout(Duration::from_secs(5), watch.message())
        .await
        .unwrap()
        .expect_err("with a status");
    assert_eq!(status.code(), Code::Unavailable);
    // Ended by the streams' end, not by the drain timeout: no open stream held the server.
    let exit = server
        .wait_exit(Duration::from_secs(60))
        .expect("exits once its streams have ended, long before the drain timeout");
    assert!(exit.success(), "{exit:?}: {}", server.stderr());
    drop(tx);
}

#[test]
fn sigterm_stops_a_server_whose_stdout_and_stderr_readers_are_gone() {
    // As when the process that started the server and read its output has died.
    let dir = bundle_dir();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_prac"))
        .args(["serve", "--listen", "127.0.0.1:0", "--bundles"])
        .arg(dir.path())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufRead::read_line(
        &mut std::io::BufReader::new(child.stdout.take().unwrap()),
        &mut line,
    )
    .unwrap();
    assert!(line.starts_with("listening on "), "{line}");
    drop(child.stderr.take());
    let status = std::process::Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    let start = std::time::Instant::now();
    let exit = loop {
        if let Some(exit) = child.try_wait().unwrap() {
            break exit;
        }
        if start.elapsed() > Duration::from_secs(30) {
            let _ = child.kill();
            panic!("the server did not stop on SIGTERM with its output's readers gone");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(exit.success(), "{exit:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_and_reflection() {
    use tonic_health::pb::health_check_response::ServingStatus;
    // No bundles: the server runs but does not claim to serve.
    let empty = tempfile::tempdir().unwrap();
    let server = Server::start(empty.path(), &[]);
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(
        server.health("prac.v1.Prac").await,
        ServingStatus::NotServing
    );
    assert_eq!(server.health("").await, ServingStatus::NotServing);
    drop(server);

    let dir = bundle_dir();
    let server = Server::start(dir.path(), &[]);
    server.wait_serving().await;
    assert_eq!(server.health("").await, ServingStatus::Serving);
    // Both reflection versions (v1, and v1alpha for Postman, older grpcurl and others) list
    // the services.
    macro_rules! listed_services {
        ($version:ident) => {{
            use tonic_reflection::pb::$version::{
                ServerReflectionRequest, server_reflection_client::ServerReflectionClient,
                server_reflection_request::MessageRequest,
                server_reflection_response::MessageResponse,
            };
            let mut reflection = ServerReflectionClient::new(server.channel().await);
            let (tx, rx) = mpsc::channel(1);
            tx.send(ServerReflectionRequest {
                host: String::new(),
                message_request: Some(MessageRequest::ListServices(String::new())),
            })
            .await
            .unwrap();
            let mut responses = reflection
                .server_reflection_info(ReceiverStream::new(rx))
                .await
                .unwrap()
                .into_inner();
            let response = responses.message().await.unwrap().unwrap();
            let Some(MessageResponse::ListServicesResponse(list)) = response.message_response
            else {
                panic!("unexpected reflection answer");
            };
            list.service
                .into_iter()
                .map(|s| s.name)
                .collect::<Vec<String>>()
        }};
    }
    for names in [listed_services!(v1), listed_services!(v1alpha)] {
        for service in ["prac.v1.Prac", "grpc.health.v1.Health"] {
            assert!(names.iter().any(|n| n == service), "{service}: {names:?}");
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_bundles_are_skipped_with_their_reason_or_fatal_with_strict() {
    let dir = bundle_dir();
    let bytes = prac::bundle::to_bytes(&toy_policy("broken", 3)).unwrap();
    std::fs::write(
        dir.path().join("broken.safetensors"),
        &bytes[..bytes.len() / 2],
    )
    .unwrap();
    let mut no_model = toy_policy("nomodel", 4);
    no_model.manifest.model = None;
    no_model.model = None;
    prac::bundle::save(&no_model, &dir.path().join("nomodel.safetensors")).unwrap();
    let server = Server::start(dir.path(), &["--log-format", "json"]);
    server.wait_serving().await;
    let mut client = server.client().await;
    let names: Vec<String> = client
        .list_policies(proto::ListPoliciesRequest {})
        .await
        .unwrap()
        .into_inner()
        .policies
        .into_iter()
        .map(|p| p.name)
        .collect();
    assert_eq!(names, vec!["toy"]);
    // A client asking for a skipped bundle's policy is told why; any other unknown name hears
    // which bundles were skipped.
    let open = |policy: &str| proto::OpenSessionRequest {
        policy: policy.into(),
        ..Default::default()
    };
    let refused = client.open_session(open("nomodel")).await.unwrap_err();
    assert_eq!(refused.code(), tonic::Code::NotFound);
    assert!(
        refused
            .message()
            .contains("'nomodel' is not served: its bundle was skipped (manifest.model: absent"),
        "{refused:?}"
    );
    let refused = client.open_session(open("other")).await.unwrap_err();
    assert!(
        refused.message().ends_with(
            "this server has: toy; bundles skipped (the server's log says why): broken, nomodel"
        ),
        "{refused:?}"
    );
    // JSON logs: one object per line; the bad bundle's line names the file and the reason.
    let log = server.stderr();
    let lines: Vec<serde_json::Value> = log
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: {l}")))
        .collect();
    let skipped: Vec<&str> = lines
        .iter()
        .filter(|l| l["fields"]["message"] == "skipping bad bundle" && l["level"] == "ERROR")
        .map(|l| l["fields"]["error"].as_str().unwrap())
        .collect();
    assert_eq!(skipped.len(), 2, "{log}");
    assert!(
        skipped[0].contains("broken.safetensors: safetensors"),
        "{skipped:?}"
    );
    assert!(
        skipped[1].contains("nomodel.safetensors: manifest.model: absent"),
        "{skipped:?}"
    );
    drop(server);

    let mut strict = Server::start(dir.path(), &["--strict"]);
    let exit = strict
        .wait_exit(Duration::from_secs(10))
        .expect("--strict exits");
    assert!(!exit.success());
    let log = strict.stderr();
    assert!(
        log.contains("broken.safetensors") && log.contains("--strict"),
        "{log}"
    );
}

/// Runs `sessions` concurrent sessions of `steps` unary steps on observations that follow each
/// session's own forecast; returns every response, per session.
async fn run_sessions(
    server: &Server,
    sessions: usize,
    steps: usize,
) -> Vec<Vec<proto::StepResponse>> {
    let mut tasks = Vec::new();
    for k in 0..sessions {
        let mut client = server.client().await;
        tasks.push(tokio::spawn(async move {
            // Every other session guards its plans: batches mix guarded and unguarded jobs.
            let guard = (k % 2 == 1).then_some(proto::PlanGuard {
                every_critic: k % 4 == 1,
                support_limit: 1.0,
                ..Default::default()
            });
            let session = open(
                &mut client,
                proto::SessionOptions {
                    guard,
                    ..options(Some(Tolerance::EpsilonCoef(0.0002)), None, 12)
                },
            )
            .await;
            let mut obs = vec![0.1 * k as f32, -0.2, 0.3];
            let mut out = Vec::new();
            for i in 0..steps {
                let r = client
                    .step(step_request(&session, obs.clone(), i == 0))
                    .await
                    .unwrap()
                    .into_inner();
                obs = r.forecast[0]
                    .predicted_observation
                    .iter()
                    .enumerate()
                    .map(|(j, v)| v + 0.01 * ((i + j) % 5) as f32)
                    .collect();
                out.push(r);
            }
            out
        }));
    }
    let mut all = Vec::new();
    for task in tasks {
        all.push(task.await.unwrap());
    }
    all
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cross_session_batching_gives_the_answers_of_one_at_a_time() {
    let dir = bundle_dir();
    // A window makes the worker gather concurrent sessions into real batches.
    let batched = Server::start(dir.path(), &["--batch-window", "2ms", "--batch-max", "16"]);
    let inline = Server::start(dir.path(), &["--batch-max", "0"]);
    batched.wait_serving().await;
    inline.wait_serving().await;
    let (a, b) = tokio::join!(run_sessions(&batched, 8, 40), run_sessions(&inline, 8, 40));
    assert_eq!(a, b);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_batch_queue_is_answered_with_resource_exhausted() {
    let dir = bundle_dir();
    let server = Server::start(
        dir.path(),
        &[
            "--batch-queue",
            "1",
            "--batch-max",
            "1",
            "--batch-window",
            "20ms",
            "--max-horizon-limit",
            "256",
        ],
    );
    server.wait_serving().await;
    let mut client = server.client().await;
    let mut ids = Vec::new();
    for _ in 0..32 {
        ids.push(
            open(
                &mut client,
                options(Some(Tolerance::Epsilon(1e9)), Some(Growth::Fixed(200)), 200),
            )
            .await,
        );
    }
    let mut tasks = Vec::new();
    for id in &ids {
        let mut client = client.clone();
        let id = id.clone();
        tasks.push(tokio::spawn(async move {
            client.step(step_request(&id, vec![0.0; 3], false)).await
        }));
    }
    let (mut ok, mut refused) = (0, 0);
    for task in tasks {
        match task.await.unwrap() {
            Ok(_) => ok += 1,
            Err(status) => {
                assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
                assert!(status.message().contains("overloaded"), "{status:?}");
                refused += 1;
            }
        }
    }
    assert!(ok >= 1 && refused >= 1, "ok {ok} refused {refused}");
    // Refused steps lost nothing: every session steps normally afterwards.
    for id in &ids {
        client
            .step(step_request(id, vec![0.0; 3], false))
            .await
            .unwrap();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_step_whose_caller_gave_up_is_not_applied() {
    let dir = bundle_dir();
    // A long window holds each step in the worker long enough for its caller to give up.
    let server = Server::start(dir.path(), &["--batch-window", "300ms"]);
    server.wait_serving().await;
    let mut client = server.client().await;
    let session = open(&mut client, options(None, None, 0)).await;
    let first = client
        .step(step_request(&session, vec![0.0; 3], false))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(first.step, 0);
    let abandoned = tokio::time::timeout(
        Duration::from_millis(50),
        client.step(step_request(&session, vec![0.1; 3], false)),
    )
    .await;
    assert!(abandoned.is_err(), "the caller gave up");
    tokio::time::sleep(Duration::from_millis(500)).await;
    let next = client
        .step(step_request(&session, vec![0.1; 3], false))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        next.step, 1,
        "the abandoned step must not have moved the session"
    );
}
