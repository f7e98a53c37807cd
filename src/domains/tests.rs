use super::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Plays `steps` uniform random actions from `seed`, resetting at episode ends; returns every
/// observation and reward.
fn rollout(name: &str, seed: u64, steps: usize) -> (Vec<f32>, Vec<f64>) {
    let mut env = make(name).unwrap();
    let spec = env.spec().clone();
    let mut obs = vec![0.0; spec.obs_dim];
    env.reset(seed, &mut obs).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xabc);
    let (mut all, mut rewards) = (obs.clone(), Vec::new());
    let mut episode = 0;
    for _ in 0..steps {
        let action: Vec<f32> = (0..spec.act_dim)
            .map(|i| rng.random_range(spec.action_low[i]..=spec.action_high[i]))
            .collect();
        let t = env.step(&action, &mut obs).unwrap();
        all.extend_from_slice(&obs);
        rewards.push(t.reward);
        if t.terminated || t.truncated {
            episode += 1;
            env.reset(seed + episode, &mut obs).unwrap();
            all.extend_from_slice(&obs);
        }
    }
    (all, rewards)
}

#[test]
fn same_seed_and_actions_give_bit_identical_observations() {
    for name in DOMAINS {
        let (a, ra) = rollout(name, 7, 1000);
        let (b, rb) = rollout(name, 7, 1000);
        assert!(
            a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()),
            "{name}"
        );
        assert_eq!(ra, rb, "{name}");
        assert_ne!(a, rollout(name, 8, 1000).0, "{name}: seeds must matter");
    }
}

#[test]
fn random_play_stays_finite_and_inside_the_documented_ranges() {
    for name in DOMAINS {
        let spec = make(name).unwrap().spec().clone();
        let (obs, rewards) = rollout(name, 3, 1000);
        assert!(rewards.iter().all(|r| r.is_finite()), "{name}");
        for (i, v) in obs.iter().enumerate() {
            let d = i % spec.obs_dim;
            assert!(
                v.is_finite() && *v >= spec.obs_low[d] && *v <= spec.obs_high[d],
                "{name}: obs[{d}] = {v}"
            );
        }
    }
}

#[test]
fn bad_actions_are_errors_and_change_nothing() {
    for name in DOMAINS {
        let mut env = make(name).unwrap();
        let spec = env.spec().clone();
        let mut obs = vec![0.0; spec.obs_dim];
        assert!(matches!(
            env.step(&vec![0.0; spec.act_dim], &mut obs),
            Err(EnvError::EpisodeOver)
        ));
        env.reset(1, &mut obs).unwrap();
        let wrong = vec![0.0; spec.act_dim + 1];
        assert!(matches!(
            env.step(&wrong, &mut obs),
            Err(EnvError::ActionLength { .. })
        ));
        let mut nan = vec![0.0; spec.act_dim];
        nan[0] = f32::NAN;
        assert!(matches!(
            env.step(&nan, &mut obs),
            Err(EnvError::NonFiniteAction { index: 0, .. })
        ));
        assert!(matches!(
            env.step(&vec![0.0; spec.act_dim], &mut [0.0; 1][..0]),
            Err(EnvError::ObservationLength { .. })
        ));
        // The refused steps left no trace: the episode continues as a fresh one would.
        let mut fresh = make(name).unwrap();
        let mut fresh_obs = vec![0.0; spec.obs_dim];
        fresh.reset(1, &mut fresh_obs).unwrap();
        let zero = vec![0.0; spec.act_dim];
        env.step(&zero, &mut obs).unwrap();
        fresh.step(&zero, &mut fresh_obs).unwrap();
        assert_eq!(obs, fresh_obs, "{name}");
    }
}

#[test]
fn out_of_range_actions_are_clipped() {
    for name in DOMAINS {
        let spec = make(name).unwrap().spec().clone();
        let (mut a, mut b) = (make(name).unwrap(), make(name).unwrap());
        let (mut oa, mut ob) = (vec![0.0; spec.obs_dim], vec![0.0; spec.obs_dim]);
        a.reset(5, &mut oa).unwrap();
        b.reset(5, &mut ob).unwrap();
        let huge: Vec<f32> = spec.action_high.iter().map(|h| h * 10.0).collect();
        a.step(&huge, &mut oa).unwrap();
        b.step(&spec.action_high, &mut ob).unwrap();
        assert_eq!(oa, ob, "{name}");
    }
}

#[test]
fn episodes_end_at_their_length() {
    for name in DOMAINS {
        let mut env = make(name).unwrap();
        let spec = env.spec().clone();
        let mut obs = vec![0.0; spec.obs_dim];
        env.reset(0, &mut obs).unwrap();
        let zero = vec![0.0; spec.act_dim];
        let mut steps = 0;
        loop {
            steps += 1;
            let t = env.step(&zero, &mut obs).unwrap();
            if t.terminated || t.truncated {
                break;
            }
        }
        assert!(steps <= spec.episode_len, "{name}");
    }
}

#[test]
fn pendulum_follows_gymnasium_pendulum_v1() {
    let mut env = Pendulum::new();
    let mut obs = [0.0f32; 3];
    env.reset(11, &mut obs).unwrap();
    let (mut th, mut thdot) = (
        f64::from(obs[1]).atan2(f64::from(obs[0])),
        f64::from(obs[2]),
    );
    for k in 0..200 {
        let u = ((k as f64) * 0.37).sin() * 2.0;
        let t = env.step(&[u as f32], &mut obs).unwrap();
        // gymnasium: cost from the state before the step, then semi-implicit Euler.
        let norm = (th + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI)
            - std::f64::consts::PI;
        let u32_ = f64::from(u as f32);
        let cost = norm * norm + 0.1 * thdot * thdot + 0.001 * u32_ * u32_;
        assert!((t.reward + cost).abs() < 1e-4, "step {k}");
        let new_thdot = (thdot + (15.0 * th.sin() + 3.0 * u32_) * 0.05).clamp(-8.0, 8.0);
        th += new_thdot * 0.05;
        thdot = new_thdot;
        assert!(
            (f64::from(obs[0]) - th.cos()).abs() < 1e-3 && (f64::from(obs[2]) - thdot).abs() < 1e-3
        );
        assert_eq!(t.truncated, k == 199);
    }
}

