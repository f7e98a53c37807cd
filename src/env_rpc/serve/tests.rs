use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::*;
use crate::env_rpc::RemoteEnv;

/// Serves `domain` from a thread of its own; returns the address.
fn serve_in_background(domain: &str) -> String {
    let server = DomainServer::new(domain, 0).unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        runtime.block_on(async {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
            tx.send(listener.local_addr().unwrap()).unwrap();
            serve_on(server, listener).await
        })
    });
    rx.recv().unwrap().to_string()
}

#[test]
fn a_served_domain_plays_bit_for_bit_as_the_local_one() {
    for domain in ["pendulum", "lander", "hopper", "ant"] {
        let addr = serve_in_background(domain);
        let mut remote = RemoteEnv::connect(&addr, 3).unwrap();
        let mut local = domains::make(domain).unwrap();
        let spec = local.spec().clone();
        assert_eq!(remote.spec().name, spec.name);
        assert_eq!(remote.spec().obs_dim, spec.obs_dim);
        assert_eq!(remote.spec().episode_len, spec.episode_len);
        assert_eq!(
            (&remote.spec().action_low, &remote.spec().action_high),
            (&spec.action_low, &spec.action_high)
        );
        let (mut a, mut b) = (vec![0.0; spec.obs_dim], vec![0.0; spec.obs_dim]);
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let mut action = vec![0.0; spec.act_dim];
        let mut ends = 0;
        for episode in 0..3u64 {
            remote.reset(100 + episode, &mut a).unwrap();
            local.reset(100 + episode, &mut b).unwrap();
            assert_eq!(a, b, "{domain}: reset");
            for t in 0..250 {
                for (x, (lo, hi)) in action
                    .iter_mut()
                    .zip(spec.action_low.iter().zip(&spec.action_high))
                {
                    *x = rng.random_range(*lo..=*hi);
                }
                let r = remote.step(&action, &mut a).unwrap();
                let l = local.step(&action, &mut b).unwrap();
                assert_eq!(a, b, "{domain}: episode {episode} step {t}");
                assert_eq!(r, l, "{domain}: episode {episode} step {t}");
                if l.terminated || l.truncated {
                    ends += 1;
                    break;
                }
            }
        }
        if domain == "pendulum" {
            assert_eq!(ends, 3, "pendulum episodes end at step 200, INTERRUPTED");
        }
    }
}

fn seed(value: i64) -> HashMap<String, pb::Tensor> {
    HashMap::from([("seed".to_string(), tensor::scalar_i64(value))])
}

fn step(action: Vec<f32>) -> Request {
    Request::Step(pb::StepRequest {
        actions: HashMap::from([(ACTION, tensor::floats(&action))]),
        requested_observations: vec![OBSERVATION, REWARD],
    })
}

#[test]
fn bad_requests_are_refused_with_a_code_and_change_nothing() {
    let server = DomainServer::new("pendulum", 0).unwrap();
    let (mut joined, mut created) = (None, Vec::new());
    let mut handle = |request: Request| server.handle(request, &mut joined, &mut created);
    let code = |answer: Result<Response, Refusal>| match answer {
        Err(Refusal(code, message)) => (code, message),
        Ok(_) => panic!("accepted"),
    };

    let (c, m) = code(handle(step(vec![0.0])));
    assert!(
        c == FAILED_PRECONDITION && m.contains("create and join"),
        "{m}"
    );
    let (c, m) = code(handle(Request::CreateWorld(pb::CreateWorldRequest {
        settings: HashMap::from([("speed".to_string(), tensor::scalar_i64(1))]),
    })));
    assert!(
        c == INVALID_ARGUMENT && m.contains("unknown settings"),
        "{m}"
    );
    let (c, m) = code(handle(Request::CreateWorld(pb::CreateWorldRequest {
        settings: seed(-1),
    })));
    assert!(c == INVALID_ARGUMENT && m.contains(">= 0"), "{m}");
    let Ok(Response::CreateWorld(world)) = handle(Request::CreateWorld(pb::CreateWorldRequest {
        settings: seed(4),
    })) else {
        panic!("no world");
    };
    let (c, _) = code(handle(Request::JoinWorld(pb::JoinWorldRequest {
        world_name: "elsewhere".into(),
        settings: HashMap::new(),
    })));
    assert_eq!(c, NOT_FOUND);
    assert!(matches!(
        handle(Request::JoinWorld(pb::JoinWorldRequest {
            world_name: world.world_name.clone(),
            settings: HashMap::new(),
        })),
        Ok(Response::JoinWorld(_))
    ));
    // The first step starts the episode; its action is ignored.
    let Ok(Response::Step(first)) = handle(step(vec![f32::NAN])) else {
        panic!("no first step");
    };
    assert_eq!(first.state(), pb::EnvironmentStateType::Running);
    for (bad, expected) in [
        (vec![f32::NAN], "finite"),
        (vec![2.5], "outside [-2, 2]"),
        (vec![0.0, 0.0], "shape"),
    ] {
        let (c, m) = code(handle(step(bad)));
        assert!(c == INVALID_ARGUMENT && m.contains(expected), "{m}");
    }
    let (c, m) = code(handle(Request::Step(pb::StepRequest {
        actions: HashMap::from([(ACTION, tensor::floats(&[0.0]))]),
        requested_observations: vec![42],
    })));
    assert!(c == INVALID_ARGUMENT && m.contains("uid 42"), "{m}");
    let (c, _) = code(handle(Request::DestroyWorld(pb::DestroyWorldRequest {
        world_name: world.world_name.clone(),
    })));
    assert_eq!(c, FAILED_PRECONDITION);

    // Nothing refused moved the pendulum: the next step is the episode's first, as a fresh
    // world of the same seed plays it.
    let Ok(Response::Step(served)) = handle(step(vec![1.0])) else {
        panic!("the step failed");
    };
    let mut env = domains::make("pendulum").unwrap();
    let (mut start, mut next) = (vec![0.0; 3], vec![0.0; 3]);
    env.reset(4, &mut start).unwrap();
    let reward = env.step(&[1.0], &mut next).unwrap().reward;
    let mut observed = vec![0.0; 3];
    tensor::read_into(
        "observation",
        &first.observations[&OBSERVATION],
        &mut observed,
    )
    .unwrap();
    assert_eq!(observed, start);
    tensor::read_into(
        "observation",
        &served.observations[&OBSERVATION],
        &mut observed,
    )
    .unwrap();
    assert_eq!(observed, next);
    assert_eq!(
        tensor::read_scalar("reward", &served.observations[&REWARD]).unwrap(),
        reward
    );
}

#[test]
fn unknown_domains_are_refused_at_start() {
    let e = DomainServer::new("rocket", 0).err().unwrap().to_string();
    assert!(
        e.contains("unknown domain 'rocket'") && e.contains("hopper"),
        "{e}"
    );
}
