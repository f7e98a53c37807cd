//! Fuzz targets, shared by cargo-fuzz (`fuzz/`, nightly, libFuzzer) and by the normal tests (a
//! seeded mutation run on stable): each takes arbitrary bytes and must neither panic nor hang.
//! An `Err` is a correct answer; a panic is a bug.

use std::path::Path;
use std::sync::Arc;

use arbitrary::{Arbitrary, Unstructured};

use crate::bundle;
use crate::plan::ReplanScratch;
use crate::policy::{Evaluator, Policy};
use crate::proto;
use crate::serve::session::{Session, SessionSettings, StepInput};
use crate::testing::toy_policy;

/// Seed inputs: a valid bundle (the loader's mutations start from it).
pub fn valid_bundle() -> Vec<u8> {
    bundle::to_bytes(&toy_policy("toy", 1)).expect("the toy policy serialises")
}

/// The bundle loader on arbitrary bytes, from memory and as a file reads it (header first):
/// both must agree. Returns whether the bytes loaded.
pub fn bundle_bytes(data: &[u8]) -> bool {
    let path = Path::new("fuzz.safetensors");
    let from_memory = bundle::from_bytes(data, path);
    let from_file = bundle::from_reader(std::io::Cursor::new(data), data.len() as u64, path);
    assert_eq!(
        from_memory.is_ok(),
        from_file.is_ok(),
        "memory: {:?}, file: {:?}",
        from_memory.as_ref().err(),
        from_file.as_ref().err()
    );
    match from_memory {
        Ok(policy) => {
            // What loads must also plan: one replan from a zero state.
            plan_once(Arc::new(policy));
            true
        }
        Err(_) => false,
    }
}

/// Manifests an attacker wrote: each must be refused, not allocated from or served.
pub fn attack_manifests() -> Vec<Vec<u8>> {
    let base = toy_policy("toy", 1).manifest;
    let attacks: [fn(&mut bundle::Manifest); 5] = [
        |m| m.critic.n_critics = 1_000_000_000,
        |m| m.critic.n_critics = 1 << 62,
        |m| {
            m.action_low = vec![-3e38; 2];
            m.action_high = vec![3e38; 2];
        },
        |m| {
            m.value_scale = Some(bundle::ValueScale {
                v_pi: 1.7e308,
                v_rand: -1.7e308,
            })
        },
        |m| m.actor.hidden = vec![1 << 40],
    ];
    attacks
        .iter()
        .map(|attack| {
            let mut manifest = base.clone();
            attack(&mut manifest);
            serde_json::to_vec(&manifest).expect("a manifest serialises")
        })
        .collect()
}

/// The loader's manifest checks: the toy policy's tensors under an arbitrary manifest text.
/// Returns whether the bundle loaded.
pub fn bundle_manifest(data: &[u8]) -> bool {
    let text = String::from_utf8_lossy(data);
    let bytes = bundle::to_bytes_with_manifest(&toy_policy("toy", 1), &text)
        .expect("serialising the toy tensors");
    bundle_bytes(&bytes)
}

fn plan_once(policy: Arc<Policy>) {
    let Ok(settings) = SessionSettings::resolve(None, &policy, 64) else {
        return;
    };
    let (od, ad) = (policy.obs_dim(), policy.act_dim());
    if od > 4096 || ad > 4096 {
        return;
    }
    let mut session = Session::new("fuzz".into(), policy.clone(), settings);
    let mut evaluator = Evaluator::for_sessions(policy, 1);
    let mut scratch = ReplanScratch::new(od, ad);
    let zeros = vec![0.0; od];
    let input = StepInput {
        observation: &zeros,
        new_episode: true,
        arrival: crate::serve::arrival::Arrival::next(),
    };
    if let Ok(report) = session.apply_step(&mut evaluator, &mut scratch, input) {
        let response = session.response(&report);
        assert!(response.action.iter().all(|a| a.is_finite()));
    }
}

#[derive(Arbitrary, Debug)]
enum Tolerance {
    Epsilon(f64),
    Coef(f64),
}

#[derive(Arbitrary, Debug)]
enum Growth {
    Grow(u32),
    Fixed(u32),
}

#[derive(Arbitrary, Debug)]
struct Options {
    tolerance: Option<Tolerance>,
    growth: Option<Growth>,
    max_horizon: u32,
    sampled: bool,
    seed: u64,
    guard: Option<(bool, f64, f64)>,
}

#[derive(Arbitrary, Debug)]
struct PlannedAction {
    action: Vec<f32>,
    decided_at: u64,
}

#[derive(Arbitrary, Debug)]
struct Resume {
    episode: u64,
    start_step: u64,
    actions: Vec<PlannedAction>,
}

#[derive(Arbitrary, Debug)]
struct Step {
    observation: Vec<f32>,
    new_episode: bool,
}

