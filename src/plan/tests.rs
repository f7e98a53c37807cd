//! Replan against networks whose answers are known in closed form: a linear policy, the critic
//! Q(s, a) = -|a - pi(s)|^2 (so pi is exactly greedy), and a linear model that is also the
//! environment (an exact model).

use super::*;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

const OBS: usize = 2;
const ACT: usize = 1;

struct ClosedForm {
    /// Added to the model's prediction, to make it inexact.
    model_bias: f32,
    /// Makes the model return NaN.
    broken_model: bool,
    /// The model returns NaN from states whose first value exceeds this (a failure part-way).
    nan_above: f32,
    /// A second critic, -(a - pi(s) - critic_shift)^2, aggregated with the first by min; 0: the
    /// two critics agree.
    critic_shift: f32,
}

impl ClosedForm {
    fn exact() -> Self {
        ClosedForm {
            critic_shift: 0.0,
            model_bias: 0.0,
            broken_model: false,
            nan_above: f32::INFINITY,
        }
    }
    fn mean_action(obs: &[f32]) -> f32 {
        (0.8 * obs[0] - 0.5 * obs[1]).tanh()
    }
    /// The two critics' values of action `a` at `obs`.
    fn critics(&self, obs: &[f32], a: f32) -> [f32; 2] {
        let mean = Self::mean_action(obs);
        let shifted = mean + self.critic_shift;
        [-(a - mean) * (a - mean), -(a - shifted) * (a - shifted)]
    }
}

/// The true environment, which the exact model reproduces bit for bit.
fn env_step(obs: &[f32], action: &[f32]) -> [f32; OBS] {
    [
        0.9 * obs[0] + 0.1 * obs[1],
        -0.2 * obs[0] + 0.95 * obs[1] + 0.3 * action[0],
    ]
}

impl Networks for ClosedForm {
    fn obs_dim(&self) -> usize {
        OBS
    }
    fn act_dim(&self) -> usize {
        ACT
    }
    fn act(&mut self, obs: &[f32], noise: &[f32], actions: &mut [f32]) {
        for (k, action) in actions.iter_mut().enumerate() {
            let o = &obs[k * OBS..(k + 1) * OBS];
            *action = ((0.8 * o[0] - 0.5 * o[1]) + 0.3 * noise[k]).tanh();
        }
    }
    fn q_pair(
        &mut self,
        obs: &[f32],
        a: &[f32],
        b: &[f32],
        q_a: &mut [f32],
        q_b: &mut [f32],
        mut largest_gap: Option<&mut [f32]>,
    ) {
        for k in 0..q_a.len() {
            let [a1, a2] = self.critics(&obs[k * OBS..(k + 1) * OBS], a[k]);
            let [b1, b2] = self.critics(&obs[k * OBS..(k + 1) * OBS], b[k]);
            q_a[k] = a1.min(a2);
            q_b[k] = b1.min(b2);
            if let Some(gap) = largest_gap.as_deref_mut() {
                gap[k] = (a1 - b1).max(a2 - b2);
            }
        }
    }
    fn policy_distance(&mut self, obs: &[f32], actions: &[f32], distance: &mut [f32]) {
        for (k, d) in distance.iter_mut().enumerate() {
            let o = &obs[k * OBS..(k + 1) * OBS];
            *d = support_distance(actions[k], 0.8 * o[0] - 0.5 * o[1], 0.3);
        }
    }
    fn predict_next(&mut self, obs: &[f32], actions: &[f32], next_obs: &mut [f32]) {
        for k in 0..actions.len() {
            let n = env_step(&obs[k * OBS..(k + 1) * OBS], &actions[k..k + 1]);
            next_obs[k * OBS] = if self.broken_model {
                f32::NAN
            } else {
                n[0] + self.model_bias
            };
            if obs[k * OBS] > self.nan_above {
                next_obs[k * OBS] = f32::NAN;
            }
            next_obs[k * OBS + 1] = n[1] + self.model_bias;
        }
    }
}