#[test]
fn a_lander_with_its_engines_off_crashes_with_minus_100() {
    for seed in 0..6 {
        let mut env = Lander::new();
        let mut obs = [0.0f32; 8];
        env.reset(seed, &mut obs).unwrap();
        let mut steps = 0;
        let last = loop {
            let t = env.step(&[0.0, 0.0], &mut obs).unwrap();
            steps += 1;
            if t.terminated || t.truncated {
                break t;
            }
        };
        assert!(
            last.terminated && last.reward == -100.0,
            "seed {seed}: {last:?}"
        );
        // It fell from the top: it took a second or more.
        assert!(steps > 40, "seed {seed}: {steps} steps");
    }
}

/// gym's hand-written controller for LunarLanderContinuous (`heuristic` in lunar_lander.py).
fn lander_heuristic(s: &[f32], a: &mut [f32]) {
    let angle_target = (s[0] * 0.5 + s[2]).clamp(-0.4, 0.4);
    let hover_target = 0.55 * s[0].abs();
    let (mut angle_todo, mut hover_todo) = (
        (angle_target - s[4]) * 0.5 - s[5],
        (hover_target - s[1]) * 0.5 - s[3] * 0.5,
    );
    if s[6] > 0.5 || s[7] > 0.5 {
        angle_todo = 0.0;
        hover_todo = -s[3] * 0.5;
    }
    a[0] = (hover_todo * 20.0 - 1.0).clamp(-1.0, 1.0);
    a[1] = (-angle_todo * 20.0).clamp(-1.0, 1.0);
}

/// The spring legs must carry the lander and let it come to rest (+100), as in gym, where this
/// controller scores about 250-290: with folding legs or chattering joints it cannot.
#[test]
fn gyms_heuristic_lands_the_lander_and_comes_to_rest() {
    let mut env = Lander::new();
    let (mut total, mut rested) = (0.0, 0);
    let episodes = 20;
    for seed in 0..episodes {
        let mut obs = [0.0f32; 8];
        let mut action = [0.0f32; 2];
        env.reset(seed, &mut obs).unwrap();
        loop {
            lander_heuristic(&obs, &mut action);
            let t = env.step(&action, &mut obs).unwrap();
            total += t.reward;
            if t.terminated || t.truncated {
                rested += usize::from(t.terminated && t.reward == 100.0);
                break;
            }
        }
    }
    let mean = total / episodes as f64;
    assert!(mean > 200.0, "mean return {mean}");
    assert!(rested >= 18, "{rested} of {episodes} came to rest");
}

#[test]
fn the_lander_starts_at_the_top_centre_with_its_legs_in_the_air() {
    let mut env = Lander::new();
    let mut obs = [0.0f32; 8];
    for seed in 0..5 {
        env.reset(seed, &mut obs).unwrap();
        // x near the centre, y (relative to the helipad) near the top, no leg contact.
        assert!(
            obs[0].abs() < 0.1 && obs[1] > 1.2 && obs[1] < 1.5,
            "{obs:?}"
        );
        assert_eq!((obs[6], obs[7]), (0.0, 0.0));
    }
}

#[test]
fn walkers_without_torques_fall_and_terminate() {
    for name in ["hopper", "walker"] {
        for seed in 0..3 {
            let mut env = make(name).unwrap();
            let spec = env.spec().clone();
            let mut obs = vec![0.0f32; spec.obs_dim];
            env.reset(seed, &mut obs).unwrap();
            assert_eq!(
                &obs[..3],
                &[0.0, 0.0, 1.0],
                "{name}: starts at its height facing the target"
            );
            let zero = vec![0.0; spec.act_dim];
            let mut steps = 0;
            let last = loop {
                let t = env.step(&zero, &mut obs).unwrap();
                steps += 1;
                if t.terminated || t.truncated {
                    break t;
                }
            };
            assert!(last.terminated && !last.truncated, "{name} seed {seed}");
            // Falling: it lost height or tipped over (|pitch| >= 1) well before the episode's end.
            assert!(
                obs[0] < -0.05 || obs[7].abs() >= 1.0,
                "{name} seed {seed}: {obs:?}"
            );
            assert!(steps < 300, "{name} seed {seed}: {steps}");
        }
    }
}

#[test]
fn the_hopper_weighs_what_the_model_says() {
    // hopper.xml's capsules at MuJoCo's density 1000: 15.8 kg.
    let env = Planar::hopper();
    assert!(
        (env.total_mass() - 15.8).abs() < 0.1,
        "{}",
        env.total_mass()
    );
}

#[test]
fn the_cheetah_never_terminates_and_weighs_what_the_model_says() {
    let mut env = Planar::cheetah();
    // PyBullet's own half_cheetah.xml: capsules at density 1000 and two feet of 10 kg.
    let mass = env.total_mass();
    assert!((mass - 38.19).abs() < 0.01, "{mass}");
    let mut obs = [0.0f32; 26];
    env.reset(0, &mut obs).unwrap();
    let mut steps = 0;
    loop {
        let t = env.step(&[0.0; 6], &mut obs).unwrap();
        steps += 1;
        assert!(!t.terminated);
        if t.truncated {
            break;
        }
    }
    assert_eq!(steps, 1000);
}

#[test]
fn a_random_cheetah_stays_on_its_feet_at_a_walking_pace() {
    // When joint torques were never cleared they summed up step after step, and random play
    // flung the cheetah at 15+ m/s and onto its back in every episode.
    for seed in 0..3 {
        let (observations, _) = rollout("cheetah", seed, 1000);
        let (mut fastest, mut steepest) = (0.0f32, 0.0f32);
        for obs in observations.chunks(26) {
            fastest = fastest.max((obs[3] / 0.3).abs());
            steepest = steepest.max(obs[7].abs());
        }
        assert!(fastest < 6.0, "seed {seed}: {fastest} m/s");
        assert!(steepest < 1.2, "seed {seed}: pitch {steepest}");
    }
}

#[test]
fn falling_walkers_reach_bullets_terminal_speed() {
    // btMultiBody's drag, -m v (0.04 + 0.04 |v|), balances gravity at v (1 + v) = 9.8 / 0.04:
    // 15.16 m/s. Without drag a 5 s fall would reach 49 m/s.
    let terminal = (-1.0 + (1.0f32 + 4.0 * 9.8 / 0.04).sqrt()) / 2.0;
    let mut obs = vec![0.0f32; 28];
    let mut planar = Planar::hopper();
    planar.reset(0, &mut obs[..15]).unwrap();
    let mut ant = Spatial::ant();
    ant.reset(0, &mut obs).unwrap();
    for (name, speed) in [
        ("hopper", planar.body.drop_for_test(5.0)),
        ("ant", ant.body.drop_for_test(5.0)),
    ] {
        assert!(
            (speed + terminal).abs() < 0.02 * terminal,
            "{name}: {speed} m/s, terminal {terminal}"
        );
    }
}

