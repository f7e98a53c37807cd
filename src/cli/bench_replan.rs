//! `prac bench-replan`: microseconds per Replan for Hopper-sized networks and the GFLOP/s reached.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use clap::Args;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use prac::plan::{
    Growth, Networks, NonFinite, Plan, ReplanConfig, ReplanJob, ReplanScratch, replan_batch,
};
use prac::policy::Evaluator;
use prac::testing::hopper_sized_manifest;

#[derive(Args, Debug)]
pub struct BenchReplanArgs {
    /// Seconds measured per case.
    #[arg(long, default_value_t = 1.0)]
    seconds: f64,
    /// Plan lengths to measure.
    #[arg(long, value_delimiter = ',', default_value = "1,8,32")]
    lengths: Vec<usize>,
    /// Sessions replanned together (cross-session batch sizes).
    #[arg(long, value_delimiter = ',', default_value = "1,8,64")]
    batches: Vec<usize>,
    /// Instead: Replan on these bundles (repeatable), one session in-process on its domain's
    /// simulated trajectories: microseconds, FLOPs and network calls per step.
    #[arg(long)]
    bundle: Vec<PathBuf>,
    /// eps coefficient of --bundle's session (eps = coef x (V_pi - V_rand)).
    #[arg(long, default_value_t = 0.005)]
    epsilon_coef: f64,
    /// The dense layers' code path: auto (the widest the CPU has), avx512, avx2 or scalar, to
    /// measure one path on a CPU that has a wider one.
    #[arg(long, value_enum, default_value_t = prac::Kernel::Auto)]
    kernel: prac::Kernel,
}

impl BenchReplanArgs {
    pub fn run(self) -> anyhow::Result<()> {
        prac::use_kernel(self.kernel).map_err(anyhow::Error::msg)?;
        println!("dense-layer kernel: {:?}", prac::kernel());
        let per_case = Duration::from_secs_f64(self.seconds);
        if !self.bundle.is_empty() {
            let rows = self
                .bundle
                .iter()
                .map(|path| bundle_replan(path, self.epsilon_coef, per_case))
                .collect::<anyhow::Result<Vec<_>>>()?;
            print!("{}", bundle_report(&rows, matmul_gflops(per_case)));
            return Ok(());
        }
        let lengths: Vec<usize> = self.lengths.into_iter().filter(|&l| l > 0).collect();
        let batches: Vec<usize> = self.batches.into_iter().filter(|&b| b > 0).collect();
        let rows = lengths_and_batches(&lengths, &batches, per_case);
        let kernel = prac::testing::critic_kernel(&[1, 8, 64, 256, 1024], per_case);
        let matmul = matmul_gflops(per_case);
        print!("{}", report(&rows, &kernel, matmul));
        Ok(())
    }
}

/// Counts network evaluations (rows), to turn time into FLOP/s, and calls.
struct Counting<N> {
    inner: N,
    acts: u64,
    qs: u64,
    predicts: u64,
    calls: u64,
}

impl<N: Networks> Networks for Counting<N> {
    fn obs_dim(&self) -> usize {
        self.inner.obs_dim()
    }
    fn act_dim(&self) -> usize {
        self.inner.act_dim()
    }
    fn act(&mut self, obs: &[f32], noise: &[f32], actions: &mut [f32]) {
        self.calls += 1;
        self.acts += (obs.len() / self.obs_dim()) as u64;
        self.inner.act(obs, noise, actions)
    }
    fn q_pair(
        &mut self,
        obs: &[f32],
        a: &[f32],
        b: &[f32],
        q_a: &mut [f32],
        q_b: &mut [f32],
        largest_gap: Option<&mut [f32]>,
    ) {
        self.calls += 1;
        self.qs += 2 * q_a.len() as u64;
        self.inner.q_pair(obs, a, b, q_a, q_b, largest_gap)
    }
    fn policy_distance(&mut self, obs: &[f32], actions: &[f32], distance: &mut [f32]) {
        self.calls += 1;
        self.acts += (obs.len() / self.obs_dim()) as u64;
        self.inner.policy_distance(obs, actions, distance)
    }
    fn act_and_distance(
        &mut self,
        obs: &[f32],
        noise: &[f32],
        actions: &mut [f32],
        planned: &[f32],
        distance: &mut [f32],
    ) {
        self.calls += 1;
        self.acts += (obs.len() / self.obs_dim()) as u64;
        self.inner
            .act_and_distance(obs, noise, actions, planned, distance)
    }
    fn predict_next(&mut self, obs: &[f32], actions: &[f32], next_obs: &mut [f32]) {
        self.calls += 1;
        self.predicts += (obs.len() / self.obs_dim()) as u64;
        self.inner.predict_next(obs, actions, next_obs)
    }
}