#[derive(Arbitrary, Debug)]
struct Requests {
    options: Option<Options>,
    resume: Option<Resume>,
    steps: Vec<Step>,
}

/// Request handling against a loaded policy: arbitrary session options, an arbitrary resumed
/// plan and arbitrary observations, through the server's own session code (what OpenSession and
/// Step run, without the transport). Returns whether some step was applied.
pub fn requests(data: &[u8]) -> bool {
    let Ok(input) = Requests::arbitrary(&mut Unstructured::new(data)) else {
        return false;
    };
    let policy = Arc::new(toy_policy("toy", 1));
    let options = input.options.map(|o| proto::SessionOptions {
        tolerance: o.tolerance.map(|t| match t {
            Tolerance::Epsilon(e) => proto::session_options::Tolerance::Epsilon(e),
            Tolerance::Coef(c) => proto::session_options::Tolerance::EpsilonCoef(c),
        }),
        growth: o.growth.map(|g| match g {
            Growth::Grow(k) => proto::session_options::Growth::Grow(k),
            Growth::Fixed(n) => proto::session_options::Growth::Fixed(n),
        }),
        max_horizon: o.max_horizon,
        sampled: o.sampled,
        seed: o.seed,
        guard: o.guard.map(
            |(every_critic, support_limit, max_epsilon_coef)| proto::PlanGuard {
                every_critic,
                support_limit,
                max_epsilon_coef,
            },
        ),
    });
    let Ok(settings) = SessionSettings::resolve(options.as_ref(), &policy, 256) else {
        return false;
    };
    let mut session = Session::new("fuzz".into(), policy.clone(), settings);
    if let Some(resume) = input.resume {
        let plan = proto::Plan {
            session_id: String::new(),
            episode: resume.episode,
            start_step: resume.start_step,
            actions: resume
                .actions
                .into_iter()
                .map(|a| proto::PlannedAction {
                    action: a.action,
                    predicted_observation: Vec::new(),
                    decided_at: a.decided_at,
                })
                .collect(),
        };
        let _ = session.resume(&plan);
    }
    let mut evaluator = Evaluator::for_sessions(policy, 1);
    let mut scratch = ReplanScratch::new(3, 2);
    let mut applied = false;
    for step in input.steps.iter().take(64) {
        let input = StepInput {
            observation: &step.observation,
            new_episode: step.new_episode,
            arrival: crate::serve::arrival::Arrival::next(),
        };
        if let Ok(report) = session.apply_step(&mut evaluator, &mut scratch, input) {
            applied = true;
            let response = session.response(&report);
            assert!(!response.forecast.is_empty() && response.forecast.len() <= 257);
            assert!(response.action.iter().all(|a| a.is_finite()));
            // Counters never wrap, whatever plan was resumed.
            let max = crate::serve::session::MAX_COUNTER;
            assert!(response.step <= max + 64 && response.episode <= max + 64);
            assert!(response.f_t >= 1 && response.f_t <= response.step + 1);
        }
        let _ = session.plan_proto();
    }
    applied
}

/// How a target took the mutated inputs: accepted (loaded, or served a step) or refused.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Outcomes {
    pub accepted: usize,
    pub refused: usize,
}

/// A seeded stand-in for libFuzzer on stable: the seeds, then `runs` inputs made by flipping,
/// inserting, deleting and splicing bytes of the seeds, fed to `target`. Returns how the target
/// took the mutated inputs.
pub fn mutate_and_run(
    seeds: &[Vec<u8>],
    runs: usize,
    seed: u64,
    target: fn(&[u8]) -> bool,
) -> Outcomes {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    for seed in seeds {
        target(seed);
    }
    let mut outcomes = Outcomes::default();
    for _ in 0..runs {
        let mut data = seeds[rng.random_range(0..seeds.len())].clone();
        for _ in 0..rng.random_range(1..8) {
            let len = data.len();
            match rng.random_range(0..5) {
                0 if len > 0 => {
                    let i = rng.random_range(0..len);
                    data[i] ^= 1 << rng.random_range(0..8);
                }
                1 if len > 0 => {
                    let i = rng.random_range(0..len);
                    data[i] = rng.random();
                }
                2 => {
                    let i = rng.random_range(0..=len);
                    data.insert(i, rng.random());
                }
                3 if len > 0 => {
                    data.truncate(rng.random_range(0..len));
                }
                _ => {
                    let other = &seeds[rng.random_range(0..seeds.len())];
                    if !other.is_empty() {
                        let from = rng.random_range(0..other.len());
                        let to = rng.random_range(from..=other.len());
                        let at = rng.random_range(0..=len);
                        data.splice(at..at, other[from..to].iter().copied());
                    }
                }
            }
        }
        if target(&data) {
            outcomes.accepted += 1;
        } else {
            outcomes.refused += 1;
        }
    }
    outcomes
}

