//! The shipped bundles do their tasks (the criteria of docs/results.md), on seeds their training
//! runs never evaluated on. A walker's forward distance comes from `Env::forward_position`.

use std::path::Path;
use std::sync::Arc;

use prac::eval::{Episode, mean_std, policy_episodes};

fn play(domain: &str, episodes: usize) -> (Arc<prac::policy::Policy>, Vec<Episode>) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("bundles/{domain}.safetensors"));
    let policy = Arc::new(prac::bundle::load(&path).unwrap());
    assert_eq!(policy.manifest.domain, domain);
    let mut env = prac::domains::make(domain).unwrap();
    let played = policy_episodes(&policy, env.as_mut(), episodes, 777_000).unwrap();
    (policy, played)
}

/// Episodes the task did not end early (the robot did not fall).
fn count_upright(episodes: &[Episode]) -> usize {
    episodes.iter().filter(|e| !e.terminated).count()
}

fn mean_return(episodes: &[Episode]) -> f64 {
    mean_std(&episodes.iter().map(|e| e.ret).collect::<Vec<_>>()).0
}

#[test]
fn the_shipped_pendulum_bundle_solves_pendulum() {
    let (policy, episodes) = play("pendulum", 30);
    let mean = mean_return(&episodes);
    assert!(mean >= -200.0, "mean return {mean}");
    let scale = policy.manifest.value_scale.unwrap();
    assert!(scale.v_pi > scale.v_rand);
}

#[test]
fn the_shipped_lander_bundle_lands() {
    let (_, episodes) = play("lander", 20);
    let mean = mean_return(&episodes);
    assert!(mean >= 200.0, "mean return {mean}");
}

#[test]
fn the_shipped_cheetah_bundle_runs_forward() {
    let (_, episodes) = play("cheetah", 3);
    for e in &episodes {
        assert!(!e.terminated && e.len == 1000, "{} steps", e.len);
        let distance = e.distance.unwrap();
        // 33.7 m on average over 50 episodes (PyBullet: 30.7 m with the same policy).
        assert!(distance > 25.0, "ran {distance} m");
        // The progress reward sums to distance / control period, and the alive bonus is at
        // most 1 per step: the return bounds the distance from below.
        assert!(
            distance >= 0.0165 * (e.ret - 1000.0) - 0.01,
            "ran {distance} m for a return of {}",
            e.ret
        );
    }
}

/// The walker criterion: moving forward without falling in at least 80% of episodes.
fn walks_forward_without_falling(domain: &str) {
    let (_, episodes) = play(domain, 5);
    let upright = count_upright(&episodes);
    assert!(
        upright * 5 >= episodes.len() * 4,
        "{domain}: {upright} of 5 upright"
    );
    for e in &episodes {
        let distance = e.distance.unwrap();
        assert!(
            distance > 10.0,
            "{domain}: moved {distance} m in {} steps",
            e.len
        );
    }
}

#[test]
fn the_shipped_walker_bundle_walks_forward_without_falling() {
    walks_forward_without_falling("walker");
}

#[test]
fn the_shipped_ant_bundle_walks_forward_without_falling() {
    walks_forward_without_falling("ant");
}

#[test]
fn the_shipped_hopper_bundle_hops_forward_without_falling() {
    walks_forward_without_falling("hopper");
}

/// The Humanoid's criterion: upright for all 1000 steps in at least 80% of episodes, walking at
/// least 10 m forward on average (a fallen episode counts with the distance it made).
#[test]
fn the_shipped_humanoid_bundle_walks_without_falling() {
    let (_, episodes) = play("humanoid", 5);
    let upright = count_upright(&episodes);
    assert!(upright >= 4, "{upright} of 5 upright");
    let distances: Vec<f64> = episodes.iter().map(|e| e.distance.unwrap()).collect();
    let mean = mean_std(&distances).0;
    assert!(mean >= 10.0, "walked {mean} m on average: {distances:?}");
}
