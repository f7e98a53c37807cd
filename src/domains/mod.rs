//! Environments: the task interface shared by training and the simulator client.
//! Domains: `pendulum` (gymnasium's Pendulum-v1, no physics engine), `lander`
//! (LunarLanderContinuous on rapier2d), the planar walkers `hopper`, `walker` and `cheetah`
//! (rapier2d) and the 3D walkers `ant` and `humanoid` (rapier3d multibodies).

mod episode;
mod features;
mod floor_contacts;
mod lander;
mod pendulum;
mod planar;
mod robots;
pub(crate) mod scene;
mod spatial;
mod walker;
mod walker_base;

pub use episode::EpisodeTotals;
pub use features::{Feature, Features, features};
pub(crate) use lander::Lander;
pub(crate) use pendulum::Pendulum;
pub use planar::{Planar, PlanarBody, PlanarState};
pub use scene::{Part, Scene, Shape};
pub use spatial::{Spatial, SpatialBody};
pub use walker::{Body, Walker};

/// What a domain is: sizes, bounds and episode length.
#[derive(Clone, Debug, PartialEq)]
pub struct EnvSpec {
    pub name: &'static str,
    pub obs_dim: usize,
    pub act_dim: usize,
    /// Documented observation ranges (inclusive); observations never leave them.
    pub(crate) obs_low: Vec<f32>,
    pub(crate) obs_high: Vec<f32>,
    /// Actions are clipped to these bounds.
    pub action_low: Vec<f32>,
    pub action_high: Vec<f32>,
    /// Steps after which an episode is truncated.
    pub episode_len: u32,
    /// Seconds of simulated time per step.
    pub control_period: f64,
    /// "none" for closed-form dynamics, else the physics engine.
    pub engine: &'static str,
}

impl EnvSpec {
    /// The lowest and highest observation bound over the dimensions.
    pub fn obs_range(&self) -> (f32, f32) {
        span(&self.obs_low, &self.obs_high)
    }

    /// The lowest and highest action bound over the dimensions.
    pub fn action_range(&self) -> (f32, f32) {
        span(&self.action_low, &self.action_high)
    }
}

/// The lowest of `low` and the highest of `high`.
fn span(low: &[f32], high: &[f32]) -> (f32, f32) {
    let lo = low.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = high.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    (lo, hi)
}

/// The outcome of one step (the observation is written into the caller's buffer).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Transition {
    pub reward: f64,
    /// The task ended (failure or success); a new episode must start.
    pub terminated: bool,
    /// The episode hit its step limit.
    pub truncated: bool,
}

/// A step the environment refuses; its state is unchanged.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EnvError {
    #[error("action has {got} values; {domain} expects {expected}")]
    ActionLength {
        domain: &'static str,
        got: usize,
        expected: usize,
    },
    #[error("action[{index}] is {value}; every value must be finite")]
    NonFiniteAction { index: usize, value: f32 },
    #[error("the episode is over; call reset first")]
    EpisodeOver,
    #[error("state has {got} {what}; {domain} has {expected}")]
    StateLength {
        domain: &'static str,
        what: &'static str,
        got: usize,
        expected: usize,
    },
    #[error("state {what}[{index}] is {value}; every value must be finite")]
    NonFiniteState {
        what: &'static str,
        index: usize,
        value: f32,
    },
    /// An environment served over dm_env_rpc failed or refused (the message names the server).
    #[error("{0}")]
    Remote(String),
    #[error("observation buffer has {got} values; {domain} writes {expected}")]
    ObservationLength {
        domain: &'static str,
        got: usize,
        expected: usize,
    },
}

