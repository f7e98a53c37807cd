use std::time::Duration;

use super::*;
use crate::bundle::ValueScale;
use crate::testing::test_manifest;

fn policy() -> Arc<Policy> {
    Arc::new(crate::testing::random_policy(
        test_manifest("toy", "toy", 3, 2, &[16, 16], &[8, 8]),
        5,
    ))
}

fn session(policy: &Arc<Policy>, options: proto::SessionOptions) -> Session {
    let settings = SessionSettings::resolve(Some(&options), policy, 256).unwrap();
    Session::new("s".into(), policy.clone(), settings)
}

fn step(s: &mut Session, obs: &[f32]) -> proto::StepResponse {
    let mut evaluator = Evaluator::for_sessions(s.policy.clone(), 1);
    let mut scratch = ReplanScratch::new(3, 2);
    let report = s
        .apply_step(
            &mut evaluator,
            &mut scratch,
            StepInput {
                observation: obs,
                new_episode: false,
                arrival: Arrival::next(),
            },
        )
        .unwrap();
    s.response(&report)
}

#[test]
fn a_step_taken_back_changes_nothing() {
    let policy = policy();
    let options = proto::SessionOptions {
        sampled: true,
        seed: 9,
        tolerance: Some(proto::session_options::Tolerance::Epsilon(1e6)),
        ..Default::default()
    };
    let (mut a, mut b) = (session(&policy, options), session(&policy, options));
    step(&mut a, &[0.1, 0.2, 0.3]);
    step(&mut b, &[0.1, 0.2, 0.3]);
    let lost = step(&mut a, &[0.5, 0.5, 0.5]);
    assert!(a.take_back(2));
    // Only the last step, and only once.
    assert!(!a.take_back(2));
    assert!(!a.take_back(1));
    assert_eq!(a.steps_served(), 1);
    let (ra, rb) = (
        step(&mut a, &[0.4, 0.0, 0.1]),
        step(&mut b, &[0.4, 0.0, 0.1]),
    );
    assert_eq!(ra, rb, "the taken-back step left a trace");
    assert_eq!(ra.step, 1);
    assert_ne!(lost.forecast, ra.forecast);
    assert_eq!(a.plan_proto(), b.plan_proto());
}

#[test]
fn a_step_overtaken_by_a_later_arrival_is_refused_and_changes_nothing() {
    let policy = policy();
    let mut s = session(&policy, proto::SessionOptions::default());
    let mut evaluator = Evaluator::for_sessions(policy.clone(), 1);
    let mut scratch = ReplanScratch::new(3, 2);
    let (early, late, later) = (Arrival::next(), Arrival::next(), Arrival::next());
    let obs = [0.1, 0.2, 0.3];
    let mut step = |s: &mut Session, arrival| {
        s.apply_step(
            &mut evaluator,
            &mut scratch,
            StepInput {
                observation: &obs,
                new_episode: false,
                arrival,
            },
        )
    };
    assert_eq!(step(&mut s, late).unwrap().step, 0);
    let plan = s.plan_proto();
    assert!(matches!(step(&mut s, early), Err(StepError::OvertakenBy)));
    assert_eq!(s.plan_proto(), plan);
    assert_eq!(s.steps_served(), 1);
    // A step taken back is as if it never arrived: an earlier one may go after all.
    let served = step(&mut s, later).unwrap().served;
    assert!(s.take_back(served));
    assert_eq!(step(&mut s, late).unwrap().step, 1);
}

#[tokio::test(start_paused = true)]
async fn a_session_in_use_never_expires_and_idles_from_its_last_use() {
    let sessions = Sessions::new(8, Duration::from_millis(30));
    let policy = policy();
    let s = session(&policy, Default::default());
    sessions.insert(s, Default::default(), None).unwrap();
    let in_use = sessions.get("s", None).unwrap();
    tokio::time::advance(Duration::from_millis(80)).await;
    assert_eq!(sessions.evict_idle(), 0, "evicted while a request used it");
    drop(in_use);
    assert_eq!(
        sessions.evict_idle(),
        0,
        "idle time must start when the request ends"
    );
    tokio::time::advance(Duration::from_millis(80)).await;
    assert_eq!(sessions.evict_idle(), 1);
    assert!(matches!(
        sessions.get("s", None),
        Err(SessionError::Expired { .. })
    ));
}

#[test]
fn resumed_counters_that_could_wrap_are_refused() {
    let policy = policy();
    let plan = |start_step: u64, episode: u64, decided_at: u64| proto::Plan {
        session_id: String::new(),
        episode,
        start_step,
        actions: vec![proto::PlannedAction {
            action: vec![0.0, 0.0],
            predicted_observation: vec![],
            decided_at,
        }],
    };
    for (start, episode, decided) in [
        (u64::MAX, 0, 0),
        (u64::MAX, 0, u64::MAX),
        (0, u64::MAX, 0),
        (MAX_COUNTER + 1, 0, 0),
    ] {
        let mut s = session(&policy, Default::default());
        let e = s.resume(&plan(start, episode, decided)).unwrap_err();
        assert!(e.contains("at most 9007199254740991"), "{e}");
    }
    let mut s = session(&policy, Default::default());
    s.resume(&plan(MAX_COUNTER, MAX_COUNTER, MAX_COUNTER))
        .unwrap();
    let response = step(&mut s, &[0.0; 3]);
    assert_eq!(response.step, MAX_COUNTER + 1);
    assert_eq!(response.episode, MAX_COUNTER);
    assert!(response.f_t >= 1);
}

