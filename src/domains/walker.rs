//! The walker skeleton, the same in 2D and 3D: PyBullet's WalkerBase episode (the action check,
//! the reward, the end) around a body that does the physics. A step is Bullet's four substeps,
//! with the links' poses remembered before the last one (PyBullet's observation reads those),
//! then the observation, the alive bonus, the potential, and the feet contacts for the next
//! observation, in PyBullet's order.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::scene::Scene;
use super::walker_base::{BULLET_SUBSTEPS, WalkerEpisode};
use super::{Env, EnvError, EnvSpec, Transition, check_obs_len};

/// A walker's physics: the robot's links in a world (rapier2d or rapier3d).
pub trait Body: Send {
    /// Builds a fresh world with the robot posed as PyBullet's reset draws it from `rng`.
    fn reset(&mut self, rng: &mut ChaCha8Rng);
    /// One Bullet substep under the joint torques of the clipped action.
    fn substep(&mut self, action: &[f32]);
    /// Keeps the links' current poses: those PyBullet's observation and reward read.
    fn remember_link_poses(&mut self);
    /// PyBullet's calc_state, written into `obs`; returns the (torso z, pitch) it saw.
    fn observe(&mut self, obs: &mut [f32]) -> (f32, f32);
    /// PyBullet's alive bonus at that torso z and pitch, and whether falling ends the episode.
    fn alive(&self, z: f32, pitch: f32) -> (f64, bool);
    /// PyBullet's potential: minus the distance to the target per control period.
    fn potential(&self) -> f64;
    /// Measures which observed feet touch the floor now; the next observation shows them.
    fn measure_feet_contact(&mut self);
    /// The joints as the last observation read them (PyBullet's `j`).
    fn joint_state(&self) -> &[f32];
    /// The torso's centre of mass x.
    fn forward_x(&self) -> f32;
    /// The robot's mass in kg.
    fn total_mass(&self) -> f32;
    /// The picture of the world now.
    fn scene(&self) -> Scene;
    /// The path of the torso through the predicted observations.
    fn trace(&self, predicted: &[f32], spec: &EnvSpec) -> Vec<(f64, f64)>;
}

/// A walker domain: its body and PyBullet's task around it.
pub struct Walker<B> {
    pub(super) body: B,
    spec: EnvSpec,
    episode: WalkerEpisode,
}

impl<B: Body> Walker<B> {
    /// A walker whose electricity and stall costs are scaled by `cost_scale`.
    pub(super) fn new(body: B, spec: EnvSpec, cost_scale: f64) -> Walker<B> {
        let episode = WalkerEpisode::new(&spec, cost_scale);
        Walker {
            body,
            spec,
            episode,
        }
    }

    /// Starts an episode from the body as it stands and writes its first observation.
    pub(super) fn start(&mut self, obs: &mut [f32]) {
        self.episode.start(self.body.potential());
        self.body.observe(obs);
    }

    /// The robot's mass in kg.
    pub fn total_mass(&self) -> f32 {
        self.body.total_mass()
    }
}

impl<B: Body> Env for Walker<B> {
    fn spec(&self) -> &EnvSpec {
        &self.spec
    }

    fn reset(&mut self, seed: u64, obs: &mut [f32]) -> Result<(), EnvError> {
        check_obs_len(&self.spec, obs)?;
        self.body.reset(&mut ChaCha8Rng::seed_from_u64(seed));
        self.start(obs);
        Ok(())
    }

    fn step(&mut self, action: &[f32], obs: &mut [f32]) -> Result<Transition, EnvError> {
        check_obs_len(&self.spec, obs)?;
        let a = self.episode.begin_step(&self.spec, action)?;
        for _ in 1..BULLET_SUBSTEPS {
            self.body.substep(&a);
        }
        // What the observation reads: the poses the last substep starts from.
        self.body.remember_link_poses();
        self.body.substep(&a);
        let (z, pitch) = self.body.observe(obs);
        let (alive, ends) = self.body.alive(z, pitch);
        let potential = self.body.potential();
        self.body.measure_feet_contact();
        Ok(self
            .episode
            .finish_step(a, alive, ends, potential, self.body.joint_state()))
    }

    fn scene(&self) -> Scene {
        self.body.scene()
    }

    fn trace(&self, predicted: &[f32]) -> Vec<(f64, f64)> {
        self.body.trace(predicted, &self.spec)
    }

    /// The torso's x (the progress reward measures the mean of the robot's parts).
    fn forward_position(&self) -> Option<f64> {
        Some(f64::from(self.body.forward_x()))
    }

    fn reward_terms(&self) -> &[(&'static str, f64)] {
        self.episode.reward_terms()
    }
}
