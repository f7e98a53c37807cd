//! `prac bench-replan`: microseconds per Replan for Hopper-sized networks and the GFLOP/s reached.

use std::sync::Arc;
use std::time::{Duration, Instant};

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::plan::{Growth, Networks, Plan, ReplanConfig, ReplanScratch, replan};
use crate::policy::{Evaluator, Policy, hopper_sized_manifest};

/// Counts network evaluations, to turn time into FLOP/s.
struct Counting<N> {
    inner: N,
    acts: u64,
    qs: u64,
    predicts: u64,
}

impl<N: Networks> Networks for Counting<N> {
    fn obs_dim(&self) -> usize {
        self.inner.obs_dim()
    }
    fn act_dim(&self) -> usize {
        self.inner.act_dim()
    }
    fn act(&mut self, obs: &[f32], noise: Option<&[f32]>, action: &mut [f32]) {
        self.acts += 1;
        self.inner.act(obs, noise, action)
    }
    fn q(&mut self, obs: &[f32], action: &[f32]) -> f32 {
        self.qs += 1;
        self.inner.q(obs, action)
    }
    fn q_pair(&mut self, obs: &[f32], a: &[f32], b: &[f32]) -> (f32, f32) {
        self.qs += 2;
        self.inner.q_pair(obs, a, b)
    }
    fn predict_next(&mut self, obs: &[f32], action: &[f32], next_obs: &mut [f32]) {
        self.predicts += 1;
        self.inner.predict_next(obs, action, next_obs)
    }
}

pub struct BenchRow {
    pub plan_length: usize,
    pub replans: u64,
    pub micros_per_replan: f64,
    pub gflops: f64,
}

/// Times Replan at each plan length for `per_length` wall time. The plan is held whole (eps huge,
/// fixed length): every step checks length - 1 old actions and appends one, the costliest case.
pub fn run(lengths: &[usize], per_length: Duration) -> Vec<BenchRow> {
    let policy = Arc::new(Policy::random(hopper_sized_manifest(), 1));
    let (actor_flops, critic_flops, model_flops) = policy.flops();
    let n_critics = policy.critics.len() as u64;
    let (obs_dim, act_dim) = (policy.obs_dim(), policy.act_dim());
    let mut rows = Vec::new();
    for &length in lengths {
        let config = ReplanConfig {
            epsilon: f32::MAX,
            growth: Growth::Fixed(length),
            max_horizon: length,
            sampled: false,
        };
        let mut nets = Counting {
            inner: Evaluator::new(policy.clone()),
            acts: 0,
            qs: 0,
            predicts: 0,
        };
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut scratch = ReplanScratch::new(obs_dim, act_dim);
        let mut plan = Plan::with_capacity(obs_dim, act_dim, length + 1);
        let mut spare = plan.clone();
        let base: Vec<f32> = (0..obs_dim).map(|i| (i as f32 * 0.7).sin()).collect();
        let mut state = base.clone();
        let mut one = |nets: &mut Counting<Evaluator>, t: u64, state: &mut Vec<f32>| {
            let old = if t == 0 {
                plan.tail(plan.len())
            } else {
                plan.tail(1)
            };
            replan(
                nets,
                &config,
                state,
                t,
                old,
                &mut spare,
                &mut scratch,
                &mut rng,
            )
            .expect("finite networks");
            std::mem::swap(&mut plan, &mut spare);
            // A nearby state each step (a random model followed for long would diverge).
            let i = t as usize % state.len();
            state[i] = base[i] + 0.01 * ((t % 7) as f32);
        };
        for t in 0..length as u64 + 10 {
            one(&mut nets, t, &mut state);
        }
        nets.acts = 0;
        nets.qs = 0;
        nets.predicts = 0;
        let start = Instant::now();
        let mut replans = 0u64;
        while start.elapsed() < per_length {
            for _ in 0..64 {
                one(&mut nets, 1000 + replans, &mut state);
                replans += 1;
            }
        }
        let seconds = start.elapsed().as_secs_f64();
        let flops = nets.acts * actor_flops
            + nets.qs * critic_flops * n_critics
            + nets.predicts * model_flops;
        rows.push(BenchRow {
            plan_length: length,
            replans,
            micros_per_replan: seconds * 1e6 / replans as f64,
            gflops: flops as f64 / seconds / 1e9,
        });
    }
    rows
}

pub fn report(rows: &[BenchRow]) -> String {
    let mut out = String::from(
        "Replan, Hopper-sized networks (actor, 2 critics [256, 256]; model 4 x 64; obs 15, act 3)\n\
         whole plan kept (worst case), one thread, f32\n\
         plan_length  replans  us/replan  GFLOP/s\n",
    );
    for r in rows {
        out.push_str(&format!(
            "{:>11}  {:>7}  {:>9.1}  {:>7.2}\n",
            r.plan_length, r.replans, r.micros_per_replan, r.gflops
        ));
    }
    out
}