struct Episode {
    nets: ClosedForm,
    config: ReplanConfig,
    plan: Plan,
    spare: Plan,
    scratch: ReplanScratch,
    rng: ChaCha8Rng,
    obs: [f32; OBS],
    t: u64,
}

struct StepRecord {
    outcome: ReplanOutcome,
    plan: Plan,
    executed: f32,
    f_t: u64,
    obs: [f32; OBS],
}

impl Episode {
    fn new(nets: ClosedForm, config: ReplanConfig, seed: u64) -> Self {
        let cap = config.max_horizon + 4;
        Episode {
            nets,
            config,
            plan: Plan::with_capacity(OBS, ACT, cap),
            spare: Plan::with_capacity(OBS, ACT, cap),
            scratch: ReplanScratch::new(OBS, ACT),
            rng: ChaCha8Rng::seed_from_u64(seed),
            obs: [0.7, -0.4],
            t: 0,
        }
    }

    /// Algorithm 1's loop: replan on the observed state (the old plan minus the action already
    /// executed), execute the first action, observe the true next state.
    fn step(&mut self) -> StepRecord {
        let old = if self.t == 0 {
            PlanView::empty()
        } else {
            self.plan.tail(1)
        };
        let outcome = replan(
            &mut self.nets,
            ReplanJob {
                config: self.config,
                state: &self.obs,
                step: self.t,
                old,
                new: &mut self.spare,
                rng: &mut self.rng,
            },
            &mut self.scratch,
        )
        .unwrap();
        std::mem::swap(&mut self.plan, &mut self.spare);
        let executed = self.plan.action(0)[0];
        let f_t = self.t + 1 - self.plan.decided_at(0);
        let obs = self.obs;
        self.obs = env_step(&self.obs, &[executed]);
        self.t += 1;
        StepRecord {
            outcome,
            plan: self.plan.clone(),
            executed,
            f_t,
            obs,
        }
    }
}

fn huge_eps(growth: Growth, max_horizon: usize) -> ReplanConfig {
    ReplanConfig {
        epsilon: 1e9,
        growth,
        max_horizon,
        sampled: false,
        guard: Guard::default(),
    }
}

#[test]
fn eps_zero_with_exact_model_keeps_plans_equal_to_pi() {
    let mut ep = Episode::new(ClosedForm::exact(), ReplanConfig::default(), 0);
    for t in 0..100 {
        let rec = ep.step();
        // The executed action is exactly the policy's action at the true state...
        assert_eq!(rec.executed, ClosedForm::mean_action(&rec.obs), "step {t}");
        // ...and every planned action is pi at the model's (exact) imagined state.
        let mut s = rec.obs;
        for j in 0..rec.plan.len() {
            assert_eq!(rec.plan.action(j)[0], ClosedForm::mean_action(&s));
            s = env_step(&s, rec.plan.action(j));
            assert_eq!(rec.plan.next_obs(j), &s);
        }
        // Nothing ever breaks, so the plan is the whole old plan plus k new actions.
        assert_eq!(rec.outcome.broke_at, None);
        let expected_len = (2 + t).min(DEFAULT_MAX_HORIZON);
        assert_eq!(rec.plan.len(), expected_len, "step {t}");
    }
}

#[test]
fn huge_eps_never_breaks_and_grows_by_k_minus_1_to_the_cap() {
    for k in [1usize, 2, 3, 5] {
        let cap = 10;
        let mut ep = Episode::new(
            ClosedForm {
                critic_shift: 0.0,
                model_bias: 0.5,
                broken_model: false,
                nan_above: f32::INFINITY,
            },
            huge_eps(Growth::Grow(k), cap),
            1,
        );
        for t in 0..30usize {
            let rec = ep.step();
            assert_eq!(rec.outcome.broke_at, None);
            let expected = (k + t * (k - 1)).min(cap);
            assert_eq!(rec.plan.len(), expected, "k {k} step {t}");
            let kept_expected = if t == 0 {
                0
            } else {
                (k + (t - 1) * (k - 1)).min(cap) - 1
            };
            assert_eq!(rec.outcome.kept, kept_expected, "k {k} step {t}");
        }
    }
}