/// An episodic control task. `reset` and `step` write the observation into `obs` (obs_dim
/// values), so a built-in domain's step allocates nothing of its own (the physics engine's step
/// inside it does; see `engine`). The same seed and actions give bit-identical
/// observations.
pub trait Env: Send {
    fn spec(&self) -> &EnvSpec;
    fn reset(&mut self, seed: u64, obs: &mut [f32]) -> Result<(), EnvError>;
    fn step(&mut self, action: &[f32], obs: &mut [f32]) -> Result<Transition, EnvError>;
    /// The current state as shapes to draw.
    fn scene(&self) -> Scene;
    /// Points in the scene's coordinates for a sequence of predicted observations following the
    /// current state (an imagined plan): the lander's position, a walker's torso, the pendulum's
    /// tip. Walkers do not observe their x position, so it is integrated from the predicted
    /// forward speed.
    fn trace(&self, predicted: &[f32]) -> Vec<(f64, f64)>;
    /// Where the robot is along the direction its task rewards moving in (metres): the walkers'
    /// x. None for tasks without one (pendulum, lander).
    fn forward_position(&self) -> Option<f64> {
        None
    }
    /// The last step's reward split into named terms that sum to it (PyBullet's `rewards` list
    /// for the walkers); empty for tasks that do not split it.
    fn reward_terms(&self) -> &[(&'static str, f64)] {
        &[]
    }
}

/// How far the robot moved forward since it was at `start` (an earlier `forward_position`).
pub fn forward_distance(start: Option<f64>, env: &dyn Env) -> Option<f64> {
    start.zip(env.forward_position()).map(|(a, b)| b - a)
}

/// An angle wrapped to [-pi, pi).
pub(crate) fn wrap_angle(x: f64) -> f64 {
    (x + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI) - std::f64::consts::PI
}

/// Checks an action and returns it clipped to the bounds (into `clipped`).
pub(crate) fn clip_action(
    spec: &EnvSpec,
    action: &[f32],
    clipped: &mut [f32],
) -> Result<(), EnvError> {
    if action.len() != spec.act_dim {
        return Err(EnvError::ActionLength {
            domain: spec.name,
            got: action.len(),
            expected: spec.act_dim,
        });
    }
    if let Some(index) = action.iter().position(|v| !v.is_finite()) {
        return Err(EnvError::NonFiniteAction {
            index,
            value: action[index],
        });
    }
    for i in 0..action.len() {
        clipped[i] = action[i].clamp(spec.action_low[i], spec.action_high[i]);
    }
    Ok(())
}

thread_local! {
    // Const-initialised without a destructor: reading it never allocates.
    static IN_ENGINE: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs a call into the physics engine that allocates inside rapier 0.36: its step (multibody
/// mass matrices and their LU factors, solver scratch vectors) and the first mutable access to
/// a body after a step (rapier records modified bodies in a list its step takes and drops).
/// Everything of ours around these calls must not allocate; the allocation audit
/// (tests/no_alloc.rs) tells the two apart with [`in_engine`].
pub(crate) fn engine<R>(call: impl FnOnce() -> R) -> R {
    IN_ENGINE.with(|flag| flag.set(true));
    let result = call();
    IN_ENGINE.with(|flag| flag.set(false));
    result
}

/// A body to push forces into: `&mut bodies[handle]` as a call into the engine, whose
/// bookkeeping of modified bodies allocates (see [`engine`]).
pub(crate) fn body_mut<S, H>(bodies: &mut S, handle: H) -> &mut S::Output
where
    S: std::ops::IndexMut<H> + ?Sized,
{
    engine(move || {
        let bodies = bodies;
        &mut bodies[handle]
    })
}

/// Whether this thread is inside a call into the physics engine (see [`engine`]).
pub(crate) fn in_engine() -> bool {
    IN_ENGINE.with(std::cell::Cell::get)
}

pub(crate) fn check_obs_len(spec: &EnvSpec, obs: &[f32]) -> Result<(), EnvError> {
    if obs.len() == spec.obs_dim {
        Ok(())
    } else {
        Err(EnvError::ObservationLength {
            domain: spec.name,
            got: obs.len(),
            expected: spec.obs_dim,
        })
    }
}

/// Every domain's name.
pub const DOMAINS: &[&str] = &[
    "lander", "hopper", "walker", "cheetah", "ant", "humanoid", "pendulum",
];

/// A new environment of the named domain.
pub fn make(name: &str) -> Option<Box<dyn Env>> {
    match name {
        "lander" => Some(Box::new(Lander::new())),
        "hopper" | "walker" | "cheetah" => Planar::named(name).map(|p| Box::new(p) as Box<dyn Env>),
        "ant" => Some(Box::new(Spatial::ant())),
        "humanoid" => Some(Box::new(Spatial::humanoid())),
        "pendulum" => Some(Box::new(Pendulum::new())),
        _ => None,
    }
}

/// Seconds per step of the named domain, None for a domain prac lacks. Each domain is built
/// once, on first asking.
pub fn control_period(name: &str) -> Option<f64> {
    use std::sync::OnceLock;
    static PERIODS: OnceLock<Vec<(&'static str, f64)>> = OnceLock::new();
    let periods = PERIODS.get_or_init(|| {
        DOMAINS
            .iter()
            .filter_map(|&d| make(d).map(|env| (d, env.spec().control_period)))
            .collect()
    });
    periods.iter().find(|(d, _)| *d == name).map(|&(_, p)| p)
}

#[cfg(test)]
mod tests;
