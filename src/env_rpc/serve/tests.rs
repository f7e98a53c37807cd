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

fn settings(pairs: &[(&str, i64)]) -> HashMap<String, pb::Tensor> {
    pairs
        .iter()
        .map(|&(k, v)| (k.to_string(), tensor::scalar_i64(v)))
        .collect()
}

#[test]
fn a_vector_world_steps_each_env_as_the_local_domain_with_next_step_autoreset() {
    let (n, seed, act_dim, obs_dim) = (3usize, 20u64, 3usize, 15usize);
    let server = DomainServer::new("hopper", 0).unwrap();
    let (mut joined, mut created) = (None, Vec::new());
    let mut handle = |request: Request| server.handle(request, &mut joined, &mut created);
    let refused = |answer: Result<Response, Refusal>| match answer {
        Err(Refusal(code, message)) => (code, message),
        Ok(_) => panic!("accepted"),
    };
    for (bad, expected) in [(0, "1..=1024"), (5000, "1..=1024")] {
        let (c, m) = refused(handle(Request::CreateWorld(pb::CreateWorldRequest {
            settings: settings(&[("num_envs", bad)]),
        })));
        assert!(c == INVALID_ARGUMENT && m.contains(expected), "{m}");
    }
    let Ok(Response::CreateWorld(world)) = handle(Request::CreateWorld(pb::CreateWorldRequest {
        settings: settings(&[("num_envs", n as i64), ("seed", seed as i64)]),
    })) else {
        panic!("no world");
    };
    let Ok(Response::JoinWorld(join)) = handle(Request::JoinWorld(pb::JoinWorldRequest {
        world_name: world.world_name,
        settings: HashMap::new(),
    })) else {
        panic!("not joined");
    };
    let specs = join.specs.unwrap();
    assert_eq!(specs.actions[&ACTION].shape, [n as i32, act_dim as i32]);
    assert_eq!(
        specs.observations[&OBSERVATION].shape,
        [n as i32, obs_dim as i32]
    );
    assert_eq!(specs.observations[&TERMINATED].shape, [n as i32]);
    let (c, m) = refused(handle(Request::Reset(pb::ResetRequest {
        settings: settings(&[("num_envs", 2)]),
    })));
    assert!(
        c == INVALID_ARGUMENT && m.contains("unknown settings"),
        "{m}"
    );

    let vector_step = |action: &[f32]| {
        Request::Step(pb::StepRequest {
            actions: HashMap::from([(
                ACTION,
                pb::Tensor {
                    shape: vec![n as i32, act_dim as i32],
                    ..tensor::floats(action)
                },
            )]),
            requested_observations: vec![OBSERVATION, REWARD, TERMINATED, TRUNCATED],
        })
    };
    let read = |answer: pb::StepResponse| {
        let mut obs = vec![0.0; n * obs_dim];
        tensor::read_into("observation", &answer.observations[&OBSERVATION], &mut obs).unwrap();
        let Some(pb::tensor::Payload::Doubles(rewards)) = &answer.observations[&REWARD].payload
        else {
            panic!("no rewards")
        };
        let flags = |uid| match &answer.observations[&uid].payload {
            Some(pb::tensor::Payload::Bools(b)) => b.array.clone(),
            _ => panic!("no flags"),
        };
        assert_eq!(answer.state(), pb::EnvironmentStateType::Running);
        (
            obs,
            rewards.array.clone(),
            flags(TERMINATED),
            flags(TRUNCATED),
        )
    };

    let mut local: Vec<_> = (0..n).map(|_| domains::make("hopper").unwrap()).collect();
    let mut next_seed: Vec<u64> = (0..n as u64).map(|i| seed + i).collect();
    let mut expected = vec![0.0; n * obs_dim];
    let Ok(Response::Step(first)) = handle(vector_step(&[f32::NAN; 9])) else {
        panic!("the first step starts the episodes, ignoring its actions");
    };
    for i in 0..n {
        local[i]
            .reset(next_seed[i], &mut expected[i * obs_dim..(i + 1) * obs_dim])
            .unwrap();
        next_seed[i] += n as u64;
    }
    assert_eq!(read(first).0, expected);

    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (mut ended, mut autoresets) = (vec![false; n], 0);
    for t in 0..120 {
        let action: Vec<f32> = (0..n * act_dim)
            .map(|_| rng.random_range(-1.0..=1.0))
            .collect();
        if t == 30 {
            for (bad, message) in [
                (vec![0.0; act_dim], "shape"),
                (
                    [vec![0.0; 5], vec![f32::NAN], vec![0.0; 3]].concat(),
                    "action[1][2] is NaN",
                ),
            ] {
                let request = if bad.len() == n * act_dim {
                    vector_step(&bad)
                } else {
                    step(bad)
                };
                let (c, m) = refused(handle(request));
                assert!(c == INVALID_ARGUMENT && m.contains(message), "{m}");
            }
        }
        let Ok(Response::Step(answer)) = handle(vector_step(&action)) else {
            panic!("step {t} refused");
        };
        let (obs, rewards, terminated, truncated) = read(answer);
        for i in 0..n {
            let out = &mut expected[i * obs_dim..(i + 1) * obs_dim];
            if ended[i] {
                local[i].reset(next_seed[i], out).unwrap();
                next_seed[i] += n as u64;
                assert_eq!(
                    (rewards[i], terminated[i], truncated[i]),
                    (0.0, false, false)
                );
                ended[i] = false;
                autoresets += 1;
            } else {
                let s = local[i]
                    .step(&action[i * act_dim..(i + 1) * act_dim], out)
                    .unwrap();
                assert_eq!(
                    (rewards[i], terminated[i], truncated[i]),
                    (s.reward, s.terminated, s.truncated),
                    "env {i} step {t}"
                );
                ended[i] = s.terminated || s.truncated;
            }
        }
        assert_eq!(obs, expected, "step {t}");
    }
    assert!(autoresets >= n, "random hoppers fall within 120 steps");
}