#[test]
fn fixed_mode_refills_to_n() {
    let n = 6;
    let mut ep = Episode::new(
        ClosedForm {
            critic_shift: 0.0,
            model_bias: 0.3,
            broken_model: false,
            nan_above: f32::INFINITY,
        },
        huge_eps(Growth::Fixed(n), 32),
        2,
    );
    for t in 0..20 {
        let rec = ep.step();
        assert_eq!(rec.plan.len(), n);
        assert_eq!(rec.outcome.kept, if t == 0 { 0 } else { n - 1 });
        assert_eq!(rec.outcome.appended, if t == 0 { n } else { 1 });
    }
    // Fixed n is still capped by the max horizon.
    let mut capped = Episode::new(ClosedForm::exact(), huge_eps(Growth::Fixed(50), 8), 2);
    assert_eq!(capped.step().plan.len(), 8);
}

#[test]
fn a_planted_bad_action_breaks_exactly_at_its_index() {
    let mut nets = ClosedForm::exact();
    let config = ReplanConfig {
        epsilon: 0.01,
        growth: Growth::Grow(2),
        max_horizon: 32,
        sampled: false,
        guard: Guard::default(),
    };
    let state = [0.3f32, 0.2];
    // An old plan of the policy's own actions along the exact rollout, decided at step 4...
    let mut old = Plan::with_capacity(OBS, ACT, 16);
    let mut s = state;
    for _ in 0..8 {
        let a = [ClosedForm::mean_action(&s)];
        let next = env_step(&s, &a);
        old.push(&a, &next, 4);
        s = next;
    }
    for bad in [0usize, 3, 7] {
        let mut planted = Plan::with_capacity(OBS, ACT, 16);
        for j in 0..old.len() {
            let a = old.action(j)[0];
            // -|d|^2 = -0.25 < -eps: this action must break the plan.
            let a = if j == bad { (a - 0.5).max(-1.0) } else { a };
            planted.push(&[a], old.next_obs(j), old.decided_at(j));
        }
        let mut new = Plan::with_capacity(OBS, ACT, 40);
        let mut scratch = ReplanScratch::new(OBS, ACT);
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let outcome = replan(
            &mut nets,
            ReplanJob {
                config,
                state: &state,
                step: 5,
                old: planted.tail(0),
                new: &mut new,
                rng: &mut rng,
            },
            &mut scratch,
        )
        .unwrap();
        assert_eq!(outcome.broke_at, Some(bad));
        assert_eq!(outcome.kept, bad);
        assert_eq!(outcome.appended, 2);
        assert_eq!(new.len(), bad + 2);
        for j in 0..bad {
            assert_eq!(new.action(j), planted.action(j));
            assert_eq!(new.decided_at(j), 4);
        }
        // The replacement is pi at the breaking state, decided now.
        let mut s = state;
        for j in 0..bad {
            s = env_step(&s, new.action(j));
        }
        assert_eq!(new.action(bad)[0], ClosedForm::mean_action(&s));
        assert_eq!(new.decided_at(bad), 5);
    }
}

/// The policy's own actions along the exact rollout from `state`, with action `planted`
/// replaced by `replace(mean action there)`.
fn plan_with(state: [f32; OBS], planted: usize, replace: impl Fn(f32) -> f32) -> Plan {
    let mut old = Plan::with_capacity(OBS, ACT, 16);
    let mut s = state;
    for j in 0..8 {
        let mean = ClosedForm::mean_action(&s);
        let a = [if j == planted { replace(mean) } else { mean }];
        let next = env_step(&s, &a);
        old.push(&a, &next, 4);
        s = next;
    }
    old
}

fn replan_alone(
    nets: &mut ClosedForm,
    config: ReplanConfig,
    state: [f32; OBS],
    old: &Plan,
) -> ReplanOutcome {
    // The same job for Replan and for the reference, each into its own plan.
    let job = |new, rng| ReplanJob {
        config,
        state: &state,
        step: 5,
        old: old.tail(0),
        new,
        rng,
    };
    let (mut new, mut expected) = (
        Plan::with_capacity(OBS, ACT, 40),
        Plan::with_capacity(OBS, ACT, 40),
    );
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let outcome = replan(
        nets,
        job(&mut new, &mut rng),
        &mut ReplanScratch::new(OBS, ACT),
    )
    .unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let job = job(&mut expected, &mut rng);
    assert_eq!(reference::reference_replan(nets, job), Ok(outcome));
    assert_eq!(new, expected);
    outcome
}