#[test]
fn the_ant_and_humanoid_weigh_what_pybullet_gives_them() {
    // PyBullet's MJCF importer: density 1000 over each geom's volume (ant.xml's own density 5 is
    // ignored). Ant: 182.2 kg; Humanoid: 42.1 kg plus 7 hinge-chain links of 0.1 g.
    for (mut env, expected) in [(Spatial::ant(), 182.18), (Spatial::humanoid(), 42.117)] {
        let spec = env.spec().clone();
        let mut obs = vec![0.0; spec.obs_dim];
        env.reset(0, &mut obs).unwrap();
        // rapier folds the chain links' own mass in at the first step.
        env.step(&vec![0.0; spec.act_dim], &mut obs).unwrap();
        let mass = env.total_mass();
        assert!((mass - expected).abs() < 0.005, "{}: {mass}", spec.name);
    }
}

#[test]
fn the_humanoids_links_touch_each_other_but_not_their_ancestors_as_in_pybullet() {
    // Links with shapes: 0 torso, 2 lower waist, 3 pelvis; per leg (right 4-7, left 8-11) the
    // thigh on its third hinge and shin and foot on the knee; per arm (right 12-14, left 15-17)
    // the upper arm on its second hinge and the forearm and hand on the elbow.
    let env = Spatial::humanoid();
    let (waist, pelvis, right_thigh, right_shin, left_thigh, left_shin) = (2, 3, 6, 7, 10, 11);
    let (right_forearm, left_forearm) = (14, 17);
    assert!(env.body.links_collide(right_shin, left_shin));
    assert!(env.body.links_collide(right_thigh, left_thigh));
    assert!(env.body.links_collide(right_forearm, left_thigh));
    assert!(env.body.links_collide(left_forearm, pelvis));
    assert!(env.body.links_collide(right_forearm, waist));
    assert!(!env.body.links_collide(right_shin, right_thigh), "a parent");
    assert!(!env.body.links_collide(left_shin, pelvis), "an ancestor");
    assert!(
        !env.body.links_collide(right_forearm, 0),
        "the torso is every arm's ancestor"
    );
    // The Ant's geoms have no conaffinity in its file: its legs pass through each other.
    let ant = Spatial::ant();
    assert!(!ant.body.links_collide(2, 4));

    // Random episodes touch themselves now and then (ours: 40 of 212 steps over these 10).
    let mut env = Spatial::humanoid();
    let (mut obs, mut rng) = ([0.0f32; 44], ChaCha8Rng::seed_from_u64(3));
    let (mut steps, mut touching) = (0, 0);
    for seed in 0..10 {
        env.reset(seed, &mut obs).unwrap();
        loop {
            let action: Vec<f32> = (0..17).map(|_| rng.random_range(-1.0..=1.0)).collect();
            let t = env.step(&action, &mut obs).unwrap();
            steps += 1;
            touching += usize::from(env.body.self_contacts() > 0);
            if t.terminated || t.truncated {
                break;
            }
        }
    }
    assert!(touching > 0, "no self-contact in {steps} steps");
    eprintln!("self-contact in {touching} of {steps} steps");
}

#[test]
fn the_humanoid_without_torques_falls_and_terminates() {
    for seed in 0..3 {
        let mut env = make("humanoid").unwrap();
        let mut obs = [0.0f32; 44];
        env.reset(seed, &mut obs).unwrap();
        // PyBullet fixes the Humanoid's initial_z at 0.8; its torso starts at 1.4.
        assert!((obs[0] - 0.6).abs() < 1e-5, "{}", obs[0]);
        // Facing the target (the parts' mean y is a hair off 0 with the random joint angles).
        assert!(obs[1].abs() < 1e-3 && obs[2] > 0.999, "{obs:?}");
        let mut steps = 0;
        let last = loop {
            let t = env.step(&[0.0; 17], &mut obs).unwrap();
            steps += 1;
            if t.terminated || t.truncated {
                break t;
            }
        };
        assert!(last.terminated && !last.truncated, "seed {seed}");
        assert!(last.reward < 0.0, "dying costs the alive bonus");
        assert!(
            obs[0] + 0.8 <= 0.78,
            "seed {seed}: torso at {}",
            obs[0] + 0.8
        );
        assert!(steps < 300, "seed {seed}: {steps}");
    }
}

/// PyBullet resets the Ant's ankles outside their limits and its limits never push a joint back,
/// so with zero torque the legs give way under the torso: PyBullet's AntBulletEnv-v0 ends at step
/// 20 with its torso on the floor in every one of 30 zero-action episodes (measured with pybullet
/// 3.2.7), and so must ours.
#[test]
fn the_ant_at_rest_collapses_as_pybullets_does() {
    // PyBullet's Ant with zero torque (scripts/conformance/reference_cases.py): every one of its
    // episodes ends by a fall, within these steps.
    let fixture = &reference_cases()["ant_at_rest"];
    let theirs: Vec<u64> = fixture["steps"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s.as_u64().unwrap())
        .collect();
    assert!(
        fixture["terminated"]
            .as_array()
            .unwrap()
            .iter()
            .all(|t| t.as_bool().unwrap())
    );
    let (earliest, latest) = (theirs.iter().min().unwrap(), theirs.iter().max().unwrap());
    let mut env = make("ant").unwrap();
    let mut obs = [0.0f32; 28];
    for seed in 0..5 {
        env.reset(seed, &mut obs).unwrap();
        assert_eq!(obs[0], 0.0);
        assert!(obs[1].abs() < 1e-3 && obs[2] > 0.999, "{obs:?}");
        let mut steps = 0;
        let last = loop {
            let t = env.step(&[0.0; 8], &mut obs).unwrap();
            steps += 1;
            if t.terminated || t.truncated {
                break t;
            }
        };
        assert!(last.terminated, "seed {seed}: stood for {steps} steps");
        // Ours falls within 5 steps of PyBullet's.
        assert!(
            (earliest - 5..=latest + 5).contains(&steps),
            "seed {seed}: fell at step {steps}, PyBullet's at {earliest}..={latest}"
        );
    }
}

