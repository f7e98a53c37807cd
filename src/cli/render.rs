//! `prac render`: a picture of a domain, optionally with a policy's imagined plan overlaid.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, bail};
use clap::Args;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use prac::domains;
use prac::plan::{Planner, ReplanConfig};
use prac::policy::Evaluator;
use prac::render::Forecast;

#[derive(Args, Debug)]
pub struct RenderArgs {
    domain: String,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[arg(long)]
    out: PathBuf,
    /// Steps played before drawing (the policy's, else random actions).
    #[arg(long, default_value_t = 0)]
    steps: u32,
    /// A bundle whose PrAC plan is drawn (predicted states as dots).
    #[arg(long)]
    policy: Option<PathBuf>,
    /// eps coefficient of the drawn plan's session (eps = C x (V_pi - V_rand)); needs
    /// --policy [default: 0, as prac-sim's].
    #[arg(long, requires = "policy", default_value_t = 0.0)]
    epsilon_coef: f64,
    #[arg(long, default_value_t = 800)]
    width: u32,
    /// Picture height; with --policy the lower third shows the committed actions.
    #[arg(long, default_value_t = 640)]
    height: u32,
}

impl RenderArgs {
    pub fn run(self) -> anyhow::Result<()> {
        let drawn = render(&RenderRequest {
            domain: &self.domain,
            seed: self.seed,
            out: &self.out,
            steps: self.steps,
            policy: self.policy.as_deref(),
            epsilon_coef: self.epsilon_coef,
            size: (self.width.clamp(64, 4096), self.height.clamp(64, 4096)),
        })?;
        println!(
            "wrote {} ({drawn} planned states drawn)",
            self.out.display()
        );
        Ok(())
    }
}

struct RenderRequest<'a> {
    domain: &'a str,
    seed: u64,
    out: &'a Path,
    /// Steps played before drawing: the policy's (PrAC) actions, else uniform random ones.
    steps: u32,
    policy: Option<&'a Path>,
    epsilon_coef: f64,
    size: (u32, u32),
}

/// Renders the request; returns the plan length drawn.
fn render(req: &RenderRequest<'_>) -> anyhow::Result<usize> {
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
        let policy = Arc::new(prac::bundle::load(path)?);
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
    prac::render::render_scene(&env.scene(), forecast.as_ref(), &title, req.out, req.size)?;
    Ok(committed.map_or(0, |(trace, _, _)| trace.len()))
}
