//! The per-step path (Session::step: Replan and the networks) does not allocate after a session's
//! first step. Counted with a global allocator, in its own test binary.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use prac::plan::{ReplanConfig, ReplanScratch};
use prac::policy::{Evaluator, Policy, hopper_sized_manifest};
use prac::serve::arrival::Arrival;
use prac::serve::session::{Session, SessionSettings};

struct Counting;

static COUNTING: AtomicBool = AtomicBool::new(false);
static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if COUNTING.load(Ordering::Relaxed) {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if COUNTING.load(Ordering::Relaxed) {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn steps_after_the_first_do_not_allocate() {
    let policy = Arc::new(Policy::random(hopper_sized_manifest(), 3));
    for (epsilon, sampled) in [(0.0, false), (0.05, true), (1e9, false)] {
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
        COUNTING.store(true, Ordering::SeqCst);
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
        COUNTING.store(false, Ordering::SeqCst);
        assert_eq!(
            ALLOCATIONS.swap(0, Ordering::SeqCst),
            0,
            "eps {epsilon} sampled {sampled}"
        );
    }
}
