//! The per-step path (Session::step: Replan and the networks) does not allocate after a session's
//! first step. Counted with a global allocator, in its own test binary, on the test's own thread
//! only (the test harness's thread may allocate meanwhile, e.g. on a loaded machine).

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use prac::plan::{ReplanConfig, ReplanScratch};
use prac::policy::Evaluator;
use prac::serve::{Arrival, Session, SessionSettings};
use prac::testing::hopper_sized_manifest;

struct Counting;

thread_local! {
    // Const-initialised without a destructor: reading it never allocates.
    static COUNTING: Cell<bool> = const { Cell::new(false) };
}
static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

fn counting() -> bool {
    COUNTING.with(Cell::get)
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if counting() {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if counting() {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
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
    for (manifest, epsilon, sampled) in [
        (&plain, 0.0, false),
        (&plain, 0.05, true),
        (&plain, 1e9, false),
        (&normalising, 0.05, false),
    ] {
        let policy = Arc::new(prac::testing::random_policy(manifest.clone(), 3));
        let settings = SessionSettings {
            replan: ReplanConfig {
                epsilon,
                sampled,
                ..ReplanConfig::default()
            },
            seed: 1,
        };
        let mut session = Session::new("s".into(), policy.clone(), settings);
        let mut evaluator = Evaluator::for_sessions(policy.clone(), 1);
        let mut scratch = ReplanScratch::new(15, 3);
        let mut obs: Vec<f32> = (0..15).map(|i| (i as f32 * 0.3).sin()).collect();
        session
            .step(&mut evaluator, &mut scratch, &obs, true, Arrival::next())
            .unwrap();
        COUNTING.with(|c| c.set(true));
        for t in 0..200 {
            obs[t % 15] += 0.01;
            session
                .step(
                    &mut evaluator,
                    &mut scratch,
                    &obs,
                    t % 50 == 0,
                    Arrival::next(),
                )
                .unwrap();
        }
        COUNTING.with(|c| c.set(false));
        assert_eq!(
            ALLOCATIONS.swap(0, Ordering::SeqCst),
            0,
            "eps {epsilon} sampled {sampled} normalising {}",
            manifest.obs_normalization.is_some()
        );
    }
}
