//! The server in-process: its handlers called directly on a state built as `serve` builds it, and
//! `serve` itself run from a bound listener with a shutdown future. Where time matters, tokio's
//! clock is paused and advanced instead of slept on.

use std::time::Duration;

use tonic::{Code, Request};

use super::*;
use crate::proto::prac_server::Prac;
use crate::testing::{TOY_OBS, toy_policy};

/// A directory holding the toy policy as `toy.safetensors`.
fn toy_bundles() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    crate::bundle::save(&toy_policy("toy", 1), &dir.path().join("toy.safetensors")).unwrap();
    dir
}

/// The settings of `prac serve --bundles DIR --listen 127.0.0.1:0` with `change` applied.
fn config(dir: &std::path::Path, change: impl FnOnce(&mut ServeArgs)) -> ServeConfig {
    let mut args = ServeArgs {
        bundles: Some(dir.to_path_buf()),
        listen: Some("127.0.0.1:0".parse().unwrap()),
        ..Default::default()
    };
    change(&mut args);
    ServeConfig::resolve(&args).unwrap()
}

/// The service over a state built as `serve` builds it, with the bundles of `config` loaded.
fn service(config: &ServeConfig) -> PracService {
    let state = server_state(
        config,
        None,
        Arc::new(super::metrics::Metrics::default()),
        CancellationToken::new(),
    )
    .unwrap();
    let loaded = Registry::load_dir(&config.bundles).unwrap();
    assert!(loaded.errors.is_empty());
    *state.registry.write().unwrap() = Some(Arc::new(loaded.registry));
    PracService { state }
}

async fn open(service: &PracService, options: proto::SessionOptions) -> String {
    service
        .open_session(Request::new(proto::OpenSessionRequest {
            local_steps: 0,
            policy: "toy".into(),
            options: Some(options),
            resume: None,
        }))
        .await
        .unwrap()
        .into_inner()
        .session_id
}

async fn step(
    service: &PracService,
    id: &str,
    observation: &[f32],
    new_episode: bool,
) -> Result<proto::StepResponse, tonic::Status> {
    service
        .step(Request::new(proto::StepRequest {
            session_id: id.to_string(),
            observation: observation.to_vec(),
            new_episode,
        }))
        .await
        .map(tonic::Response::into_inner)
}

fn observation(t: usize, k: usize) -> Vec<f32> {
    (0..TOY_OBS)
        .map(|i| ((t * 7 + k * 3 + i) as f32 * 0.37).sin())
        .collect()
}