#[test]
fn joint_torques_add_no_momentum_and_multibody_links_stay_jointed() {
    for mut env in [Spatial::ant(), Spatial::humanoid()] {
        let spec = env.spec().clone();
        let mut obs = vec![0.0f32; spec.obs_dim];
        env.reset(1, &mut obs).unwrap();
        env.body.float_freely_for_test();
        // Let the reset's self-contacts (the Humanoid's feet may start touching) settle first.
        for _ in 0..60 {
            env.step(&vec![0.0; spec.act_dim], &mut obs).unwrap();
        }
        let (linear_before, angular_before) = env.body.momentum_for_test();
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        // The angular impulse the joints applied: what one-sided torques would have added.
        let mut impulse = 0.0;
        for _ in 0..40 {
            let action: Vec<f32> = (0..spec.act_dim)
                .map(|_| rng.random_range(-1.0..=1.0))
                .collect();
            impulse += env.body.torque_impulse_for_test(&action);
            env.step(&action, &mut obs).unwrap();
        }
        // What is left is the multibody integrator's drift when joints run into their limits:
        // under 1% of that impulse for the Ant, 3-6% for the Humanoid, whose joints hit theirs
        // far more often (one-sided torques would add about all of it).
        let (linear_after, angular_after) = env.body.momentum_for_test();
        let linear = (linear_after - linear_before).length();
        let angular = (angular_after - angular_before).length();
        assert!(impulse > 100.0, "{}: {impulse}", spec.name);
        assert!(
            linear < 0.1 * impulse,
            "{}: linear momentum {linear}, impulse {impulse}",
            spec.name
        );
        assert!(
            angular < 0.1 * impulse,
            "{}: angular momentum {angular}, impulse {impulse}",
            spec.name
        );
        let gap = env.body.largest_joint_gap_for_test();
        assert!(gap < 1e-3, "{}: a joint came apart by {gap} m", spec.name);
    }
}

#[test]
fn a_3d_trace_integrates_the_predicted_forward_speed() {
    let mut env = Spatial::humanoid();
    let mut obs = [0.0f32; 44];
    env.reset(2, &mut obs).unwrap();
    // Three predicted states moving forward at 1 m/s (obs[3] = 0.3 vx) at a constant height.
    let mut predicted = Vec::new();
    for _ in 0..3 {
        let mut o = obs;
        o[3] = 0.3;
        o[4] = 0.0;
        predicted.extend_from_slice(&o);
    }
    let trace = env.trace(&predicted);
    assert_eq!(trace.len(), 3);
    for pair in trace.windows(2) {
        assert!((pair[1].0 - pair[0].0 - 0.0165).abs() < 1e-5, "{trace:?}");
        assert!((pair[1].1 - pair[0].1).abs() < 1e-6, "{trace:?}");
    }
}

#[test]
fn walkers_report_their_forward_position_and_the_others_none() {
    for name in DOMAINS {
        let mut env = make(name).unwrap();
        let mut obs = vec![0.0f32; env.spec().obs_dim];
        env.reset(4, &mut obs).unwrap();
        let walker = !matches!(*name, "pendulum" | "lander");
        assert_eq!(env.forward_position().is_some(), walker, "{name}");
        if let Some(x) = env.forward_position() {
            // Every walker starts at the origin, 1 km before its target.
            assert!(x.abs() < 0.5, "{name}: starts at x = {x}");
        }
    }
}

#[test]
fn the_walkers_reward_terms_sum_to_their_reward() {
    for name in ["hopper", "walker", "cheetah", "ant", "humanoid"] {
        let mut env = make(name).unwrap();
        let (od, ad) = (env.spec().obs_dim, env.spec().act_dim);
        let mut obs = vec![0.0; od];
        env.reset(5, &mut obs).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for _ in 0..50 {
            let action: Vec<f32> = (0..ad).map(|_| rng.random_range(-1.0..=1.0)).collect();
            let t = env.step(&action, &mut obs).unwrap();
            let terms = env.reward_terms();
            let names: Vec<&str> = terms.iter().map(|(n, _)| *n).collect();
            assert_eq!(
                names,
                ["alive", "progress", "electricity", "joints_at_limit"],
                "{name}"
            );
            let sum: f64 = terms.iter().map(|(_, v)| v).sum();
            assert!(
                (sum - t.reward).abs() < 1e-9,
                "{name}: {sum} vs {}",
                t.reward
            );
            if t.terminated || t.truncated {
                break;
            }
        }
    }
    assert!(make("pendulum").unwrap().reward_terms().is_empty());
}

/// The robots as PyBullet 3.2.7 simulates them, read back from it by
/// scripts/conformance/pybullet_bodies.py.
const PYBULLET_BODIES: &str = include_str!("../../tests/fixtures/pybullet-bodies.json");