#[test]
fn the_support_limit_breaks_at_an_action_the_policy_would_not_take() {
    let mut nets = ClosedForm::exact();
    let state = [0.3f32, 0.2];
    // The ClosedForm policy's Gaussian has std 0.3 before tanh: 2.5 std from its mean.
    let old = plan_with(state, 3, |mean| (mean.atanh() + 2.5 * 0.3).tanh());
    let config = |support_limit| ReplanConfig {
        guard: Guard {
            every_critic: false,
            support_limit,
            ..Default::default()
        },
        ..huge_eps(Growth::Grow(2), 32)
    };
    assert_eq!(
        replan_alone(&mut nets, config(0.0), state, &old).broke_at,
        None
    );
    assert_eq!(
        replan_alone(&mut nets, config(3.0), state, &old).broke_at,
        None
    );
    let outcome = replan_alone(&mut nets, config(2.0), state, &old);
    assert_eq!((outcome.broke_at, outcome.kept), (Some(3), 3));
    // The policy's own actions lie 0 std from its mean: even a tiny limit keeps them.
    let own = plan_with(state, usize::MAX, |mean| mean);
    assert_eq!(
        replan_alone(&mut nets, config(1e-3), state, &own).broke_at,
        None
    );
    assert_eq!(support_distance(1.0, 50.0, 0.3), 0.0);
    assert!((support_distance(0.5, 0.5f32.atanh() - 0.6, 0.3) - 2.0).abs() < 1e-5);
}

#[test]
fn every_critic_breaks_where_one_critic_objects_and_their_aggregate_does_not() {
    // Critic 2 is centred 0.2 above the policy: for a = pi(s) + 0.1 critic 1's gap is 0.01 and
    // critic 2's -0.03, and the aggregate min's is -0.03.
    let mut nets = ClosedForm {
        critic_shift: 0.2,
        ..ClosedForm::exact()
    };
    let state = [0.3f32, 0.2];
    let old = plan_with(state, 2, |mean| mean + 0.1);
    let config = |every_critic| ReplanConfig {
        epsilon: 0.005,
        guard: Guard {
            every_critic,
            support_limit: 0.0,
            ..Default::default()
        },
        ..ReplanConfig::default()
    };
    let paper = replan_alone(&mut nets, config(false), state, &old);
    assert_eq!((paper.broke_at, paper.kept), (None, 8));
    let guarded = replan_alone(&mut nets, config(true), state, &old);
    assert_eq!((guarded.broke_at, guarded.kept), (Some(2), 2));
}

#[test]
fn forecast_f_t_over_an_episode() {
    // Grow 2 that never breaks: a_t was decided at floor(t / 2), so f_t = floor((t + 1) / 2) + 1
    // until the cap bounds it.
    let mut ep = Episode::new(ClosedForm::exact(), huge_eps(Growth::Grow(2), 1000), 3);
    for t in 0..50u64 {
        assert_eq!(ep.step().f_t, t.div_ceil(2) + 1, "step {t}");
    }
    // Capped at H: the plan is H long and every action waits H - 1 steps, so f_t reaches H.
    let h = 4;
    let mut capped = Episode::new(ClosedForm::exact(), huge_eps(Growth::Grow(2), h), 3);
    let f: Vec<u64> = (0..12).map(|_| capped.step().f_t).collect();
    assert_eq!(f, vec![1, 2, 2, 3, 3, 4, 4, 4, 4, 4, 4, 4]);
    // A model that is always wrong under eps = 0 breaks at the first action every step: f_t = 1.
    let mut breaking = Episode::new(
        ClosedForm {
            critic_shift: 0.0,
            model_bias: 0.2,
            broken_model: false,
            nan_above: f32::INFINITY,
        },
        ReplanConfig::default(),
        3,
    );
    for t in 0..20 {
        let rec = breaking.step();
        assert_eq!(rec.f_t, 1, "step {t}");
        if t > 0 {
            assert_eq!(rec.outcome.broke_at, Some(0));
        }
    }
}

