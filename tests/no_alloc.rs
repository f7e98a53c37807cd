//! The per-step paths do not allocate after the first step: a session's step (Replan and the
//! networks) and every domain's `Env::step` outside its calls into the physics engine (rapier
//! 0.36 allocates inside its step and its bookkeeping of modified bodies; those allocations are
//! counted apart and printed). Counted with a global
//! allocator, in its own test binary, on the test's own thread only (the test harness's thread
//! may allocate meanwhile, e.g. on a loaded machine).

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::Arc;

use prac::plan::{Guard, ReplanConfig, ReplanScratch};
use prac::policy::Evaluator;
use prac::testing::hopper_sized_manifest;
use prac::testing::serve::{Arrival, Session, SessionSettings, StepInput};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

struct Counting;

thread_local! {
    // Const-initialised without destructors: using them never allocates. Per thread, as the
    // tests run side by side.
    static COUNTING: Cell<bool> = const { Cell::new(false) };
    static ALLOCATIONS: Cell<usize> = const { Cell::new(0) };
    static ENGINE_ALLOCATIONS: Cell<usize> = const { Cell::new(0) };
}

fn counting() -> bool {
    COUNTING.with(Cell::get)
}

fn count() {
    if counting() {
        let counter = if prac::testing::in_physics_engine() {
            &ENGINE_ALLOCATIONS
        } else {
            &ALLOCATIONS
        };
        counter.with(|n| n.set(n.get() + 1));
    }
}

/// This thread's count since the last call.
fn take(counter: &'static std::thread::LocalKey<Cell<usize>>) -> usize {
    counter.with(|n| n.replace(0))
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count();
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn steps_after_the_first_do_not_allocate() {
    let plain = hopper_sized_manifest();
    // A bundle exported from SB3 with VecNormalize normalises observations on the per-step path.
    let mut normalising = hopper_sized_manifest();
    normalising.format_version = prac::manifest::FORMAT_VERSION_ACTOR_KINDS;
    normalising.obs_normalization = Some(prac::manifest::ObsNormalization {
        mean: vec![0.1; 15],
        var: vec![2.0; 15],
        clip_obs: 10.0,
        epsilon: 1e-8,
    });
    let guarded = Guard {
        every_critic: true,
        support_limit: 3.0,
        ..Default::default()
    };
    for (manifest, epsilon, sampled, guard) in [
        (&plain, 0.0, false, Guard::default()),
        (&plain, 0.05, true, Guard::default()),
        (&plain, 1e9, false, Guard::default()),
        (&normalising, 0.05, false, Guard::default()),
        (&plain, 0.05, false, guarded),
        (&plain, 1e9, true, guarded),
    ] {
        let policy = Arc::new(prac::testing::random_policy(manifest.clone(), 3));
        let settings = SessionSettings {
            replan: ReplanConfig {
                epsilon,
                sampled,
                guard,
                ..ReplanConfig::default()
            },
            seed: 1,
        };
        let mut session = Session::new("s".into(), policy.clone(), settings);
        let mut evaluator = Evaluator::for_sessions(policy.clone(), 1);
        let mut scratch = ReplanScratch::new(15, 3);
        let mut obs: Vec<f32> = (0..15).map(|i| (i as f32 * 0.3).sin()).collect();
        let first = StepInput {
            observation: &obs,
            new_episode: true,
            arrival: Arrival::next(),
        };
        session
            .apply_step(&mut evaluator, &mut scratch, first)
            .unwrap();
        COUNTING.with(|c| c.set(true));
        for t in 0..200 {
            obs[t % 15] += 0.01;
            let input = StepInput {
                observation: &obs,
                new_episode: t % 50 == 0,
                arrival: Arrival::next(),
            };
            session
                .apply_step(&mut evaluator, &mut scratch, input)
                .unwrap();
        }
        COUNTING.with(|c| c.set(false));
        assert_eq!(
            take(&ALLOCATIONS),
            0,
            "eps {epsilon} sampled {sampled} normalising {} guard {guard:?}",
            manifest.obs_normalization.is_some()
        );
    }
}

#[test]
fn domain_steps_allocate_nothing_outside_the_physics_engine() {
    const STEPS: usize = 300;
    for &name in prac::domains::DOMAINS {
        let mut env = prac::domains::make(name).unwrap();
        let spec = env.spec().clone();
        let mut obs = vec![0.0; spec.obs_dim];
        let mut action = vec![0.0; spec.act_dim];
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut episode = 0;
        env.reset(episode, &mut obs).unwrap();
        // The first step may size buffers; every later one must reuse them.
        env.step(&action, &mut obs).unwrap();
        let mut counted = 0;
        while counted < STEPS {
            for (a, (lo, hi)) in action
                .iter_mut()
                .zip(spec.action_low.iter().zip(&spec.action_high))
            {
                *a = rng.random_range(*lo..=*hi);
            }
            COUNTING.with(|c| c.set(true));
            let transition = env.step(&action, &mut obs);
            COUNTING.with(|c| c.set(false));
            counted += 1;
            let transition = transition.unwrap();
            if transition.terminated || transition.truncated {
                episode += 1;
                env.reset(episode, &mut obs).unwrap();
                env.step(&action, &mut obs).unwrap();
            }
        }
        let engine = take(&ENGINE_ALLOCATIONS);
        eprintln!(
            "{name}: {:.1} allocations per step inside rapier (its step, its bookkeeping)",
            engine as f64 / STEPS as f64
        );
        assert_eq!(
            take(&ALLOCATIONS),
            0,
            "{name}: Env::step allocated outside its calls into the physics engine over {STEPS} steps"
        );
    }
}
