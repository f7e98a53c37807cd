//! Fixtures for tests, benchmarks and fuzzing: random policies of a given architecture, the
//! toy policy the tests serve, and the fuzz targets. Not part of prac's API.

use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::manifest::{
    ActorKind, ActorSpec, CriticSpec, FORMAT_VERSION, Manifest, ModelSpec, Normalization,
    Provenance, QAggregation, ValueScale,
};
use crate::nn::{Activation, Dense, Mlp};
use crate::policy::{Actor, DynamicsModel, Policy};

#[cfg(any(test, feature = "fuzz"))]
pub mod fuzz;

/// The server's session and its step pipeline, for the allocation audit and the Replan bench.
pub mod serve {
    pub use crate::serve::arrival::Arrival;
    pub use crate::serve::session::{Session, SessionSettings, StepInput};
}

/// Whether this thread is inside a call into the physics engine, where rapier allocates: the
/// allocation audit counts those allocations apart from the domains' own.
pub fn in_physics_engine() -> bool {
    crate::domains::in_engine()
}

/// Each critic's layer norms as (scale, shift) per hidden layer (empty without layer norm).
pub fn critic_norms(policy: &Policy) -> Vec<Vec<(Vec<f32>, Vec<f32>)>> {
    let norms = |critic: &Mlp| {
        let each = |n: &crate::nn::LayerNorm| (n.scale().to_vec(), n.shift().to_vec());
        critic.norms().iter().map(each).collect()
    };
    policy.critics.iter().map(norms).collect()
}

/// Observation and action sizes of the toy policy.
pub const TOY_OBS: usize = 3;
pub const TOY_ACT: usize = 2;

/// A small random policy: obs 3, act 2, actions in [-2, 2] x [0, 1].
pub fn toy_policy(name: &str, seed: u64) -> Policy {
    let mut manifest = test_manifest(name, "toy", TOY_OBS, TOY_ACT, &[32, 32], &[16, 16]);
    manifest.action_low = vec![-2.0, 0.0];
    manifest.action_high = vec![2.0, 1.0];
    random_policy(manifest, seed)
}

/// A policy with PyTorch-default random weights (U(+-1/sqrt(fan_in))) for the manifest's
/// architecture: for benchmarks and tests.
pub fn random_policy(manifest: Manifest, seed: u64) -> Policy {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (obs, act) = (manifest.obs_dim, manifest.act_dim);
    let mut dense = |out: usize, inp: usize| {
        let bound = 1.0 / (inp as f32).sqrt();
        let w: Vec<f32> = (0..out * inp)
            .map(|_| rng.random_range(-bound..bound))
            .collect();
        let b: Vec<f32> = (0..out).map(|_| rng.random_range(-bound..bound)).collect();
        Dense::from_row_major(out, inp, &w, &b)
    };
    let mut chain = |inp: usize, hidden: &[usize], out: Option<usize>| {
        let mut layers = Vec::new();
        let mut width = inp;
        for &h in hidden.iter().chain(out.as_ref()) {
            layers.push(dense(h, width));
            width = h;
        }
        layers
    };
    let spec = &manifest.actor;
    let trunk = Mlp::new(obs, chain(obs, &spec.hidden, None), spec.activation, true)
        .expect("consistent shapes");
    let latent = trunk.output_dim();
    let critics = (0..manifest.critic.n_critics)
        .map(|_| {
            Mlp::new(
                obs + act,
                chain(obs + act, &manifest.critic.hidden, Some(1)),
                manifest.critic.activation,
                false,
            )
            .expect("consistent shapes")
        })
        .collect();
    let model = manifest.model.as_ref().map(|spec| DynamicsModel {
        net: Mlp::new(
            obs + act,
            chain(obs + act, &spec.hidden, Some(obs)),
            spec.activation,
            false,
        )
        .expect("consistent shapes"),
        normalization: spec.normalization.clone(),
    });
    let mu = chain(latent, &[], Some(act)).remove(0);
    let log_std = chain(latent, &[], Some(act)).remove(0);
    Policy {
        content_hash: String::new(),
        actor: Actor {
            trunk,
            mu,
            log_std: Some(log_std),
            mean_clip: f32::INFINITY,
        },
        critics,
        model,
        manifest,
    }
}

/// The architecture of the paper's Hopper policy (SB3 defaults, model 4 x 64), for benchmarks and
/// tests.
pub fn hopper_sized_manifest() -> Manifest {
    test_manifest(
        "hopper-bench",
        "hopper",
        15,
        3,
        &[256, 256],
        &[64, 64, 64, 64],
    )
}

/// A manifest with identity normalisation, symmetric unit action bounds and a made-up value
/// scale: for benchmarks and tests that build their own networks.
pub fn test_manifest(
    name: &str,
    domain: &str,
    obs_dim: usize,
    act_dim: usize,
    hidden: &[usize],
    model_hidden: &[usize],
) -> Manifest {
    Manifest {
        format_version: FORMAT_VERSION,
        name: name.to_string(),
        domain: domain.to_string(),
        obs_dim,
        act_dim,
        action_low: vec![-1.0; act_dim],
        action_high: vec![1.0; act_dim],
        gamma: 0.98,
        actor: ActorSpec {
            hidden: hidden.to_vec(),
            activation: Activation::Relu,
            kind: ActorKind::Gaussian,
            mean_clip: None,
        },
        critic: CriticSpec {
            n_critics: 2,
            hidden: hidden.to_vec(),
            activation: Activation::Relu,
            layer_norm: false,
        },
        model: Some(ModelSpec {
            hidden: model_hidden.to_vec(),
            activation: Activation::Relu,
            normalization: Normalization::identity(obs_dim, act_dim),
        }),
        q_aggregation: QAggregation::Min,
        value_scale: Some(ValueScale {
            v_pi: 10.0,
            v_rand: -10.0,
        }),
        obs_normalization: None,
        obs_bounds: None,
        default_guard: None,
        features: None,
        provenance: Provenance {
            trainer: "random init (test)".to_string(),
            steps: 0,
            seed: 0,
            date: "1970-01-01T00:00:00Z".to_string(),
        },
    }
}

/// The MLP kernel alone: one Hopper-sized critic (18 inputs, [256, 256] ReLU, 1 output) over
/// `rows` states at a time.
pub struct KernelRow {
    pub rows: usize,
    pub micros_per_call: f64,
    pub gflops: f64,
}

/// Times the critic's forward at each batch size for `per_case` wall time.
pub fn critic_kernel(batch_rows: &[usize], per_case: Duration) -> Vec<KernelRow> {
    let policy = random_policy(hopper_sized_manifest(), 3);
    let critic = &policy.critics[0];
    let mut scratch = critic.scratch();
    batch_rows
        .iter()
        .map(|&rows| {
            let inputs: Vec<f32> = (0..rows * critic.input_dim())
                .map(|i| (i as f32 * 0.37).sin())
                .collect();
            std::hint::black_box(critic.forward_rows(&inputs, &mut scratch));
            let start = Instant::now();
            let mut calls = 0u64;
            while start.elapsed() < per_case {
                std::hint::black_box(
                    critic.forward_rows(std::hint::black_box(&inputs), &mut scratch),
                );
                calls += 1;
            }
            let seconds = start.elapsed().as_secs_f64();
            KernelRow {
                rows,
                micros_per_call: seconds * 1e6 / calls as f64,
                gflops: (critic.flops() * rows as u64 * calls) as f64 / seconds / 1e9,
            }
        })
        .collect()
}