struct BenchRow {
    plan_length: usize,
    batch: usize,
    replans: u64,
    micros_per_replan: f64,
    gflops: f64,
}

/// Times Replan at each plan length and batch size (sessions replanned together) for
/// `per_case` wall time. Plans are held whole (eps huge, fixed length): every step checks
/// length - 1 old actions and appends one, the costliest case. FLOPs are the multiply-adds of
/// every network evaluation, counted as two each.
fn lengths_and_batches(lengths: &[usize], batches: &[usize], per_case: Duration) -> Vec<BenchRow> {
    let policy = Arc::new(prac::testing::random_policy(hopper_sized_manifest(), 1));
    let (actor_flops, critic_flops, model_flops) = policy.flops();
    let n_critics = policy.critic_count() as u64;
    let (obs_dim, act_dim) = (policy.obs_dim(), policy.act_dim());
    let mut rows = Vec::new();
    for &length in lengths {
        for &batch in batches {
            let config = ReplanConfig {
                epsilon: f32::MAX,
                growth: Growth::Fixed(length),
                max_horizon: length,
                sampled: false,
                ..ReplanConfig::default()
            };
            let mut nets = Counting {
                inner: Evaluator::with_capacity(policy.clone(), batch),
                acts: 0,
                qs: 0,
                predicts: 0,
                calls: 0,
            };
            let mut rngs: Vec<ChaCha8Rng> =
                (0..batch as u64).map(ChaCha8Rng::seed_from_u64).collect();
            let mut scratch = ReplanScratch::with_capacity(obs_dim, act_dim, batch);
            let mut plans: Vec<Plan> = (0..batch)
                .map(|_| Plan::with_capacity(obs_dim, act_dim, length + 1))
                .collect();
            let mut spares = plans.clone();
            let base: Vec<Vec<f32>> = (0..batch)
                .map(|b| (0..obs_dim).map(|i| ((i + b) as f32 * 0.7).sin()).collect())
                .collect();
            let mut states = base.clone();
            let mut results = vec![Err(NonFinite { what: "", index: 0 }); batch];
            let mut step = |nets: &mut Counting<Evaluator>, t: u64| {
                let mut jobs: Vec<ReplanJob<'_, ChaCha8Rng>> = plans
                    .iter()
                    .zip(spares.iter_mut())
                    .zip(rngs.iter_mut())
                    .zip(&states)
                    .map(|(((plan, new), rng), state)| ReplanJob {
                        config,
                        state,
                        step: t,
                        old: if t == 0 {
                            plan.tail(plan.len())
                        } else {
                            plan.tail(1)
                        },
                        new,
                        rng,
                    })
                    .collect();
                replan_batch(nets, &mut jobs, &mut scratch, &mut results);
                drop(jobs);
                assert!(results.iter().all(Result::is_ok), "finite networks");
                std::mem::swap(&mut plans, &mut spares);
                // A nearby state each step (a random model followed for long would diverge).
                for (state, base) in states.iter_mut().zip(&base) {
                    let i = t as usize % state.len();
                    state[i] = base[i] + 0.01 * ((t % 7) as f32);
                }
            };
            for t in 0..length as u64 + 10 {
                step(&mut nets, t);
            }
            nets.acts = 0;
            nets.qs = 0;
            nets.predicts = 0;
            let start = Instant::now();
            let mut steps = 0u64;
            while start.elapsed() < per_case {
                step(&mut nets, 1000 + steps);
                steps += 1;
            }
            let seconds = start.elapsed().as_secs_f64();
            let flops = nets.acts * actor_flops
                + nets.qs * critic_flops * n_critics
                + nets.predicts * model_flops;
            let replans = steps * batch as u64;
            rows.push(BenchRow {
                plan_length: length,
                batch,
                replans,
                micros_per_replan: seconds * 1e6 / replans as f64,
                gflops: flops as f64 / seconds / 1e9,
            });
        }
    }
    rows
}