#[test]
fn the_walkers_weigh_bend_and_push_as_in_pybullet() {
    let fixture: serde_json::Value = serde_json::from_str(PYBULLET_BODIES).unwrap();
    let f32_of = |v: &serde_json::Value| v.as_f64().unwrap() as f32;
    type Measured = ((f32, [f32; 3]), Vec<((f32, f32), f32)>, usize);
    let robots: [(&str, Measured); 5] = [
        ("hopper", {
            let e = Planar::hopper();
            (
                e.body.mass_and_centre_for_test(),
                e.body.joints_for_test(),
                e.body.parts_for_test(),
            )
        }),
        ("walker", {
            let e = Planar::walker();
            (
                e.body.mass_and_centre_for_test(),
                e.body.joints_for_test(),
                e.body.parts_for_test(),
            )
        }),
        ("cheetah", {
            let e = Planar::cheetah();
            (
                e.body.mass_and_centre_for_test(),
                e.body.joints_for_test(),
                e.body.parts_for_test(),
            )
        }),
        ("ant", {
            let e = Spatial::ant();
            (
                e.body.mass_and_centre_for_test(),
                e.body.joints_for_test(),
                e.body.parts_for_test(),
            )
        }),
        ("humanoid", {
            let e = Spatial::humanoid();
            (
                e.body.mass_and_centre_for_test(),
                e.body.joints_for_test(),
                e.body.parts_for_test(),
            )
        }),
    ];
    for (name, ((mass, centre), joints, parts)) in robots {
        let robot = &fixture[name];
        let links = robot["links"].as_array().unwrap();
        // Mass and centre of mass with every joint at 0 (links that only chain hinges weigh
        // 0.1 g here and nothing there; the Humanoid's near-identity body quaternions, dropped
        // here, move its feet by up to 8 mm there).
        let their_mass: f32 = links.iter().map(|l| f32_of(&l["mass"])).sum();
        assert!(
            (mass - their_mass).abs() < 0.01,
            "{name}: {mass} kg against {their_mass}"
        );
        for axis in 0..3 {
            let moment: f32 = links
                .iter()
                .map(|l| f32_of(&l["mass"]) * f32_of(&l["com"][axis]))
                .sum();
            let theirs = moment / their_mass;
            assert!(
                (centre[axis] - theirs).abs() < 3e-3,
                "{name}: centre of mass axis {axis} at {} against {theirs}",
                centre[axis]
            );
        }
        // Limits and torques per motor, in PyBullet's order.
        let motors = robot["motors"].as_array().unwrap();
        assert_eq!(joints.len(), motors.len(), "{name}");
        for (((lo, hi), torque), motor) in joints.iter().zip(motors) {
            let joint = motor["joint"].as_str().unwrap();
            let link = links.iter().find(|l| l["joint"] == joint).unwrap();
            let range = &link["range"];
            assert!(
                (lo - f32_of(&range[0])).abs() < 1e-3 && (hi - f32_of(&range[1])).abs() < 1e-3,
                "{name} {joint}: {lo}..{hi} against {range}"
            );
            assert_eq!(*torque, f32_of(&motor["torque"]), "{name} {joint}");
        }
        assert_eq!(parts, robot["parts"].as_array().unwrap().len(), "{name}");
    }
}

/// A fixture's JSON array of numbers.
fn floats(v: &serde_json::Value) -> Vec<f32> {
    let values = v.as_array().unwrap();
    values.iter().map(|x| x.as_f64().unwrap() as f32).collect()
}

/// Cases measured in PyBullet by scripts/conformance/reference_cases.py: the Hopper dropped
/// flat-footed, a thigh torque in the air, the Ant at rest.
fn reference_cases() -> serde_json::Value {
    serde_json::from_str(include_str!(
        "../../tests/fixtures/pybullet-reference-cases.json"
    ))
    .unwrap()
}

/// PyBullet's planar walkers in states random actions brought them to, one random action each
/// and what PyBullet observes after it (scripts/conformance/matched_states.py --step-fixture).
const PYBULLET_STEPS: &str = include_str!("../../tests/fixtures/pybullet-steps.json");

#[test]
fn planar_walkers_step_from_pybullets_states_as_pybullet_does() {
    let fixture: serde_json::Value = serde_json::from_str(PYBULLET_STEPS).unwrap();
    // Mean absolute differences after one step in what PyBullet's step returns, whose torso is
    // where the last substep found it (height m, forward speed m/s, pitch rad, joint angle over
    // its range, the progress reward's body x m). With Bullet's floor manifold and contact ERP
    // the largest are the Walker's, 4e-5 m, 0.0016 m/s, 6e-5 rad, 1.4e-4 and 3e-5 m; rapier's
    // own contacts at ERP 0.08 were up to 0.009 m/s off, a free root integrated at the torso
    // 0.18 m/s, and the body x of the current poses is 0.007 m off on the Hopper.
    let bounds = [
        ("height", 0.0003),
        ("forward speed", 0.005),
        ("pitch", 0.0002),
        ("joint angle", 0.0006),
        ("body x", 0.0003),
    ];
    // Observed feet contacts that agree with PyBullet's, over all robots' cases and feet.
    let (mut contacts_agreeing, mut contacts) = (0, 0);
    for name in ["hopper", "walker", "cheetah"] {
        let mut env = Planar::named(name).unwrap();
        let n = env.spec().act_dim;
        let mut obs = vec![0.0; env.spec().obs_dim];
        let cases = fixture[name].as_array().unwrap();
        assert!(cases.len() >= 10, "{name}");
        let mut sums = [0.0f32; 5];
        for case in cases {
            let state: PlanarState = serde_json::from_value(case["state"].clone()).unwrap();
            env.set_state(&state, &mut obs).unwrap();
            env.step(&floats(&case["actions"][0]), &mut obs).unwrap();
            let step = &case["pybullet"]["steps"][0];
            let theirs = floats(&step["obs"]);
            let term = |name: &str| {
                let ours = env
                    .reward_terms()
                    .iter()
                    .find(|(n, _)| *n == name)
                    .unwrap()
                    .1;
                (ours, step["reward_terms"][name].as_f64().unwrap())
            };
            let (alive, their_alive) = term("alive");
            assert_eq!(alive, their_alive, "{name}: alive bonus after a step");
            let feet = walker_base::MORE + 2 * n;
            let [body_x, ..] = env
                .body
                .scores_for_test(&obs[feet..], &floats(&case["actions"][0]));
            sums[4] += (body_x - step["body_x"].as_f64().unwrap()).abs() as f32;
            let joints: f32 = (0..n)
                .map(|j| (obs[8 + 2 * j] - theirs[8 + 2 * j]).abs() / 2.0)
                .sum();
            sums[0] += (obs[0] - theirs[0]).abs();
            sums[1] += (obs[3] - theirs[3]).abs() / 0.3;
            sums[2] += (obs[7] - theirs[7]).abs();
            sums[3] += joints / n as f32;
            // The contacts the step measured, which the next observation shows.
            let now = floats(&step["obs_now"]);
            for (ours, theirs) in env.body.feet_contact_for_test().iter().zip(&now[feet..]) {
                contacts += 1;
                contacts_agreeing += usize::from(ours == theirs);
            }
        }
        for ((what, bound), sum) in bounds.iter().zip(sums) {
            let mean = sum / cases.len() as f32;
            eprintln!("{name}: {what} {mean}");
            assert!(
                mean < *bound,
                "{name}: {what} {mean} off PyBullet's after a step"
            );
        }
    }
    // All 108 with each foot's Bullet contact threshold; 101 with one of 5 mm, 82 with rapier's
    // 2 cm prediction distance.
    assert!(
        contacts_agreeing == contacts,
        "{contacts_agreeing} of {contacts} contacts as PyBullet's"
    );
}