#[test]
fn sampled_mode_is_reproducible_from_its_seed() {
    let config = ReplanConfig {
        sampled: true,
        ..ReplanConfig::default()
    };
    let run = |seed: u64| -> Vec<f32> {
        let mut ep = Episode::new(ClosedForm::exact(), config, seed);
        (0..30).map(|_| ep.step().executed).collect()
    };
    assert_eq!(run(11), run(11));
    assert_ne!(run(11), run(12));
    // Sampled actions differ from the deterministic mean.
    let mut det = Episode::new(ClosedForm::exact(), ReplanConfig::default(), 11);
    let det: Vec<f32> = (0..30).map(|_| det.step().executed).collect();
    assert_ne!(run(11), det);
}

#[test]
fn an_old_plan_longer_than_the_cap_is_truncated() {
    let mut nets = ClosedForm::exact();
    let config = huge_eps(Growth::Grow(2), 5);
    let mut old = Plan::with_capacity(OBS, ACT, 12);
    for _ in 0..12 {
        old.push(&[0.1], &[0.0, 0.0], 0);
    }
    let mut new = Plan::with_capacity(OBS, ACT, 12);
    let outcome = replan(
        &mut nets,
        ReplanJob {
            config,
            state: &[0.0, 0.0],
            step: 1,
            old: old.tail(0),
            new: &mut new,
            rng: &mut ChaCha8Rng::seed_from_u64(0),
        },
        &mut ReplanScratch::new(OBS, ACT),
    )
    .unwrap();
    assert_eq!((outcome.kept, outcome.appended, new.len()), (5, 0, 5));
}

#[test]
fn a_non_finite_model_is_an_error_not_a_plan() {
    let mut nets = ClosedForm {
        critic_shift: 0.0,
        model_bias: 0.0,
        broken_model: true,
        nan_above: f32::INFINITY,
    };
    let mut new = Plan::with_capacity(OBS, ACT, 4);
    let err = replan(
        &mut nets,
        ReplanJob {
            config: ReplanConfig::default(),
            state: &[0.0, 0.0],
            step: 0,
            old: PlanView::empty(),
            new: &mut new,
            rng: &mut ChaCha8Rng::seed_from_u64(0),
        },
        &mut ReplanScratch::new(OBS, ACT),
    )
    .unwrap_err();
    assert_eq!(
        err,
        NonFinite {
            what: "model",
            index: 0
        }
    );
}