/// The machine's single-thread f32 matrix-multiply rate: 512 x 512 x 512 with matrixmultiply
/// (via nalgebra), the reference for Replan's GFLOP/s.
fn matmul_gflops(per_case: Duration) -> f64 {
    let n = 512;
    let a = nalgebra::DMatrix::<f32>::from_fn(n, n, |i, j| ((i * 7 + j) % 13) as f32 * 0.1);
    let b = a.transpose();
    let mut c = nalgebra::DMatrix::<f32>::zeros(n, n);
    c.gemm(1.0, &a, &b, 0.0);
    let start = Instant::now();
    let mut runs = 0u64;
    while start.elapsed() < per_case {
        c.gemm(1.0, &a, &b, 0.0);
        runs += 1;
    }
    (2 * n * n * n) as f64 * runs as f64 / start.elapsed().as_secs_f64() / 1e9
}

/// Replan on a shipped bundle, on its own domain's trajectories: one session in-process, the
/// simulated robot driven by the served action, as `prac serve` replans a lone session.
struct BundleReplan {
    bundle: String,
    epsilon_coef: f64,
    steps: u64,
    micros_per_step: f64,
    old_actions_tested_per_step: f64,
    plan_length: f64,
    network_calls_per_step: f64,
    mflop_per_step: f64,
    gflops: f64,
}

/// Plays the bundle's domain for `per_case` (episodes restart from the next seed), timing only
/// Replan.
fn bundle_replan(
    path: &std::path::Path,
    epsilon_coef: f64,
    per_case: Duration,
) -> anyhow::Result<BundleReplan> {
    use prac::proto::session_options::Tolerance;
    use prac::testing::serve::SessionSettings;
    let policy = Arc::new(prac::bundle::load(path)?);
    let domain = policy.manifest.domain.clone();
    let mut env = prac::domains::make(&domain).ok_or_else(|| {
        anyhow::anyhow!("the bundle is for domain {domain:?}, which this build does not have")
    })?;
    let options = prac::proto::SessionOptions {
        tolerance: Some(Tolerance::EpsilonCoef(epsilon_coef)),
        ..Default::default()
    };
    let config = SessionSettings::resolve(Some(&options), &policy, prac::plan::MAX_CHUNK)
        .map_err(|e| anyhow::anyhow!(e))?
        .replan;
    let (actor_flops, critic_flops, model_flops) = policy.flops();
    let n_critics = policy.critic_count() as u64;
    let spec = env.spec().clone();
    let (od, ad) = (spec.obs_dim, spec.act_dim);
    let mut nets = Counting {
        inner: Evaluator::with_capacity(policy.clone(), 1),
        acts: 0,
        qs: 0,
        predicts: 0,
        calls: 0,
    };
    let mut planner = prac::plan::Planner::new(config, od, ad, ChaCha8Rng::seed_from_u64(1));
    let (mut obs, mut scaled) = (vec![0.0; od], vec![0.0; ad]);
    let (mut seed, mut t) = (0u64, 0u64);
    env.reset(seed, &mut obs)?;
    let (mut replanning, mut steps, mut tested, mut plan_entries) = (Duration::ZERO, 0u64, 0, 0);
    let wall = Instant::now();
    while wall.elapsed() < per_case || steps < 100 {
        let start = Instant::now();
        let outcome = planner.replan(&mut nets, &obs, t)?;
        replanning += start.elapsed();
        steps += 1;
        tested += outcome.kept + usize::from(outcome.broke_at.is_some());
        plan_entries += planner.plan().len();
        prac::policy::unscale_action(
            &spec.action_low,
            &spec.action_high,
            planner.plan().action(0),
            &mut scaled,
        );
        let transition = env.step(&scaled, &mut obs)?;
        t += 1;
        if transition.terminated || transition.truncated {
            seed += 1;
            env.reset(seed, &mut obs)?;
            t = 0;
        }
    }
    let flops =
        nets.acts * actor_flops + nets.qs * critic_flops * n_critics + nets.predicts * model_flops;
    let per_step = |v: f64| v / steps as f64;
    Ok(BundleReplan {
        bundle: policy.manifest.name.clone(),
        epsilon_coef,
        steps,
        micros_per_step: per_step(replanning.as_secs_f64() * 1e6),
        old_actions_tested_per_step: per_step(tested as f64),
        plan_length: per_step(plan_entries as f64),
        network_calls_per_step: per_step(nets.calls as f64),
        mflop_per_step: per_step(flops as f64 / 1e6),
        gflops: flops as f64 / replanning.as_secs_f64() / 1e9,
    })
}