/// PyBullet's planar walkers in states random actions brought them to, with what PyBullet
/// observes and scores there (scripts/conformance/matched_states.py --fixture).
const PYBULLET_STATES: &str = include_str!("../../tests/fixtures/pybullet-states.json");

#[test]
fn planar_walkers_set_to_pybullets_states_observe_and_score_as_pybullet() {
    let fixture: serde_json::Value = serde_json::from_str(PYBULLET_STATES).unwrap();
    for name in ["hopper", "walker", "cheetah"] {
        let mut env = Planar::named(name).unwrap();
        let mut obs = vec![0.0; env.spec().obs_dim];
        let cases = fixture[name].as_array().unwrap();
        assert!(cases.len() >= 3, "{name}");
        for (k, case) in cases.iter().enumerate() {
            let state: PlanarState = serde_json::from_value(case["state"].clone()).unwrap();
            env.set_state(&state, &mut obs).unwrap();
            // Everything but the feet contacts, which PyBullet keeps from its last step and a
            // set state has not had.
            let theirs = floats(&case["obs"]);
            let feet = walker_base::MORE + 2 * env.spec().act_dim;
            for i in 0..feet {
                assert!(
                    (obs[i] - theirs[i]).abs() < 2e-3,
                    "{name} case {k}: obs[{i}] {} against {}",
                    obs[i],
                    theirs[i]
                );
            }
            let [body_x, alive, power, at_limit] = env
                .body
                .scores_for_test(&theirs[feet..], &floats(&case["action"]));
            let expect = |what: &str, ours: f64, tolerance: f64| {
                let theirs = case[what].as_f64().unwrap();
                assert!(
                    (ours - theirs).abs() < tolerance,
                    "{name} case {k}: {what} {ours} against {theirs}"
                );
            };
            expect("body_x", body_x, 1e-3);
            expect("alive", alive, 1e-9);
            expect("electricity", power, 1e-3);
            expect("joints_at_limit", at_limit, 1e-9);
        }
    }
    // A state of the wrong shape or with a NaN is refused and changes nothing.
    let mut env = Planar::hopper();
    let mut obs = vec![0.0; env.spec().obs_dim];
    env.reset(3, &mut obs).unwrap();
    let before = obs.clone();
    let short = PlanarState {
        joints: vec![0.0; 2],
        joint_velocities: vec![0.0; 3],
        ..PlanarState::default()
    };
    let err = env.set_state(&short, &mut obs).unwrap_err();
    assert!(err.to_string().contains("2 joint angles"), "{err}");
    let nan = PlanarState {
        root: [0.0, f32::NAN, 0.0],
        joints: vec![0.0; 3],
        joint_velocities: vec![0.0; 3],
        ..PlanarState::default()
    };
    let err = env.set_state(&nan, &mut obs).unwrap_err();
    assert!(err.to_string().contains("finite"), "{err}");
    let two_feet = PlanarState {
        joints: vec![0.0; 3],
        joint_velocities: vec![0.0; 3],
        feet_contact: vec![1.0, 0.0],
        ..PlanarState::default()
    };
    let err = env.set_state(&two_feet, &mut obs).unwrap_err();
    assert!(err.to_string().contains("2 feet contacts"), "{err}");
    assert_eq!(obs, before);
    env.step(&[0.0; 3], &mut obs).unwrap();
}

/// The Hopper in the air with its thigh `past` rad beyond its upper limit and no torque: how
/// far past the limit the thigh is after each of `steps` steps.
fn thigh_past_its_limit(past: f32, steps: usize) -> Vec<f32> {
    let mut env = Planar::named("hopper").unwrap();
    let (lo, hi) = env.body.joints_for_test()[0].0;
    let state = PlanarState {
        root: [0.0, 2.0, 0.0],
        root_velocity: [0.0; 3],
        joints: vec![hi + past, 0.0, 0.0],
        joint_velocities: vec![0.0; 3],
        ..PlanarState::default()
    };
    let mut obs = vec![0.0; env.spec().obs_dim];
    env.set_state(&state, &mut obs).unwrap();
    (0..steps)
        .map(|_| {
            env.step(&[0.0; 3], &mut obs).unwrap();
            // obs[8] is 2 (q - mid) / (hi - lo).
            lo + (obs[8] + 1.0) * (hi - lo) / 2.0 - hi
        })
        .collect()
}

#[test]
fn a_joint_just_past_its_limit_is_pushed_back_as_in_pybullet() {
    // PyBullet (HopperBulletEnv-v0, the same state): 0.02 past goes to 0.0054, -0.0091, -0.0237
    // (Bullet's ERP 0.2 per substep, the correcting speed kept); 0.041 and more stay put.
    let small = thigh_past_its_limit(0.02, 3);
    assert!(0.0 < small[0] && small[0] < 0.01, "{small:?}");
    assert!(small[1] < 0.0 && small[2] < -0.01, "{small:?}");
    for past in [0.045, 0.2] {
        let far = thigh_past_its_limit(past, 3);
        assert!(
            far.iter().all(|q| (q - past).abs() < 1e-3),
            "{past}: {far:?}"
        );
    }
}

#[test]
fn the_limit_spring_is_bullets_erp_with_almost_no_cfm() {
    let dt = walker_base::CONTROL_PERIOD / walker_base::BULLET_SUBSTEPS as f32;
    let (frequency, damping) = walker_base::bullet_limit_spring(0.01, dt, 1.0);
    let spring = rapier2d::prelude::SpringCoefficients::new(frequency, damping);
    assert!((spring.erp(dt) - walker_base::BULLET_LIMIT_ERP).abs() < 1e-5);
    assert!(spring.cfm_coeff(dt) < 1e-3);
    let stop =
        walker_base::bullet_limit_spring(walker_base::BULLET_SPLIT_IMPULSE_THRESHOLD, dt, 1.0);
    assert_eq!(stop, walker_base::BULLET_LIMIT_SPRING);
}

#[test]
fn the_contact_spring_is_bullets_contact_erp_with_almost_no_cfm() {
    let dt = walker_base::CONTROL_PERIOD / walker_base::BULLET_SUBSTEPS as f32;
    let (frequency, damping) = walker_base::bullet_erp_spring(walker_base::BULLET_CONTACT_ERP, dt);
    let spring = rapier2d::prelude::SpringCoefficients::new(frequency, damping);
    assert!((spring.erp(dt) - 0.9).abs() < 1e-5);
    assert!(spring.cfm_coeff(dt) < 1e-3);
}