#[test]
fn a_batch_gives_each_session_what_it_gets_alone() {
    // Sessions with different configs, old plans, seeds and a planted break, replanned alone and
    // together.
    let configs = [
        ReplanConfig::default(),
        huge_eps(Growth::Grow(3), 7),
        ReplanConfig {
            epsilon: 0.01,
            sampled: true,
            ..ReplanConfig::default()
        },
        huge_eps(Growth::Fixed(5), 5),
        ReplanConfig {
            epsilon: 0.001,
            growth: Growth::Fixed(9),
            max_horizon: 9,
            sampled: false,
            guard: Guard::default(),
        },
    ];
    let states: Vec<[f32; OBS]> = (0..configs.len())
        .map(|i| [0.3 * i as f32 - 0.5, 0.2 - 0.1 * i as f32])
        .collect();
    let olds: Vec<Plan> = (0..configs.len())
        .map(|i| {
            let mut old = Plan::with_capacity(OBS, ACT, 16);
            let mut s = states[i];
            for j in 0..(2 * i + 1) {
                let bad = if j == 2 { 0.6 } else { 0.0 };
                let a = [(ClosedForm::mean_action(&s) - bad).max(-1.0)];
                let next = env_step(&s, &a);
                old.push(&a, &next, j as u64);
                s = next;
            }
            old
        })
        .collect();
    let mut nets = ClosedForm {
        critic_shift: 0.0,
        model_bias: 0.01,
        broken_model: false,
        nan_above: f32::INFINITY,
    };
    let alone: Vec<(Result<ReplanOutcome, NonFinite>, Plan)> = (0..configs.len())
        .map(|i| {
            let mut new = Plan::with_capacity(OBS, ACT, 16);
            let mut rng = ChaCha8Rng::seed_from_u64(i as u64);
            let r = replan(
                &mut nets,
                ReplanJob {
                    config: configs[i],
                    state: &states[i],
                    step: 9,
                    old: olds[i].tail(0),
                    new: &mut new,
                    rng: &mut rng,
                },
                &mut ReplanScratch::new(OBS, ACT),
            );
            (r, new)
        })
        .collect();
    let mut news: Vec<Plan> = (0..configs.len())
        .map(|_| Plan::with_capacity(OBS, ACT, 16))
        .collect();
    let mut rngs: Vec<ChaCha8Rng> = (0..configs.len())
        .map(|i| ChaCha8Rng::seed_from_u64(i as u64))
        .collect();
    let mut jobs: Vec<ReplanJob<'_, ChaCha8Rng>> = news
        .iter_mut()
        .zip(rngs.iter_mut())
        .enumerate()
        .map(|(i, (new, rng))| ReplanJob {
            config: configs[i],
            state: &states[i],
            step: 9,
            old: olds[i].tail(0),
            new,
            rng,
        })
        .collect();
    let mut results = vec![Err(NonFinite { what: "", index: 0 }); configs.len()];
    replan_batch(
        &mut nets,
        &mut jobs,
        &mut ReplanScratch::new(OBS, ACT),
        &mut results,
    );
    drop(jobs);
    let mut saw_break = false;
    for i in 0..configs.len() {
        assert_eq!(results[i], alone[i].0, "session {i}");
        assert_eq!(news[i], alone[i].1, "session {i}");
        saw_break |= results[i].as_ref().unwrap().broke_at.is_some();
    }
    assert!(saw_break);
}

/// The networks of `nets`, counting the actor's passes, with an actor that gives NaN at states
/// whose first value exceeds `nan_actor_above`.
struct Instrumented {
    nets: ClosedForm,
    actor_passes: usize,
    nan_actor_above: f32,
}

impl Instrumented {
    fn new(nan_actor_above: f32) -> Instrumented {
        Instrumented {
            nets: ClosedForm::exact(),
            actor_passes: 0,
            nan_actor_above,
        }
    }
}

impl Networks for Instrumented {
    fn obs_dim(&self) -> usize {
        self.nets.obs_dim()
    }
    fn act_dim(&self) -> usize {
        self.nets.act_dim()
    }
    fn act(&mut self, obs: &[f32], noise: &[f32], actions: &mut [f32]) {
        self.actor_passes += 1;
        self.nets.act(obs, noise, actions);
        for (state, action) in obs.chunks_exact(OBS).zip(actions.chunks_exact_mut(ACT)) {
            if state[0] > self.nan_actor_above {
                action.fill(f32::NAN);
            }
        }
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
        self.nets.q_pair(obs, a, b, q_a, q_b, largest_gap);
    }
    fn predict_next(&mut self, obs: &[f32], actions: &[f32], next_obs: &mut [f32]) {
        self.nets.predict_next(obs, actions, next_obs);
    }
    fn policy_distance(&mut self, obs: &[f32], actions: &[f32], distance: &mut [f32]) {
        self.nets.policy_distance(obs, actions, distance);
    }
}