#[cfg(test)]
mod tests {
    use super::*;

    fn manifest_seed() -> Vec<u8> {
        serde_json::to_vec(&toy_policy("toy", 1).manifest).unwrap()
    }

    /// Inputs that reach a step: random bytes rarely decode to 3 finite observation values, so
    /// the seeds are the first 8 of a seeded stream of 256-byte strings that do (about 1 in 30).
    fn request_seeds() -> Vec<Vec<u8>> {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let seeds: Vec<Vec<u8>> = (0..10_000)
            .map(|_| {
                let mut bytes = vec![0u8; 256];
                rng.fill(&mut bytes[..]);
                bytes
            })
            .filter(|bytes| requests(bytes))
            .take(8)
            .collect();
        assert_eq!(seeds.len(), 8, "no request input reaches a step");
        seeds
    }

    /// cargo-fuzz starts from fuzz/corpus/*; those seeds must stay valid as the format evolves
    /// (`PRAC_WRITE_FUZZ_SEEDS=1 cargo test --lib fuzz` rewrites them).
    #[test]
    fn the_committed_fuzz_seeds_are_valid() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus");
        let bundle_seed = root.join("bundle_bytes/toy.safetensors");
        let manifest_seed_file = root.join("bundle_manifest/toy.json");
        if std::env::var_os("PRAC_WRITE_FUZZ_SEEDS").is_some() {
            for (file, bytes) in [
                (&bundle_seed, valid_bundle()),
                (&manifest_seed_file, manifest_seed()),
            ] {
                std::fs::create_dir_all(file.parent().unwrap()).unwrap();
                std::fs::write(file, bytes).unwrap();
            }
            for (k, manifest) in attack_manifests().into_iter().enumerate() {
                let file = root.join(format!("bundle_manifest/attack-{k}.json"));
                std::fs::write(file, manifest).unwrap();
            }
            for (k, seed) in request_seeds().into_iter().enumerate() {
                std::fs::write(root.join(format!("requests/step-{k}")), seed).unwrap();
            }
        }
        for k in 0..8 {
            let seed = std::fs::read(root.join(format!("requests/step-{k}"))).unwrap();
            assert!(
                requests(&seed),
                "fuzz/corpus/requests/step-{k} reaches no step"
            );
        }
        let bytes = std::fs::read(&bundle_seed).unwrap();
        bundle::from_bytes(&bytes, &bundle_seed).unwrap();
        let manifest = std::fs::read_to_string(&manifest_seed_file).unwrap();
        let bytes = bundle::to_bytes_with_manifest(&toy_policy("toy", 1), &manifest).unwrap();
        bundle::from_bytes(&bytes, &manifest_seed_file).unwrap();
    }

    #[test]
    fn the_bundle_loader_survives_mutated_bundles() {
        let seeds = vec![valid_bundle(), Vec::new(), b"{}".to_vec()];
        let outcomes = mutate_and_run(&seeds, 3000, 1, bundle_bytes);
        // Both ways reached: mutations that still load (and plan), and ones refused.
        assert!(
            outcomes.accepted > 0 && outcomes.refused > 0,
            "{outcomes:?}"
        );
    }

    #[test]
    fn the_bundle_loader_survives_mutated_manifests() {
        let outcomes = mutate_and_run(&[manifest_seed()], 3000, 2, bundle_manifest);
        assert!(
            outcomes.accepted > 0 && outcomes.refused > 0,
            "{outcomes:?}"
        );
    }

    #[test]
    fn attack_manifests_are_refused_and_their_mutations_survived() {
        let attacks = attack_manifests();
        // The committed seeds cargo-fuzz starts from are these attacks.
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus/bundle_manifest");
        for (k, manifest) in attacks.iter().enumerate() {
            let committed = std::fs::read(root.join(format!("attack-{k}.json"))).unwrap();
            assert_eq!(
                &committed, manifest,
                "fuzz/corpus/bundle_manifest/attack-{k}.json"
            );
        }
        for manifest in &attacks {
            let text = String::from_utf8_lossy(manifest);
            let bytes = bundle::to_bytes_with_manifest(&toy_policy("toy", 1), &text).unwrap();
            assert!(
                bundle::from_bytes(&bytes, Path::new("attack")).is_err(),
                "{text}"
            );
        }
        let outcomes = mutate_and_run(&attacks, 2000, 4, bundle_manifest);
        assert!(outcomes.refused > 0, "{outcomes:?}");
    }

    #[test]
    fn request_handling_survives_arbitrary_options_plans_and_observations() {
        let seeds = request_seeds();
        let outcomes = mutate_and_run(&seeds, 3000, 3, requests);
        assert!(
            outcomes.accepted > 0 && outcomes.refused > 0,
            "{outcomes:?}"
        );
    }
}