#[test]
fn a_hopper_dropped_flat_footed_lands_on_its_foot_as_in_pybullet() {
    // PyBullet (HopperBulletEnv-v0; scripts/conformance/reference_cases.py): the root's slides
    // at rest, falling at 0.5 m/s, joints at 0, no torque. After 3 steps the torso is observed
    // about 3.4 cm lower and the foot, 6.35 mm above the floor at the last collision detection,
    // touches (its contact breaking threshold is 6.54 mm), which the next step's observation
    // shows; it lands within that step. A box floor let the level capsule through to the leg,
    // 6.01 cm lower.
    let case = &reference_cases()["hopper_drop"];
    let theirs: Vec<Vec<f32>> = case["observations"]
        .as_array()
        .unwrap()
        .iter()
        .map(floats)
        .collect();
    let mut env = Planar::named("hopper").unwrap();
    let state: PlanarState = serde_json::from_value(case["state"].clone()).unwrap();
    let action = floats(&case["action"]);
    let mut obs = vec![0.0; env.spec().obs_dim];
    env.set_state(&state, &mut obs).unwrap();
    let foot = obs.len() - 1;
    // The lowest PyBullet's torso is observed once landed.
    let lowest = theirs[3..]
        .iter()
        .map(|o| o[0])
        .fold(f32::INFINITY, f32::min);
    for (step, theirs) in (1..=8).zip(&theirs) {
        env.step(&action, &mut obs).unwrap();
        let (z, touching) = (obs[0], obs[foot]);
        assert_eq!(touching, theirs[foot], "step {step}");
        match step {
            1 | 2 => {}
            3 => assert!((z - theirs[0]).abs() < 1e-4, "{z} against {}", theirs[0]),
            _ => assert!(
                z > lowest - 0.002,
                "step {step}: {z}, PyBullet's lowest {lowest}"
            ),
        }
        // Bullet lands the level foot on its heel alone and tilts it onto the toe a substep
        // later: the torso rebounds and the foot turns. Landing on both ends at once stopped it
        // dead.
        if step == 4 {
            let (vz, foot_angle) = (obs[5] / 0.3, obs[12]);
            let (their_vz, their_angle) = (theirs[5] / 0.3, theirs[12]);
            assert!(
                (vz - their_vz).abs() < 0.005 && (foot_angle - their_angle).abs() < 0.003,
                "rebound {vz} against {their_vz}, foot {foot_angle} against {their_angle}"
            );
        }
    }
}

#[test]
fn a_thigh_torque_in_the_air_moves_the_hopper_as_bullets_explicit_coriolis_does() {
    // PyBullet (HopperBulletEnv-v0; scripts/conformance/reference_cases.py): the root's slides
    // at x 0, z 1.0 moving forward at 2.5 m/s, level, joints at -0.3, -0.3, 0 and still, the
    // thigh's full torque backwards for one step (PyBullet: forward 2.3242 m/s, vertical -1.1900,
    // pitch -0.0620). rapier's semi-implicit Coriolis term gave a vertical speed of -0.7531.
    let case = &reference_cases()["thigh_torque"];
    let theirs = floats(&case["observation"]);
    let mut env = Planar::named("hopper").unwrap();
    let state: PlanarState = serde_json::from_value(case["state"].clone()).unwrap();
    let mut obs = vec![0.0; env.spec().obs_dim];
    env.set_state(&state, &mut obs).unwrap();
    env.step(&floats(&case["action"]), &mut obs).unwrap();
    let (vx, vz, pitch) = (obs[3] / 0.3, obs[5] / 0.3, obs[7]);
    let (their_vx, their_vz, their_pitch) = (theirs[3] / 0.3, theirs[5] / 0.3, theirs[7]);
    assert!(
        (vx - their_vx).abs() < 2e-3
            && (vz - their_vz).abs() < 2e-3
            && (pitch - their_pitch).abs() < 5e-4,
        "forward {vx} ({their_vx}), vertical {vz} ({their_vz}), pitch {pitch} ({their_pitch})"
    );
}

#[test]
fn bullets_bounds_give_the_feet_thresholds_measured_in_pybullet() {
    // 0.02 x the angular motion disc of a link's `fromto` capsules (two spheres with a 4 cm
    // margin) and spheres about its centre of mass: the rule the other links' thresholds follow.
    // The HalfCheetah's capsules are placed by `pos` (btCapsuleShapeZ, bounded otherwise); the
    // Humanoid's foot is a link of its own in PyBullet (a sphere 0.1 m from its frame), part of
    // the shin's in ours.
    let (hopper, walker, ant) = (Planar::hopper(), Planar::walker(), Spatial::ant());
    let thresholds = |feet: &[walker_base::Foot], bounded: &dyn Fn(usize) -> f32| {
        feet.iter()
            .map(|f| (f.contact_threshold, bounded(f.link)))
            .collect::<Vec<_>>()
    };
    let robots = [
        (
            "hopper",
            thresholds(hopper.body.feet(), &|k| hopper.body.bounded_threshold(k)),
        ),
        (
            "walker",
            thresholds(walker.body.feet(), &|k| walker.body.bounded_threshold(k)),
        ),
        (
            "ant",
            thresholds(ant.body.feet(), &|k| ant.body.bounded_threshold(k)),
        ),
    ];
    for (name, feet) in robots {
        for (measured, bounded) in feet {
            assert!(
                (measured - bounded).abs() < 2e-5,
                "{name}: {bounded} against PyBullet's {measured}"
            );
        }
    }
}

#[test]
fn an_ankle_on_its_long_axis_turns_as_in_pybullet() {
    // PyBullet (AntBulletEnv-v0) set to our reset of seed 1000, the first ankle (axis (-1, 1, 0),
    // which Bullet does not normalise) under a full torque for one step: its observed angle
    // moves by 0.0345 and its speed reads 0.204; the hip (axis (0, 0, 1)) 0.0337 and 0.228.
    // rapier's unit axis turned the ankle twice as far (0.069, 0.408).
    for (joint, moved, speed) in [(1, 0.0345, 0.204), (0, 0.0337, 0.228)] {
        let mut env = Spatial::ant();
        let mut obs = vec![0.0; env.spec().obs_dim];
        env.reset(1000, &mut obs).unwrap();
        let start = obs[walker_base::MORE + 2 * joint];
        let mut action = [0.0; 8];
        action[joint] = 1.0;
        env.step(&action, &mut obs).unwrap();
        let (position, rate) = (
            obs[walker_base::MORE + 2 * joint],
            obs[walker_base::MORE + 2 * joint + 1],
        );
        assert!(
            (position - start - moved).abs() < 5e-4 && (rate - speed).abs() < 2e-3,
            "joint {joint}: moved {}, speed {rate}",
            position - start
        );
    }
}