#[test]
fn options_resolve_as_the_proto_says() {
    use proto::session_options::{Growth as G, Tolerance};
    let policy = policy();
    let resolve =
        |options: proto::SessionOptions| SessionSettings::resolve(Some(&options), &policy, 256);
    // max_horizon 0: 32, or n for fixed n > 32.
    let horizon = |growth, max_horizon| {
        resolve(proto::SessionOptions {
            growth,
            max_horizon,
            ..Default::default()
        })
        .map(|s| s.replan.max_horizon)
    };
    assert_eq!(horizon(None, 0), Ok(32));
    assert_eq!(horizon(Some(G::Fixed(8)), 0), Ok(32));
    assert_eq!(horizon(Some(G::Fixed(40)), 0), Ok(40));
    assert_eq!(horizon(Some(G::Fixed(40)), 40), Ok(40));
    assert!(
        horizon(Some(G::Fixed(40)), 32)
            .unwrap_err()
            .contains("longer than")
    );
    assert!(
        horizon(Some(G::Fixed(300)), 0)
            .unwrap_err()
            .contains("1..=256")
    );

    // A value scale that overflows f32 never yields a non-finite tolerance.
    let mut huge = (*policy).clone();
    huge.manifest.value_scale = Some(ValueScale {
        v_pi: 1.7e308,
        v_rand: -1.7e308,
    });
    for coef in [0.0, 1.0] {
        let e = SessionSettings::resolve(
            Some(&proto::SessionOptions {
                tolerance: Some(Tolerance::EpsilonCoef(coef)),
                ..Default::default()
            }),
            &huge,
            256,
        )
        .unwrap_err();
        assert!(e.contains("not a finite f32"), "{coef}: {e}");
    }

    // An actor without a distribution (TD3, DDPG, gSDE) cannot be sampled.
    let sampled = proto::SessionOptions {
        sampled: true,
        ..Default::default()
    };
    assert!(resolve(sampled).is_ok());
    let mut deterministic = (*policy).clone();
    deterministic.manifest.actor.kind = crate::manifest::ActorKind::Deterministic;
    deterministic.actor.log_std = None;
    let e = SessionSettings::resolve(Some(&sampled), &deterministic, 256).unwrap_err();
    assert!(
        e.contains("has a deterministic actor") && e.contains("leave sampled off"),
        "{e}"
    );
    assert!(SessionSettings::resolve(None, &deterministic, 256).is_ok());
}

#[test]
fn a_guard_resolves_as_the_proto_says() {
    let policy = policy();
    let with_guard = |guard: Option<proto::PlanGuard>| proto::SessionOptions {
        guard,
        ..Default::default()
    };
    let resolve = |options: &proto::SessionOptions, policy: &Policy| {
        SessionSettings::resolve(Some(options), policy, 256)
    };
    // Unset or empty: the paper's test, and the resolved options say so.
    for options in [with_guard(None), with_guard(Some(Default::default()))] {
        let settings = resolve(&options, &policy).unwrap();
        assert_eq!(settings.replan.guard, crate::plan::Guard::default());
        assert_eq!(settings.to_proto().guard, Some(proto::PlanGuard::default()));
    }
    let guarded = with_guard(Some(proto::PlanGuard {
        every_critic: true,
        support_limit: 3.5,
        ..Default::default()
    }));
    let settings = resolve(&guarded, &policy).unwrap();
    assert_eq!(
        settings.replan.guard,
        crate::plan::Guard {
            every_critic: true,
            support_limit: 3.5,
            ..Default::default()
        }
    );
    assert_eq!(settings.to_proto().guard, guarded.guard);
    for bad in [-1.0, f64::NAN, f64::INFINITY, 1e300] {
        let options = with_guard(Some(proto::PlanGuard {
            every_critic: false,
            support_limit: bad,
            ..Default::default()
        }));
        let e = resolve(&options, &policy).unwrap_err();
        assert!(e.contains("guard.support_limit is"), "{bad}: {e}");
    }
    // The support limit measures against the policy's Gaussian; every_critic needs none.
    let mut deterministic = (*policy).clone();
    deterministic.manifest.actor.kind = crate::manifest::ActorKind::Deterministic;
    deterministic.actor.log_std = None;
    let e = resolve(&guarded, &deterministic).unwrap_err();
    assert!(
        e.contains("has a deterministic actor") && e.contains("support_limit at 0"),
        "{e}"
    );
    let critics_only = with_guard(Some(proto::PlanGuard {
        every_critic: true,
        support_limit: 0.0,
        ..Default::default()
    }));
    assert!(resolve(&critics_only, &deterministic).is_ok());
}

