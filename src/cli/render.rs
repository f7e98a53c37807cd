//! `prac render`: a picture of a domain, optionally with a policy's imagined plan overlaid.

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, bail};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::domains;
use crate::plan::{Planner, ReplanConfig};
use crate::policy::Evaluator;
use crate::render::Forecast;

pub struct RenderRequest<'a> {
    pub domain: &'a str,
    pub seed: u64,
    pub out: &'a Path,
    /// Steps played before drawing: the policy's (PrAC) actions, else uniform random ones.
    pub steps: u32,
    pub policy: Option<&'a Path>,
    pub epsilon_coef: f64,
    pub size: (u32, u32),
}

/// Renders the request; returns the plan length drawn.
pub fn run(req: &RenderRequest<'_>) -> anyhow::Result<usize> {
    let Some(mut env) = domains::make(req.domain) else {
        bail!(
            "unknown domain '{}'; known: {}",
            req.domain,
            domains::DOMAINS.join(", ")
        );
    };
    let spec = env.spec().clone();
    let mut obs = vec![0.0; spec.obs_dim];
    env.reset(req.seed, &mut obs)?;
    let mut title = format!("{} | seed {}", req.domain, req.seed);
    let mut committed = None;
    if let Some(path) = req.policy {
        let policy = Arc::new(crate::bundle::load(path)?);
        if policy.manifest.domain != req.domain {
            bail!(
                "{}: policy is for domain '{}', not '{}'",
                path.display(),
                policy.manifest.domain,
                req.domain
            );
        }
        let epsilon = match policy.manifest.value_scale {
            Some(s) => (req.epsilon_coef * (s.v_pi - s.v_rand).max(0.0)) as f32,
            None if req.epsilon_coef == 0.0 => 0.0,
            None => bail!(
                "{}: no value scale, so --epsilon-coef cannot be used",
                path.display()
            ),
        };
        let config = ReplanConfig {
            epsilon,
            ..ReplanConfig::default()
        };
        let (od, ad) = (spec.obs_dim, spec.act_dim);
        let mut evaluator = Evaluator::new(policy.clone());
        let mut planner = Planner::new(config, od, ad, ChaCha8Rng::seed_from_u64(req.seed));
        let mut action = vec![0.0; ad];
        for t in 0..=u64::from(req.steps) {
            planner
                .replan(&mut evaluator, &obs, t)
                .with_context(|| format!("replanning at step {t}"))?;
            if t == u64::from(req.steps) {
                break;
            }
            policy.unscale_action(planner.plan().action(0), &mut action);
            let step = env.step(&action, &mut obs)?;
            if step.terminated || step.truncated {
                bail!("the episode ended at step {}; ask for fewer --steps", t + 1);
            }
        }
        let plan = planner.plan();
        let predicted: Vec<f32> = (0..plan.len())
            .flat_map(|i| plan.next_obs(i).to_vec())
            .collect();
        let actions: Vec<Vec<f32>> = (0..plan.len())
            .map(|i| {
                policy.unscale_action(plan.action(i), &mut action);
                action.clone()
            })
            .collect();
        let decided_at: Vec<u64> = (0..plan.len()).map(|i| plan.decided_at(i)).collect();
        title = format!(
            "{} | policy {} | seed {} | eps coef {} | step {} | plan of {}",
            req.domain,
            policy.manifest.name,
            req.seed,
            req.epsilon_coef,
            req.steps,
            plan.len()
        );
        committed = Some((env.trace(&predicted), actions, decided_at));
    } else if req.steps > 0 {
        let mut rng = ChaCha8Rng::seed_from_u64(req.seed);
        let mut action = vec![0.0; spec.act_dim];
        for t in 0..req.steps {
            for (i, a) in action.iter_mut().enumerate() {
                *a = rng.random_range(spec.action_low[i]..=spec.action_high[i]);
            }
            let step = env.step(&action, &mut obs)?;
            if step.terminated || step.truncated {
                bail!("the episode ended at step {}; ask for fewer --steps", t + 1);
            }
        }
        title = format!("{title} | {} random steps", req.steps);
    }
    let forecast = committed
        .as_ref()
        .map(|(trace, actions, decided_at)| Forecast {
            trace,
            actions,
            decided_at,
            step: u64::from(req.steps),
            action_range: spec.action_range(),
        });
    crate::render::render_scene(&env.scene(), forecast.as_ref(), &title, req.out, req.size)?;
    Ok(committed.map_or(0, |(trace, _, _)| trace.len()))
}
