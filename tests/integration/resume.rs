//! Resume after a restart: a controller that loses its server (SIGKILL) opens a session on a new
//! one with the plan it last received, and the episode goes on with the committed actions, exactly
//! as the old server would have continued it. Malformed resumed plans are refused.

use crate::common;

use common::{ACT, OBS, Server, bundle_dir};
use prac::proto::{self, session_options::Tolerance};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tonic::Code;

fn observation(rng: &mut ChaCha8Rng) -> Vec<f32> {
    (0..OBS).map(|_| rng.random_range(-1.0..1.0)).collect()
}

fn options(epsilon: f64) -> proto::SessionOptions {
    proto::SessionOptions {
        tolerance: Some(Tolerance::Epsilon(epsilon)),
        max_horizon: 12,
        ..Default::default()
    }
}

/// The plan a client holds after a step: what it would hand to a new server.
fn held_plan(response: &proto::StepResponse) -> proto::Plan {
    proto::Plan {
        session_id: String::new(),
        episode: response.episode,
        start_step: response.step,
        actions: response.forecast.clone(),
    }
}

fn assert_same_actions(a: &[proto::PlannedAction], b: &[proto::PlannedAction]) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert_eq!(x.decided_at, y.decided_at);
        for (u, v) in x.action.iter().zip(&y.action) {
            assert!((u - v).abs() < 1e-5, "{x:?} vs {y:?}");
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_controller_resumes_its_commitment_on_a_new_server_after_sigkill() {
    let bundles = bundle_dir();
    let mut first = Server::start(bundles.path(), &[]);
    first.wait_serving().await;
    let mut client = first.client().await;
    // A tolerance this wide keeps every plan: the commitment is what must survive.
    let open = proto::OpenSessionRequest {
        local_steps: 0,
        policy: "toy".into(),
        options: Some(options(1e6)),
        resume: None,
    };
    let id = client
        .open_session(open.clone())
        .await
        .unwrap()
        .into_inner()
        .session_id;
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let observations: Vec<Vec<f32>> = (0..7).map(|_| observation(&mut rng)).collect();
    let mut last = None;
    for (t, obs) in observations[..6].iter().enumerate() {
        let response = client
            .step(proto::StepRequest {
                session_id: id.clone(),
                observation: obs.clone(),
                new_episode: t == 0,
            })
            .await
            .unwrap()
            .into_inner();
        last = Some(response);
    }
    let held = held_plan(last.as_ref().unwrap());
    assert_eq!(held.start_step, 5);
    assert!(held.actions.len() > 2, "{held:?}");
    // What the first server does next, had it lived.
    let expected = client
        .step(proto::StepRequest {
            session_id: id.clone(),
            observation: observations[6].clone(),
            new_episode: false,
        })
        .await
        .unwrap()
        .into_inner();

    first.signal("KILL");
    first.wait_exit(std::time::Duration::from_secs(10)).unwrap();
    let second = Server::start(bundles.path(), &[]);
    second.wait_serving().await;
    let mut client = second.client().await;
    let opened = client
        .open_session(proto::OpenSessionRequest {
            resume: Some(held.clone()),
            ..open
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(opened.resumed_actions as usize, held.actions.len());
    let plan = client
        .get_plan(proto::GetPlanRequest {
            session_id: opened.session_id.clone(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!((plan.episode, plan.start_step), (0, 5));
    assert_same_actions(&plan.actions, &held.actions);

    let resumed = client
        .step(proto::StepRequest {
            session_id: opened.session_id.clone(),
            observation: observations[6].clone(),
            new_episode: false,
        })
        .await
        .unwrap()
        .into_inner();
    // The episode goes on: step 6 executes the action committed for it, decided earlier.
    assert_eq!((resumed.step, resumed.episode), (6, 0));
    assert_eq!(resumed.kept as usize, held.actions.len() - 1);
    assert!(resumed.f_t > 1, "{resumed:?}");
    assert_same_actions(
        &resumed.forecast[..held.actions.len() - 1],
        &held.actions[1..],
    );
    // And exactly as the killed server would have gone on.
    assert_eq!(
        (resumed.kept, resumed.broke_at),
        (expected.kept, expected.broke_at)
    );
    assert_same_actions(&resumed.forecast, &expected.forecast);
    for (p, q) in resumed.forecast.iter().zip(&expected.forecast) {
        for (u, v) in p.predicted_observation.iter().zip(&q.predicted_observation) {
            assert!((u - v).abs() < 1e-4);
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_resumed_plans_are_refused_with_their_reason() {
    let bundles = bundle_dir();
    let server = Server::start(bundles.path(), &[]);
    server.wait_serving().await;
    let mut client = server.client().await;
    let entry = |action: Vec<f32>, decided_at: u64| proto::PlannedAction {
        action,
        predicted_observation: Vec::new(),
        decided_at,
    };
    let plan = |actions: Vec<proto::PlannedAction>| proto::Plan {
        session_id: String::new(),
        episode: 3,
        start_step: 10,
        actions,
    };
    let good = entry(vec![0.5, 0.5], 9);
    let cases = [
        (plan(vec![]), "no actions"),
        (plan(vec![entry(vec![0.5; ACT + 1], 9)]), "act_dim = 2"),
        (
            plan(vec![good.clone(), entry(vec![f32::NAN, 0.5], 9)]),
            "actions[1].action[0] is NaN",
        ),
        (plan(vec![entry(vec![0.5, 1.5], 9)]), "in [0, 1]"),
        (plan(vec![entry(vec![0.5, 0.5], 11)]), "decided at step 11"),
        (plan(vec![good.clone(); 13]), "max_horizon is 12"),
    ];
    for (resume, reason) in cases {
        let status = client
            .open_session(proto::OpenSessionRequest {
                local_steps: 0,
                policy: "toy".into(),
                options: Some(options(0.0)),
                resume: Some(resume),
            })
            .await
            .unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
        assert!(status.message().contains(reason), "{reason}: {status:?}");
    }
    // A well-formed one opens.
    let opened = client
        .open_session(proto::OpenSessionRequest {
            local_steps: 0,
            policy: "toy".into(),
            options: Some(options(0.0)),
            resume: Some(plan(vec![good; 3])),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(opened.resumed_actions, 3);
}

/// Steps `session` through `observations` (the first starts an episode); every response.
async fn step_all(
    client: &mut prac::proto::prac_client::PracClient<tonic::transport::Channel>,
    session: &str,
    observations: &[Vec<f32>],
    first_is_new_episode: bool,
) -> Vec<proto::StepResponse> {
    let mut responses = Vec::new();
    for (t, obs) in observations.iter().enumerate() {
        let response = client
            .step(proto::StepRequest {
                session_id: session.to_string(),
                observation: obs.clone(),
                new_episode: first_is_new_episode && t == 0,
            })
            .await
            .unwrap()
            .into_inner();
        responses.push(response);
    }
    responses
}

/// Bit for bit: a response's every float as its bits, each list led by its length.
fn bits(response: &proto::StepResponse) -> Vec<u64> {
    let mut out = Vec::new();
    let mut floats = |v: &[f32]| {
        out.push(v.len() as u64);
        out.extend(v.iter().map(|x| u64::from(x.to_bits())));
    };
    floats(&response.action);
    for entry in &response.forecast {
        floats(&entry.action);
        floats(&entry.predicted_observation);
    }
    out.extend(response.forecast.iter().map(|e| e.decided_at));
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resumed_session_answers_bit_for_bit_as_the_uninterrupted_one() {
    let bundles = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("bundles");
    let server = Server::start(&bundles, &[]);
    server.wait_serving().await;
    let mut client = server.client().await;
    let policies = client
        .list_policies(proto::ListPoliciesRequest {})
        .await
        .unwrap()
        .into_inner()
        .policies;
    assert!(policies.len() >= 7, "{policies:?}");
    for policy in &policies {
        let mut env = prac::domains::make(&policy.domain).unwrap();
        let mut start = vec![0.0; policy.obs_dim as usize];
        env.reset(11, &mut start).unwrap();
        let open = proto::OpenSessionRequest {
            local_steps: 0,
            policy: policy.name.clone(),
            options: Some(proto::SessionOptions {
                tolerance: Some(Tolerance::EpsilonCoef(0.01)),
                ..Default::default()
            }),
            resume: None,
        };
        // The uninterrupted session, observing each time the model's own prediction.
        let id = client
            .open_session(open.clone())
            .await
            .unwrap()
            .into_inner()
            .session_id;
        let mut observations = vec![start];
        let mut uninterrupted = Vec::new();
        for t in 0..9 {
            let response = step_all(&mut client, &id, &observations[t..=t], t == 0).await;
            let next = response[0].forecast[1.min(response[0].forecast.len() - 1)]
                .predicted_observation
                .clone();
            let next = if next.is_empty() {
                observations[t].clone()
            } else {
                next
            };
            observations.push(next);
            uninterrupted.extend(response);
        }
        for resume_after in [1, 3, 6, 8] {
            let held = held_plan(&uninterrupted[resume_after - 1]);
            let opened = client
                .open_session(proto::OpenSessionRequest {
                    resume: Some(held),
                    ..open.clone()
                })
                .await
                .unwrap()
                .into_inner();
            let resumed = step_all(
                &mut client,
                &opened.session_id,
                &observations[resume_after..9],
                false,
            )
            .await;
            for (k, (r, u)) in resumed
                .iter()
                .zip(&uninterrupted[resume_after..])
                .enumerate()
            {
                let t = resume_after + k;
                assert_eq!(
                    (r.kept, r.broke_at, r.f_t, r.step, r.episode),
                    (u.kept, u.broke_at, u.f_t, u.step, u.episode),
                    "{} resumed after step {resume_after}, step {t}",
                    policy.name
                );
                assert!(
                    bits(r) == bits(u),
                    "{} resumed after step {resume_after}, step {t}: {r:?} vs {u:?}",
                    policy.name
                );
            }
        }
    }
}