/// The Ant and Humanoid from our resets, PyBullet's robots set to the same joint angles, six
/// random actions each and what PyBullet observes after them (scripts/conformance/from_reset.py
/// --fixture).
const PYBULLET_RESET_STEPS: &str = include_str!("../../tests/fixtures/pybullet-reset-steps.json");

#[test]
fn the_3d_walkers_follow_pybullets_from_matched_resets() {
    let fixture: serde_json::Value = serde_json::from_str(PYBULLET_RESET_STEPS).unwrap();
    // Largest absolute difference over the cases' six steps (height m, forward speed m/s, roll
    // and pitch rad, joint angle over its range). Measured: the Ant's below 2e-4, the Humanoid's
    // 0.0005 m, 0.008 m/s, 0.002 rad and 0.006; with its torso moving about the model's torso
    // frame instead of its centre of mass and 10 g hinge-chain links, 0.013 m and 0.011.
    let bounds = [
        ("height", 0.0015),
        ("forward speed", 0.02),
        ("roll", 0.004),
        ("pitch", 0.004),
        ("joint angle", 0.008),
    ];
    for name in ["ant", "humanoid"] {
        let mut env = make(name).unwrap();
        let n = env.spec().act_dim;
        let mut obs = vec![0.0; env.spec().obs_dim];
        let cases = fixture[name].as_array().unwrap();
        assert!(cases.len() >= 5, "{name}");
        let mut worst = [0.0f32; 5];
        for case in cases {
            env.reset(case["seed"].as_u64().unwrap(), &mut obs).unwrap();
            let actions = case["actions"].as_array().unwrap();
            let observed = case["observations"].as_array().unwrap();
            for (action, theirs) in actions.iter().zip(observed) {
                env.step(&floats(action), &mut obs).unwrap();
                let theirs = floats(theirs);
                let joints = (0..n)
                    .map(|j| (obs[8 + 2 * j] - theirs[8 + 2 * j]).abs() / 2.0)
                    .fold(0.0f32, f32::max);
                let diffs = [
                    (obs[0] - theirs[0]).abs(),
                    (obs[3] - theirs[3]).abs() / 0.3,
                    (obs[6] - theirs[6]).abs(),
                    (obs[7] - theirs[7]).abs(),
                    joints,
                ];
                for (w, d) in worst.iter_mut().zip(diffs) {
                    *w = w.max(d);
                }
            }
        }
        for ((what, bound), largest) in bounds.iter().zip(worst) {
            assert!(
                largest < *bound,
                "{name}: {what} {largest} off PyBullet's within six steps"
            );
        }
    }
}

/// Plays swinging torques from a reset until the episode ends or 200 steps: each observation's
/// feet contacts must be those `measured` after the step before (none after a reset), and some
/// foot must touch the ground.
fn observes_feet_contacts_one_step_late<E: Env>(
    name: &str,
    mut env: E,
    measured: fn(&E) -> &[f32],
) {
    let mut obs = vec![0.0; env.spec().obs_dim];
    env.reset(5, &mut obs).unwrap();
    let feet = walker_base::MORE + 2 * env.spec().act_dim;
    let mut before = vec![0.0; obs.len() - feet];
    assert_eq!(obs[feet..], before[..], "{name} after a reset");
    let mut landed = false;
    for step in 0..200 {
        let action: Vec<f32> = (0..env.spec().act_dim)
            .map(|k| (0.3 * step as f32 + k as f32).sin())
            .collect();
        let transition = env.step(&action, &mut obs).unwrap();
        assert_eq!(obs[feet..], before[..], "{name} step {step}");
        before = measured(&env).to_vec();
        landed |= before.contains(&1.0);
        if transition.terminated {
            break;
        }
    }
    assert!(landed, "{name} never touched the ground");
}

#[test]
fn every_walker_observes_the_feet_contacts_one_step_late_as_pybullet() {
    // PyBullet's step updates `robot.feet_contact` after it has observed and scored, so a step's
    // observation shows the contacts the step before measured (the planar walkers' are checked
    // against PyBullet's own steps above).
    for name in ["hopper", "walker", "cheetah"] {
        let env = Planar::named(name).unwrap();
        observes_feet_contacts_one_step_late(name, env, |e: &Planar| {
            e.body.feet_contact_for_test()
        });
    }
    observes_feet_contacts_one_step_late("ant", Spatial::ant(), |e: &Spatial| {
        e.body.feet_contact_for_test()
    });
    let humanoid = Spatial::humanoid();
    observes_feet_contacts_one_step_late("humanoid", humanoid, |e: &Spatial| {
        e.body.feet_contact_for_test()
    });
}

#[test]
fn control_periods_come_from_each_domains_spec() {
    for &name in DOMAINS {
        let period = control_period(name).unwrap();
        assert_eq!(period, make(name).unwrap().spec().control_period, "{name}");
        assert!(period > 0.0 && period < 0.1, "{name}: {period}");
    }
    assert_eq!(control_period("toy"), None);
}

#[test]
fn every_domain_names_each_observation_and_action_entry_once() {
    for &name in DOMAINS {
        let env = make(name).unwrap();
        let spec = env.spec();
        let f = features(name).unwrap_or_else(|| panic!("{name} has no features"));
        assert_eq!(f.observation.len(), spec.obs_dim, "{name}");
        assert_eq!(f.action.len(), spec.act_dim, "{name}");
        for entries in [&f.observation, &f.action] {
            let names: std::collections::HashSet<&str> =
                entries.iter().map(|e| e.name.as_str()).collect();
            assert_eq!(names.len(), entries.len(), "{name}: a name twice");
            assert!(entries.iter().all(|e| !e.unit.is_empty()), "{name}");
        }
    }
    assert_eq!(features("toy"), None);
}
