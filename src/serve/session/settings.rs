//! A session's options, resolved against the policy and the server's limits.

use crate::plan::{DEFAULT_MAX_HORIZON, Growth, Guard, ReplanConfig};
use crate::policy::Policy;
use crate::proto;

pub(crate) const MAX_COUNTER: u64 = (1 << 53) - 1;

/// Resolved per-session options.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SessionSettings {
    pub replan: ReplanConfig,
    pub seed: u64,
}

impl SessionSettings {
    /// Fills defaults into the client's options and checks them against the policy and limit.
    pub fn resolve(
        options: Option<&proto::SessionOptions>,
        policy: &Policy,
        max_horizon_limit: usize,
    ) -> Result<SessionSettings, String> {
        use proto::session_options::{Growth as G, Tolerance};
        let default = proto::SessionOptions::default();
        let options = options.unwrap_or(&default);
        let epsilon = match options.tolerance {
            None => 0.0,
            Some(Tolerance::Epsilon(e)) => {
                if !(e.is_finite() && e >= 0.0) {
                    return Err(format!("epsilon is {e}; expected a finite value >= 0"));
                }
                e
            }
            Some(Tolerance::EpsilonCoef(c)) => {
                if !(c.is_finite() && c >= 0.0) {
                    return Err(format!("epsilon_coef is {c}; expected a finite value >= 0"));
                }
                let Some(scale) = policy.manifest.value_scale else {
                    return Err(format!(
                        "epsilon_coef needs the policy's value scale, and bundle '{}' has none; \
                         give an absolute epsilon instead",
                        policy.manifest.name
                    ));
                };
                let range = scale.v_pi - scale.v_rand;
                if range <= 0.0 {
                    return Err(format!(
                        "epsilon_coef needs V_pi > V_rand, but the bundle has V_pi = {} and \
                         V_rand = {}; give an absolute epsilon instead",
                        scale.v_pi, scale.v_rand
                    ));
                }
                c * range
            }
        };
        // The bundle's default was checked when it loaded.
        let guard = match &options.guard {
            None => policy.manifest.default_guard.unwrap_or_default(),
            Some(g) => resolve_guard(g, policy)?,
        };
        let epsilon = match epsilon_limit(guard, policy) {
            Some(limit) => epsilon.min(limit),
            None => epsilon,
        };
        // A finite tolerance always: coef x range can still overflow (or be 0 x inf).
        if !(epsilon.is_finite() && epsilon <= f32::MAX as f64) {
            return Err(format!(
                "epsilon {epsilon} is not a finite f32; give a smaller epsilon or epsilon_coef"
            ));
        }
        let check_count = |what: &str, n: u32| -> Result<usize, String> {
            if n == 0 || n as usize > max_horizon_limit {
                Err(format!(
                    "{what} is {n}; expected 1..={max_horizon_limit} (the server's horizon limit)"
                ))
            } else {
                Ok(n as usize)
            }
        };
        let growth = match options.growth {
            None => Growth::default(),
            Some(G::Grow(k)) => Growth::Grow(check_count("grow", k)?),
            Some(G::Fixed(n)) => Growth::Fixed(check_count("fixed", n)?),
        };
        let max_horizon = match (options.max_horizon, growth) {
            (0, Growth::Fixed(n)) => n.max(DEFAULT_MAX_HORIZON.min(max_horizon_limit)),
            (0, _) => DEFAULT_MAX_HORIZON.min(max_horizon_limit),
            (h, _) => check_count("max_horizon", h)?,
        };
        if let Growth::Fixed(n) = growth
            && n > max_horizon
        {
            return Err(format!(
                "fixed {n} is longer than max_horizon {max_horizon}; raise max_horizon or lower n"
            ));
        }
        if options.sampled && !policy.actor.samples() {
            return Err(format!(
                "sampled actions need a distribution to sample, and bundle '{}' has a {} actor, \
                 which acts deterministically; leave sampled off",
                policy.manifest.name,
                policy.manifest.actor.kind.as_str()
            ));
        }
        Ok(SessionSettings {
            replan: ReplanConfig {
                epsilon: epsilon as f32,
                guard,
                growth,
                max_horizon,
                sampled: options.sampled,
            },
            seed: options.seed,
        })
    }

    pub(crate) fn to_proto(self) -> proto::ResolvedOptions {
        let (mode, n) = match self.replan.growth {
            Growth::Grow(k) => ("grow", k),
            Growth::Fixed(n) => ("fixed", n),
        };
        proto::ResolvedOptions {
            epsilon: self.replan.epsilon as f64,
            growth_mode: mode.to_string(),
            growth: n as u32,
            max_horizon: self.replan.max_horizon as u32,
            sampled: self.replan.sampled,
            seed: self.seed,
            guard: Some(guard_proto(self.replan.guard)),
        }
    }
}

pub(crate) fn guard_proto(guard: Guard) -> proto::PlanGuard {
    proto::PlanGuard {
        every_critic: guard.every_critic,
        support_limit: guard.support_limit as f64,
        max_epsilon_coef: guard.max_epsilon_coef,
    }
}

/// The largest eps the guard allows: `max_epsilon_coef x (V_pi - V_rand)`, None without a limit.
/// A guard with a limit has passed `resolve_guard` or the manifest's checks, so the policy has a
/// value scale with V_pi > V_rand.
fn epsilon_limit(guard: Guard, policy: &Policy) -> Option<f64> {
    let scale = policy.manifest.value_scale?;
    (guard.max_epsilon_coef > 0.0).then_some(guard.max_epsilon_coef * (scale.v_pi - scale.v_rand))
}

fn resolve_guard(guard: &proto::PlanGuard, policy: &Policy) -> Result<Guard, String> {
    let limit = guard.support_limit;
    if !(limit.is_finite() && limit >= 0.0 && limit <= f32::MAX as f64) {
        return Err(format!(
            "guard.support_limit is {limit}; expected a finite value >= 0 (0: no limit)"
        ));
    }
    if limit > 0.0 && !policy.actor.samples() {
        return Err(format!(
            "guard.support_limit measures actions against the policy's Gaussian, and bundle \
             '{}' has a {} actor, which has none; leave support_limit at 0",
            policy.manifest.name,
            policy.manifest.actor.kind.as_str()
        ));
    }
    let coef = guard.max_epsilon_coef;
    if !(coef.is_finite() && coef >= 0.0) {
        return Err(format!(
            "guard.max_epsilon_coef is {coef}; expected a finite value >= 0 (0: no limit)"
        ));
    }
    if coef > 0.0
        && !policy
            .manifest
            .value_scale
            .is_some_and(|scale| scale.v_pi > scale.v_rand)
    {
        return Err(format!(
            "guard.max_epsilon_coef needs the policy's value scale with V_pi > V_rand, and \
             bundle '{}' has none; leave max_epsilon_coef at 0",
            policy.manifest.name
        ));
    }
    Ok(Guard {
        every_critic: guard.every_critic,
        support_limit: limit as f32,
        max_epsilon_coef: coef,
    })
}