fn bundle_report(rows: &[BundleReplan], matmul: f64) -> String {
    let mut out = format!(
        "Replan on shipped bundles, one session in-process on its domain's trajectories\n\
         machine matmul (512^3 sgemm, matrixmultiply, 1 thread): {matmul:.1} GFLOP/s\n\
         eps coefficient {coef}; tested: old actions tested per step; calls: network calls per step;\n\
         at sgemm: microseconds per step if every FLOP ran at the sgemm rate\n\
         bundle      steps  us/step  tested  plan  calls  MFLOP/step  GFLOP/s  of sgemm  at sgemm\n",
        coef = rows.first().map_or(0.0, |r| r.epsilon_coef)
    );
    for r in rows {
        out.push_str(&format!(
            "{:<10}  {:>5}  {:>7.1}  {:>6.2}  {:>4.1}  {:>5.1}  {:>10.2}  {:>7.1}  {:>7.0}%  {:>8.1}\n",
            r.bundle,
            r.steps,
            r.micros_per_step,
            r.old_actions_tested_per_step,
            r.plan_length,
            r.network_calls_per_step,
            r.mflop_per_step,
            r.gflops,
            100.0 * r.gflops / matmul,
            r.mflop_per_step * 1e3 / matmul,
        ));
    }
    out
}

fn report(rows: &[BenchRow], kernel: &[prac::testing::KernelRow], matmul: f64) -> String {
    let mut out = format!(
        "MLP kernel: one critic (18 inputs, [256, 256] ReLU, 1 output), rows per call, one thread\n\
         machine matmul (512^3 sgemm, matrixmultiply, 1 thread): {matmul:.1} GFLOP/s\n\
         rows  us/call  GFLOP/s  of sgemm\n"
    );
    for k in kernel {
        out.push_str(&format!(
            "{:>4}  {:>7.2}  {:>7.2}  {:>7.0}%\n",
            k.rows,
            k.micros_per_call,
            k.gflops,
            100.0 * k.gflops / matmul
        ));
    }
    out.push('\n');
    out.push_str(
        "Replan, Hopper-sized networks (actor, 2 critics [256, 256]; model 4 x 64; obs 15, act 3)\n\
         whole plan kept (worst case), one thread, f32; GFLOP/s\n\
         plan_length  batch  replans  us/replan  GFLOP/s\n",
    );
    for r in rows {
        out.push_str(&format!(
            "{:>11}  {:>5}  {:>7}  {:>9.1}  {:>7.2}\n",
            r.plan_length, r.batch, r.replans, r.micros_per_replan, r.gflops
        ));
    }
    out
}