#[test]
fn a_plan_kept_whole_draws_its_first_new_action_in_the_tests_actor_pass() {
    // (max horizon, old actions, actor passes): the test's pass also draws pi at the state after
    // the old plan, so appending k = 2 actions takes one more pass, not two; a plan already at
    // its cap appends nothing and takes the test's pass alone; an empty old plan has no test.
    for (cap, old_len, passes) in [(32, 5, 2), (32, 8, 2), (6, 6, 1), (32, 0, 2)] {
        let mut nets = Instrumented::new(f32::INFINITY);
        let mut old = Plan::with_capacity(OBS, ACT, 64);
        for j in 0..old_len {
            old.push(&[0.1 * j as f32], &[0.0, 0.0], j as u64);
        }
        let config = huge_eps(Growth::Grow(2), cap);
        let mut new = Plan::with_capacity(OBS, ACT, 64);
        let outcome = replan(
            &mut nets,
            ReplanJob {
                config,
                state: &[0.3, -0.2],
                step: 9,
                old: old.tail(0),
                new: &mut new,
                rng: &mut ChaCha8Rng::seed_from_u64(0),
            },
            &mut ReplanScratch::new(OBS, ACT),
        )
        .unwrap();
        assert_eq!(outcome.kept, old_len.min(cap), "cap {cap}, {old_len} old");
        assert_eq!(outcome.appended, 2.min(cap - outcome.kept));
        assert_eq!(nets.actor_passes, passes, "cap {cap}, {old_len} old");
        // The first new action is pi at the model's state after the kept ones.
        if outcome.appended > 0 {
            let after = match outcome.kept {
                0 => [0.3, -0.2],
                k => {
                    let s = new.next_obs(k - 1);
                    [s[0], s[1]]
                }
            };
            assert_eq!(new.action(outcome.kept)[0], ClosedForm::mean_action(&after));
        }
    }
}

#[test]
fn an_actor_failing_after_a_plan_kept_whole_fails_as_the_plain_algorithm_does() {
    use rand::Rng;
    let mut scenario = ChaCha8Rng::seed_from_u64(7);
    let mut after_kept_whole = 0;
    for case in 0..300 {
        let config = ReplanConfig {
            sampled: case % 2 == 1,
            ..huge_eps(Growth::Grow(2), 48)
        };
        let mut old = Plan::with_capacity(OBS, ACT, 64);
        for j in 0..scenario.random_range(0..40usize) {
            old.push(
                &[scenario.random_range(-1.0f32..1.0)],
                &[0.0, 0.0],
                j as u64,
            );
        }
        let state = [
            scenario.random_range(-1.0..1.0),
            scenario.random_range(-1.0..1.0),
        ];
        // Half the cases: a threshold between the old plan's states and the state after it (the
        // exact model's rollout), where one exists; the others anywhere.
        let mut rollout = vec![state];
        for j in 0..old.len() {
            let last = rollout[rollout.len() - 1];
            rollout.push(env_step(&last, old.action(j)));
        }
        let before_end = rollout[..rollout.len() - 1]
            .iter()
            .map(|s| s[0])
            .fold(f32::NEG_INFINITY, f32::max);
        let end = rollout[rollout.len() - 1][0];
        let above = if case % 4 < 2 && end > before_end {
            (before_end + end) / 2.0
        } else {
            scenario.random_range(-1.5..1.5)
        };
        let run = |reference: bool| {
            let mut nets = Instrumented::new(above);
            let mut new = Plan::with_capacity(OBS, ACT, 64);
            let mut rng = ChaCha8Rng::seed_from_u64(case);
            let job = ReplanJob {
                config,
                state: &state,
                step: 40,
                old: old.tail(0),
                new: &mut new,
                rng: &mut rng,
            };
            let outcome = match reference {
                true => reference::reference_replan(&mut nets, job),
                false => replan(&mut nets, job, &mut ReplanScratch::new(OBS, ACT)),
            };
            (outcome, new, rng.random::<u64>())
        };
        let (expected, expected_plan, expected_rng) = run(true);
        let (got, got_plan, got_rng) = run(false);
        assert_eq!(got, expected, "case {case}");
        if expected.is_ok() {
            assert_eq!(got_plan, expected_plan, "case {case}");
            assert_eq!(got_rng, expected_rng, "case {case}");
        }
        // The actor failed at the state after the whole old plan: the extension's first action.
        if !old.is_empty()
            && expected
                == Err(NonFinite {
                    what: "actor",
                    index: old.len(),
                })
        {
            after_kept_whole += 1;
        }
    }
    assert!(after_kept_whole > 10, "exercised {after_kept_whole} times");
}