#[test]
fn a_session_without_a_guard_gets_its_bundles_default_guard() {
    let guard = crate::plan::Guard {
        every_critic: true,
        support_limit: 3.0,
        ..Default::default()
    };
    let mut policy = (*policy()).clone();
    policy.manifest.default_guard = Some(guard);
    let resolve = |options: Option<&proto::SessionOptions>| {
        SessionSettings::resolve(options, &policy, 256).unwrap()
    };
    // No options, or options without a guard: the bundle's default, and the answer says so.
    let unset = proto::SessionOptions::default();
    for options in [None, Some(&unset)] {
        let settings = resolve(options);
        assert_eq!(settings.replan.guard, guard);
        assert_eq!(
            settings.to_proto().guard,
            Some(proto::PlanGuard {
                every_critic: true,
                support_limit: 3.0,
                ..Default::default()
            })
        );
    }
    // An empty guard asks for the paper's test; a guard of its own replaces the default.
    let paper = proto::SessionOptions {
        guard: Some(proto::PlanGuard::default()),
        ..Default::default()
    };
    assert_eq!(resolve(Some(&paper)).replan.guard, Default::default());
    let own = proto::SessionOptions {
        guard: Some(proto::PlanGuard {
            every_critic: false,
            support_limit: 5.0,
            ..Default::default()
        }),
        ..Default::default()
    };
    assert_eq!(
        resolve(Some(&own)).replan.guard,
        crate::plan::Guard {
            every_critic: false,
            support_limit: 5.0,
            ..Default::default()
        }
    );
}

#[test]
fn a_guards_epsilon_limit_holds_every_tolerance_to_it() {
    use proto::session_options::Tolerance;
    let mut policy = (*policy()).clone();
    let scale = policy
        .manifest
        .value_scale
        .expect("the test policy has a value scale");
    let range = scale.v_pi - scale.v_rand;
    assert!(range > 0.0);
    let capped = crate::plan::Guard {
        support_limit: 3.0,
        max_epsilon_coef: 0.005,
        ..Default::default()
    };
    policy.manifest.default_guard = Some(capped);
    let with = |tolerance, guard| proto::SessionOptions {
        tolerance: Some(tolerance),
        guard,
        ..Default::default()
    };
    let eps = |options: &proto::SessionOptions| {
        SessionSettings::resolve(Some(options), &policy, 256)
            .unwrap()
            .to_proto()
            .epsilon
    };
    let limit = (0.005 * range) as f32 as f64;
    // Above the limit, as a coefficient or absolute: the limit, and the answer says so.
    assert_eq!(eps(&with(Tolerance::EpsilonCoef(0.01), None)), limit);
    assert_eq!(eps(&with(Tolerance::Epsilon(1e30), None)), limit);
    // At or below it: as asked, bit for bit.
    assert_eq!(eps(&with(Tolerance::EpsilonCoef(0.005), None)), limit);
    assert_eq!(
        eps(&with(Tolerance::EpsilonCoef(0.002), None)),
        (0.002 * range) as f32 as f64
    );
    let resolved = SessionSettings::resolve(
        Some(&with(Tolerance::EpsilonCoef(0.01), None)),
        &policy,
        256,
    )
    .unwrap();
    assert_eq!(resolved.replan.guard, capped);
    assert_eq!(resolved.to_proto().guard.unwrap().max_epsilon_coef, 0.005);
    // The paper's test (an empty guard) or a guard of the session's own without a limit: none.
    let paper = Some(proto::PlanGuard::default());
    assert_eq!(
        eps(&with(Tolerance::EpsilonCoef(0.01), paper)),
        (0.01 * range) as f32 as f64
    );
    // A session may set its own limit; bad ones and ones the policy cannot scale are refused.
    let own = |coef| {
        Some(proto::PlanGuard {
            max_epsilon_coef: coef,
            ..Default::default()
        })
    };
    assert_eq!(
        eps(&with(Tolerance::EpsilonCoef(0.01), own(0.002))),
        (0.002 * range) as f32 as f64
    );
    for bad in [-1.0, f64::NAN, f64::INFINITY] {
        let e =
            SessionSettings::resolve(Some(&with(Tolerance::Epsilon(0.1), own(bad))), &policy, 256)
                .unwrap_err();
        assert!(e.contains("guard.max_epsilon_coef is"), "{bad}: {e}");
    }
    let mut unscaled = policy.clone();
    unscaled.manifest.value_scale = None;
    let e = SessionSettings::resolve(
        Some(&with(Tolerance::Epsilon(0.1), own(0.005))),
        &unscaled,
        256,
    )
    .unwrap_err();
    assert!(e.contains("needs the policy's value scale"), "{e}");
}
