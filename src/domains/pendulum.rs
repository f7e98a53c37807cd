//! gymnasium's Pendulum-v1, exactly: the same dynamics, observation, reward, reset distribution
//! and 200-step limit. No physics engine: the fast domain for tests and CI training.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::{Env, EnvError, EnvSpec, Transition, check_obs_len, clip_action, wrap_angle};

const MAX_SPEED: f64 = 8.0;
const MAX_TORQUE: f32 = 2.0;
const DT: f64 = 0.05;
const G: f64 = 10.0;
const M: f64 = 1.0;
const L: f64 = 1.0;

pub(crate) struct Pendulum {
    spec: EnvSpec,
    theta: f64,
    theta_dot: f64,
    steps: u32,
    over: bool,
}

impl Default for Pendulum {
    fn default() -> Self {
        Self::new()
    }
}

impl Pendulum {
    pub(crate) fn new() -> Pendulum {
        Pendulum {
            spec: EnvSpec {
                name: "pendulum",
                obs_dim: 3,
                act_dim: 1,
                obs_low: vec![-1.0, -1.0, -MAX_SPEED as f32],
                obs_high: vec![1.0, 1.0, MAX_SPEED as f32],
                action_low: vec![-MAX_TORQUE],
                action_high: vec![MAX_TORQUE],
                episode_len: 200,
                control_period: DT,
                engine: "none",
            },
            theta: 0.0,
            theta_dot: 0.0,
            steps: 0,
            over: true,
        }
    }

    fn observe(&self, obs: &mut [f32]) {
        obs[0] = self.theta.cos() as f32;
        obs[1] = self.theta.sin() as f32;
        obs[2] = self.theta_dot as f32;
    }
}

impl Env for Pendulum {
    fn scene(&self) -> super::Scene {
        // Upright is theta = 0: the tip at (sin theta, cos theta).
        let tip = (L * self.theta.sin(), L * self.theta.cos());
        super::Scene {
            shapes: vec![
                (
                    super::Part::Body,
                    super::Shape::Capsule((0.0, 0.0), tip, 0.08),
                ),
                // The pivot, drawn over the rod.
                (super::Part::Detail, super::Shape::Circle((0.0, 0.0), 0.05)),
            ],
            center: (0.0, 0.0),
            width: 2.6,
            height: 2.6,
        }
    }

    fn trace(&self, predicted: &[f32]) -> Vec<(f64, f64)> {
        predicted
            .chunks_exact(3)
            .map(|o| (L * f64::from(o[1]), L * f64::from(o[0])))
            .collect()
    }

    fn spec(&self) -> &EnvSpec {
        &self.spec
    }

    fn reset(&mut self, seed: u64, obs: &mut [f32]) -> Result<(), EnvError> {
        check_obs_len(&self.spec, obs)?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        self.theta = rng.random_range(-std::f64::consts::PI..=std::f64::consts::PI);
        self.theta_dot = rng.random_range(-1.0..=1.0);
        self.steps = 0;
        self.over = false;
        self.observe(obs);
        Ok(())
    }

    fn step(&mut self, action: &[f32], obs: &mut [f32]) -> Result<Transition, EnvError> {
        check_obs_len(&self.spec, obs)?;
        let mut u = [0.0f32];
        clip_action(&self.spec, action, &mut u)?;
        if self.over {
            return Err(EnvError::EpisodeOver);
        }
        let u = f64::from(u[0]);
        let (th, thdot) = (self.theta, self.theta_dot);
        let cost = wrap_angle(th).powi(2) + 0.1 * thdot * thdot + 0.001 * u * u;
        let new_thdot = (thdot + (3.0 * G / (2.0 * L) * th.sin() + 3.0 / (M * L * L) * u) * DT)
            .clamp(-MAX_SPEED, MAX_SPEED);
        self.theta = th + new_thdot * DT;
        self.theta_dot = new_thdot;
        self.steps += 1;
        let truncated = self.steps >= self.spec.episode_len;
        self.over = truncated;
        self.observe(obs);
        Ok(Transition {
            reward: -cost,
            terminated: false,
            truncated,
        })
    }
}