#[test]
fn chunked_batched_replan_matches_the_plain_algorithm() {
    use rand::Rng;
    let mut scenario = ChaCha8Rng::seed_from_u64(42);
    let mut errors = 0;
    for case in 0..400 {
        let config = ReplanConfig {
            epsilon: [0.0, 1e-4, 1e-3, 0.01, 0.1, 1e9][case % 6],
            growth: if case % 3 == 0 {
                Growth::Fixed(scenario.random_range(1..40))
            } else {
                Growth::Grow(scenario.random_range(1..4))
            },
            max_horizon: scenario.random_range(1..48),
            sampled: case % 2 == 1,
            guard: Guard {
                every_critic: case % 5 < 2,
                support_limit: [0.0, 0.5, 2.0, 4.0][case / 5 % 4],
                ..Default::default()
            },
        };
        let mut nets = ClosedForm {
            critic_shift: if case % 7 < 4 {
                scenario.random_range(-0.3..0.3)
            } else {
                0.0
            },
            model_bias: scenario.random_range(-0.02..0.02),
            broken_model: false,
            // Every fourth case: the model fails part-way through the rollout.
            nan_above: if case % 4 == 3 {
                scenario.random_range(-0.5..1.0)
            } else {
                f32::INFINITY
            },
        };
        let state = [
            scenario.random_range(-1.0..1.0),
            scenario.random_range(-1.0..1.0),
        ];
        let mut old = Plan::with_capacity(OBS, ACT, 64);
        for j in 0..scenario.random_range(0..45usize) {
            let a = [scenario.random_range(-1.0f32..1.0)];
            old.push(&a, &[0.0, 0.0], j as u64);
        }
        let mut expected = Plan::with_capacity(OBS, ACT, 64);
        let mut rng_a = ChaCha8Rng::seed_from_u64(case as u64);
        let outcome = reference::reference_replan(
            &mut nets,
            ReplanJob {
                config,
                state: &state,
                step: 50,
                old: old.tail(0),
                new: &mut expected,
                rng: &mut rng_a,
            },
        );
        let mut got = Plan::with_capacity(OBS, ACT, 64);
        let mut rng_b = ChaCha8Rng::seed_from_u64(case as u64);
        let result = replan(
            &mut nets,
            ReplanJob {
                config,
                state: &state,
                step: 50,
                old: old.tail(0),
                new: &mut got,
                rng: &mut rng_b,
            },
            &mut ReplanScratch::new(OBS, ACT),
        );
        assert_eq!(result, outcome, "case {case} {config:?}");
        if outcome.is_err() {
            errors += 1;
            continue;
        }
        assert_eq!(got, expected, "case {case}");
        // The same draws were taken from the rng.
        assert_eq!(rng_a.random::<u64>(), rng_b.random::<u64>(), "case {case}");
    }
    assert!(
        errors > 10,
        "model failures part-way were exercised: {errors}"
    );
}

#[test]
fn a_commitment_offers_its_tail_and_keeps_its_plan_until_commit() {
    let mut c = Commitment::with_capacity(1, 1, 4);
    assert!(c.next_replan(false).0.is_empty(), "nothing committed yet");
    {
        let (_, new) = c.next_replan(true);
        new.push(&[0.1], &[1.0], 3);
        new.push(&[0.2], &[2.0], 3);
        new.push(&[0.3], &[3.0], 4);
    }
    assert!(
        c.plan().is_empty(),
        "a replan is not committed until commit()"
    );
    c.commit();
    assert_eq!(c.plan().len(), 3);
    // The action executed at step 5 was decided at step 3: f_t = 5 + 1 - 3.
    assert_eq!(c.forecast(5), 3);
    let (old, new) = c.next_replan(false);
    assert_eq!(old.len(), 2, "the executed first action is dropped");
    assert_eq!((old.action(0), old.decided_at(1)), (&[0.2f32][..], 4));
    new.clear();
    assert!(
        c.next_replan(true).0.is_empty(),
        "an episode's start ignores the old plan"
    );
    c.clear();
    assert!(c.plan().is_empty());
}