#[tokio::test(start_paused = true)]
async fn idle_sessions_expire_while_busy_ones_live_on() {
    let dir = toy_bundles();
    let config = config(dir.path(), |a| {
        a.session_ttl = Some(Duration::from_millis(300));
        a.batch_max = Some(0);
    });
    let service = service(&config);
    // The store evicts by itself.
    let sessions = service.state.sessions.clone();
    let idle = open(&service, Default::default()).await;
    let busy = open(&service, Default::default()).await;
    step(&service, &idle, &observation(0, 0), true)
        .await
        .unwrap();
    for t in 0..12 {
        step(&service, &busy, &observation(t, 1), t == 0)
            .await
            .unwrap();
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let status = step(&service, &idle, &observation(1, 0), false)
        .await
        .expect_err("the idle session expired");
    assert_eq!(status.code(), Code::FailedPrecondition, "{status:?}");
    assert!(status.message().contains("expired at"), "{status:?}");
    assert!(status.message().contains("TTL is 300ms"), "{status:?}");
    assert_eq!(sessions.len(), 1, "only the busy session is left");
}

#[tokio::test]
async fn closed_and_unknown_sessions_each_say_so() {
    let dir = toy_bundles();
    let service = service(&config(dir.path(), |_| {}));
    let id = open(&service, Default::default()).await;
    step(&service, &id, &observation(0, 0), true).await.unwrap();
    service
        .close_session(Request::new(proto::CloseSessionRequest {
            session_id: id.clone(),
        }))
        .await
        .unwrap();
    let closed = step(&service, &id, &observation(1, 0), false)
        .await
        .unwrap_err();
    assert_eq!(closed.code(), Code::NotFound, "{closed:?}");
    assert!(closed.message().contains("closed at"), "{closed:?}");
    let unknown = step(&service, "no-such-session", &observation(0, 0), true)
        .await
        .unwrap_err();
    assert_eq!(unknown.code(), Code::NotFound, "{unknown:?}");
}

#[tokio::test]
async fn a_resumed_session_goes_on_as_the_old_one_would_have() {
    let dir = toy_bundles();
    let service = service(&config(dir.path(), |_| {}));
    let options = proto::SessionOptions {
        tolerance: Some(proto::session_options::Tolerance::Epsilon(1e6)),
        max_horizon: 12,
        ..Default::default()
    };
    let first = open(&service, options).await;
    let mut last = None;
    for t in 0..6 {
        last = Some(
            step(&service, &first, &observation(t, 0), t == 0)
                .await
                .unwrap(),
        );
    }
    let last = last.unwrap();
    let held = proto::Plan {
        session_id: String::new(),
        episode: last.episode,
        start_step: last.step,
        actions: last.forecast.clone(),
    };
    let resumed = service
        .open_session(Request::new(proto::OpenSessionRequest {
            local_steps: 0,
            policy: "toy".into(),
            options: Some(options),
            resume: Some(held),
        }))
        .await
        .unwrap()
        .into_inner()
        .session_id;
    let old = step(&service, &first, &observation(6, 0), false)
        .await
        .unwrap();
    let new = step(&service, &resumed, &observation(6, 0), false)
        .await
        .unwrap();
    assert_eq!(new.step, old.step);
    assert_eq!(new.f_t, old.f_t);
    assert_eq!(new.action, old.action);
    assert!(new.kept > 0, "the commitment was kept: {new:?}");
}

/// Steps `sessions` sessions for `steps` steps, all sessions' steps of one round at once.
async fn run_sessions(service: &PracService, sessions: usize, steps: usize) -> Vec<Vec<f32>> {
    let mut ids = Vec::new();
    for k in 0..sessions {
        let options = proto::SessionOptions {
            tolerance: Some(proto::session_options::Tolerance::Epsilon(0.05)),
            seed: k as u64,
            ..Default::default()
        };
        ids.push(open(service, options).await);
    }
    let mut actions = Vec::new();
    for t in 0..steps {
        let observations: Vec<Vec<f32>> = (0..ids.len()).map(|k| observation(t, k)).collect();
        let round = ids
            .iter()
            .zip(&observations)
            .map(|(id, obs)| step(service, id, obs, t == 0));
        for response in futures::future::join_all(round).await {
            actions.push(response.unwrap().action);
        }
    }
    actions
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_batch_worker_answers_each_session_as_it_would_be_answered_alone() {
    let dir = toy_bundles();
    // A batch window turns the lone-step shortcut off: every step goes through a worker.
    let batched = service(&config(dir.path(), |a| {
        a.batch_max = Some(8);
        a.batch_window = Some(Duration::from_millis(2));
        a.batch_workers = Some(1);
    }));
    let alone = service(&config(dir.path(), |a| a.batch_max = Some(0)));
    let expected = run_sessions(&alone, 6, 10).await;
    let got = run_sessions(&batched, 6, 10).await;
    assert_eq!(got, expected);
    let text = batched.state.metrics.encode(0);
    assert!(
        text.contains("prac_replanned_total{by=\"batch_worker\"} 60"),
        "every step went through the worker:\n{text}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serve_runs_from_a_bound_listener_until_its_shutdown_future_resolves() {
    let dir = toy_bundles();
    let config = config(dir.path(), |a| {
        a.drain_timeout = Some(Duration::from_secs(5))
    });
    let bound = bind(&config).await.unwrap();
    let addr = bound.grpc.local_addr().unwrap().to_string();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn({
        let config = config.clone();
        async move {
            serve(bound, &config, async {
                let _ = stopped.await;
            })
            .await
        }
    });
    let mut client = crate::client::connect(&addr).await.unwrap();
    let info = crate::client::choose_policy(&mut client, None, Duration::from_secs(10))
        .await
        .unwrap();
    assert_eq!(info.name, "toy");
    let id = client
        .open_session(proto::OpenSessionRequest {
            local_steps: 0,
            policy: "toy".into(),
            options: None,
            resume: None,
        })
        .await
        .unwrap()
        .into_inner()
        .session_id;
    let response = client
        .step(proto::StepRequest {
            session_id: id,
            observation: observation(0, 0),
            new_episode: true,
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(response.step, 0);
    stop.send(()).unwrap();
    drop(client);
    tokio::time::timeout(Duration::from_secs(10), server)
        .await
        .expect("the server stops within its drain timeout")
        .unwrap()
        .unwrap();
}

/// With tokens on, handlers serve the caller the intake attached from the headers, and refuse a
/// call that carries none (one that did not come through the intake).
#[tokio::test]
async fn handlers_take_the_caller_the_intake_attached() {
    let dir = toy_bundles();
    let config = config(dir.path(), |_| {});
    let tokens = auth::Tokens::parse("alpha-0123456789abcdef\n").unwrap();
    let state = server_state(
        &config,
        Some(Arc::new(tokens)),
        Arc::new(super::metrics::Metrics::default()),
        CancellationToken::new(),
    )
    .unwrap();
    let loaded = Registry::load_dir(&config.bundles).unwrap();
    *state.registry.write().unwrap() = Some(Arc::new(loaded.registry));
    let service = PracService { state };
    let request = || proto::OpenSessionRequest {
        local_steps: 0,
        policy: "toy".into(),
        options: None,
        resume: None,
    };
    let bare = service.open_session(Request::new(request())).await;
    assert_eq!(bare.unwrap_err().code(), Code::Unauthenticated);
    let mut attached = Request::new(request());
    attached
        .extensions_mut()
        .insert(auth::Caller(Some("alpha".into())));
    let id = service
        .open_session(attached)
        .await
        .unwrap()
        .into_inner()
        .session_id;
    // The session is the caller's: another caller cannot close it.
    let mut other = Request::new(proto::CloseSessionRequest { session_id: id });
    other
        .extensions_mut()
        .insert(auth::Caller(Some("beta".into())));
    let refused = service.close_session(other).await.unwrap_err();
    assert_eq!(refused.code(), Code::PermissionDenied, "{refused:?}");
}
