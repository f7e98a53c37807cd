//! LunarLanderContinuous (gym's Box2D task) ported to rapier2d: random chunked terrain with a flat
//! helipad, a hull on two spring legs (revolute joints with motors and limits), a main engine and
//! off-centre side engines with random dispersion, leg contacts, rest detection by hand, and the
//! +-100 terminal rewards. Constants are gym's (lunar_lander.py).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rapier2d::prelude::*;

use super::{Env, EnvError, EnvSpec, Transition, check_obs_len, clip_action};

const FPS: f32 = 50.0;
const SCALE: f32 = 30.0;
const MAIN_ENGINE_POWER: f32 = 13.0;
const SIDE_ENGINE_POWER: f32 = 0.6;
const INITIAL_RANDOM: f32 = 1000.0;
const LANDER_POLY: [(f32, f32); 6] = [
    (-14.0, 17.0),
    (-17.0, 0.0),
    (-17.0, -10.0),
    (17.0, -10.0),
    (17.0, 0.0),
    (14.0, 17.0),
];
const LEG_AWAY: f32 = 20.0;
const LEG_DOWN: f32 = 18.0;
const LEG_W: f32 = 2.0;
const LEG_H: f32 = 8.0;
const LEG_SPRING_TORQUE: f32 = 40.0;
/// Box2D's motor is a rigid velocity constraint capped at the max torque; a stiff damper
/// reproduces it (softer than 100 and the legs fold on landing). The legs are multibody links:
/// rapier's impulse-joint motor between two dynamic bodies gives way under ground contact (the
/// legs fold flat whatever the torque).
const LEG_MOTOR_DAMPING: f32 = 200.0;
const SOLVER_ITERATIONS: usize = 24;
/// The legs' extended joint limit (rad).
const LEG_REST_ANGLE: f32 = 0.4;
const SIDE_ENGINE_HEIGHT: f32 = 14.0;
const SIDE_ENGINE_AWAY: f32 = 12.0;
const W: f32 = 600.0 / SCALE;
const H: f32 = 400.0 / SCALE;
const CHUNKS: usize = 11;
/// Box2D's sleep thresholds, which gym's "not awake" test relies on.
const REST_LINEAR: f32 = 0.01;
const REST_ANGULAR: f32 = 2.0 / 180.0 * std::f32::consts::PI;
const REST_TIME: f32 = 0.5;

pub(crate) struct Lander {
    spec: EnvSpec,
    world: PhysicsWorld,
    ground: ColliderHandle,
    hull: RigidBodyHandle,
    hull_collider: ColliderHandle,
    legs: [(RigidBodyHandle, ColliderHandle); 2],
    helipad_y: f32,
    rng: ChaCha8Rng,
    prev_shaping: Option<f64>,
    game_over: bool,
    rest_time: f32,
    steps: u32,
    over: bool,
    /// The terrain polyline, for drawing.
    pub(crate) terrain: Vec<(f32, f32)>,
}

impl Default for Lander {
    fn default() -> Self {
        Self::new()
    }
}

fn spec() -> EnvSpec {
    use std::f32::consts::PI;
    EnvSpec {
        name: "lander",
        obs_dim: 8,
        act_dim: 2,
        // gymnasium's observation space bounds.
        obs_low: vec![-2.5, -2.5, -10.0, -10.0, -2.0 * PI, -10.0, 0.0, 0.0],
        obs_high: vec![2.5, 2.5, 10.0, 10.0, 2.0 * PI, 10.0, 1.0, 1.0],
        action_low: vec![-1.0; 2],
        action_high: vec![1.0; 2],
        episode_len: 1000,
        control_period: 1.0 / FPS as f64,
        engine: "rapier2d",
    }
}

impl Lander {
    pub(crate) fn new() -> Lander {
        let mut lander = Lander {
            spec: spec(),
            world: PhysicsWorld::default(),
            ground: ColliderHandle::invalid(),
            hull: RigidBodyHandle::invalid(),
            hull_collider: ColliderHandle::invalid(),
            legs: [(RigidBodyHandle::invalid(), ColliderHandle::invalid()); 2],
            helipad_y: H / 4.0,
            rng: ChaCha8Rng::seed_from_u64(0),
            prev_shaping: None,
            game_over: false,
            rest_time: 0.0,
            steps: 0,
            over: true,
            terrain: Vec::new(),
        };
        lander.build(0);
        lander.over = true;
        lander
    }

    /// A fresh world: terrain from the seed, the lander at the top centre.
    fn build(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
        let mut world = PhysicsWorld {
            gravity: Vector::new(0.0, -10.0),
            ..Default::default()
        };
        world.integration_parameters.dt = 1.0 / FPS;
        // Box2D's gym world runs 180 velocity iterations; with rapier's default 4 the legs chatter
        // against their limits and the lander never comes to rest.
        world.integration_parameters.num_solver_iterations = SOLVER_ITERATIONS;

        // Terrain: CHUNKS + 1 random heights, the helipad flattened, then smoothed (gym's
        // indexing, including height[-1] for the first chunk).
        let mut height: Vec<f32> = (0..=CHUNKS)
            .map(|_| self.rng.random_range(0.0..H / 2.0))
            .collect();
        let chunk_x: Vec<f32> = (0..CHUNKS)
            .map(|i| W / (CHUNKS - 1) as f32 * i as f32)
            .collect();
        self.helipad_y = H / 4.0;
        for h in &mut height[CHUNKS / 2 - 2..=CHUNKS / 2 + 2] {
            *h = self.helipad_y;
        }
        let smooth: Vec<f32> = (0..CHUNKS)
            .map(|i| {
                let prev = if i == 0 {
                    height[CHUNKS]
                } else {
                    height[i - 1]
                };
                0.33 * (prev + height[i] + height[i + 1])
            })
            .collect();
        self.terrain = chunk_x
            .iter()
            .copied()
            .zip(smooth.iter().copied())
            .collect();
        let points: Vec<Vector> = self
            .terrain
            .iter()
            .map(|&(x, y)| Vector::new(x, y))
            .collect();
        let (_, ground) = world.insert(
            RigidBodyBuilder::fixed(),
            ColliderBuilder::polyline(points, None).friction(0.1),
        );

        let initial_y = H;
        let hull_points: Vec<Vector> = LANDER_POLY
            .iter()
            .map(|&(x, y)| Vector::new(x / SCALE, y / SCALE))
            .collect();
        let (hull, hull_collider) = world.insert(
            RigidBodyBuilder::dynamic()
                .translation(Vector::new(W / 2.0, initial_y))
                .can_sleep(false),
            ColliderBuilder::convex_polyline(hull_points)
                .expect("the hull polygon is convex")
                .density(5.0)
                .friction(0.1)
                .restitution(0.0),
        );
        let mut legs = [(RigidBodyHandle::invalid(), ColliderHandle::invalid()); 2];
        for (k, i) in [-1.0f32, 1.0].into_iter().enumerate() {
            // Posed at the limit the motor holds them at (gym starts them at +-0.05 rad and lets
            // Box2D snap them there in the first step; a multibody would kick the hull instead).
            let angle = -i * LEG_REST_ANGLE;
            let anchor = Vector::new(i * LEG_AWAY, LEG_DOWN) / SCALE;
            let (sin, cos) = angle.sin_cos();
            let offset = Vector::new(
                cos * anchor.x - sin * anchor.y,
                sin * anchor.x + cos * anchor.y,
            );
            let (leg, leg_collider) = world.insert(
                RigidBodyBuilder::dynamic()
                    .translation(Vector::new(W / 2.0, initial_y) - offset)
                    .rotation(angle)
                    .can_sleep(false),
                ColliderBuilder::cuboid(LEG_W / SCALE, LEG_H / SCALE)
                    .density(1.0)
                    .friction(0.2)
                    .restitution(0.0),
            );
            let limits = if i < 0.0 {
                [LEG_REST_ANGLE, 0.9]
            } else {
                [-0.9, -LEG_REST_ANGLE]
            };
            let joint = RevoluteJointBuilder::new()
                .local_anchor1(Vector::new(0.0, 0.0))
                .local_anchor2(Vector::new(i * LEG_AWAY / SCALE, LEG_DOWN / SCALE))
                .limits(limits)
                .motor_model(MotorModel::ForceBased)
                .motor_velocity(0.3 * i, LEG_MOTOR_DAMPING)
                .motor_max_force(LEG_SPRING_TORQUE)
                .contacts_enabled(false);
            world
                .insert_multibody_joint(hull, leg, joint)
                .expect("a leg hangs off the hull: no loop");
            legs[k] = (leg, leg_collider);
        }
        // gym pushes the lander with a random force during its first step (reset's step).
        let push = Vector::new(
            self.rng.random_range(-INITIAL_RANDOM..INITIAL_RANDOM),
            self.rng.random_range(-INITIAL_RANDOM..INITIAL_RANDOM),
        );
        world.bodies[hull].add_force(push, true);

        self.world = world;
        self.ground = ground;
        self.hull = hull;
        self.hull_collider = hull_collider;
        self.legs = legs;
        self.prev_shaping = None;
        self.game_over = false;
        self.rest_time = 0.0;
        self.steps = 0;
        self.over = false;
    }

    fn touching(&self, collider: ColliderHandle) -> bool {
        self.world
            .contact_pair(collider, self.ground)
            .is_some_and(|pair| pair.has_any_active_contact())
    }

    /// Applies the engines of one (clipped) action for the coming step; returns their powers.
    /// gym's impulses become forces over the step: rapier recomputes a multibody's velocities
    /// from its own state, so an impulse on the hull would be lost.
    fn fire(&mut self, action: [f32; 2]) -> (f32, f32) {
        let hull = &self.world.bodies[self.hull];
        let angle = hull.rotation().angle();
        let pos = hull.translation();
        let tip = Vector::new(angle.sin(), angle.cos());
        let side = Vector::new(-tip.y, tip.x);
        let dispersion = [
            self.rng.random_range(-1.0f32..1.0) / SCALE,
            self.rng.random_range(-1.0f32..1.0) / SCALE,
        ];
        let mut main_power = 0.0;
        if action[0] > 0.0 {
            main_power = (action[0].clamp(0.0, 1.0) + 1.0) * 0.5;
            let ox = tip.x * (4.0 / SCALE + 2.0 * dispersion[0]) + side.x * dispersion[1];
            let oy = -tip.y * (4.0 / SCALE + 2.0 * dispersion[0]) - side.y * dispersion[1];
            let at = Vector::new(pos.x + ox, pos.y + oy);
            let impulse = Vector::new(-ox, -oy) * MAIN_ENGINE_POWER * main_power;
            super::body_mut(&mut self.world.bodies, self.hull).add_force_at_point(
                impulse * FPS,
                at,
                true,
            );
        }
        let mut side_power = 0.0;
        if action[1].abs() > 0.5 {
            let direction = action[1].signum();
            side_power = action[1].abs().clamp(0.5, 1.0);
            let ox = tip.x * dispersion[0]
                + side.x * (3.0 * dispersion[1] + direction * SIDE_ENGINE_AWAY / SCALE);
            let oy = -tip.y * dispersion[0]
                - side.y * (3.0 * dispersion[1] + direction * SIDE_ENGINE_AWAY / SCALE);
            let at = Vector::new(
                pos.x + ox - tip.x * 17.0 / SCALE,
                pos.y + oy + tip.y * SIDE_ENGINE_HEIGHT / SCALE,
            );
            let impulse = Vector::new(-ox, -oy) * SIDE_ENGINE_POWER * side_power;
            super::body_mut(&mut self.world.bodies, self.hull).add_force_at_point(
                impulse * FPS,
                at,
                true,
            );
        }
        (main_power, side_power)
    }

    /// One physics step with the action; writes the observation and returns the reward and
    /// whether the episode ended.
    fn advance(&mut self, action: [f32; 2], obs: &mut [f32]) -> (f64, bool) {
        let (main_power, side_power) = self.fire(action);
        super::engine(|| self.world.step());
        let hull = super::body_mut(&mut self.world.bodies, self.hull);
        hull.reset_forces(false);
        hull.reset_torques(false);
        if self.touching(self.hull_collider) {
            self.game_over = true;
        }
        let hull = &self.world.bodies[self.hull];
        let (pos, vel) = (hull.translation(), hull.linvel());
        let state = [
            (pos.x - W / 2.0) / (W / 2.0),
            (pos.y - (self.helipad_y + LEG_DOWN / SCALE)) / (H / 2.0),
            vel.x * (W / 2.0) / FPS,
            vel.y * (H / 2.0) / FPS,
            hull.rotation().angle(),
            20.0 * hull.angvel() / FPS,
            f32::from(u8::from(self.touching(self.legs[0].1))),
            f32::from(u8::from(self.touching(self.legs[1].1))),
        ];
        obs.copy_from_slice(&state);
        let s = state.map(f64::from);
        let shaping = -100.0 * (s[0] * s[0] + s[1] * s[1]).sqrt()
            - 100.0 * (s[2] * s[2] + s[3] * s[3]).sqrt()
            - 100.0 * s[4].abs()
            + 10.0 * s[6]
            + 10.0 * s[7];
        let mut reward = self.prev_shaping.map_or(0.0, |prev| shaping - prev);
        self.prev_shaping = Some(shaping);
        reward -= f64::from(main_power) * 0.30;
        reward -= f64::from(side_power) * 0.03;

        // Box2D's sleep test, by hand: the whole lander still for half a second.
        let still = [self.hull, self.legs[0].0, self.legs[1].0]
            .iter()
            .all(|&b| {
                let body = &self.world.bodies[b];
                body.linvel().length() < REST_LINEAR && body.angvel().abs() < REST_ANGULAR
            });
        self.rest_time = if still {
            self.rest_time + 1.0 / FPS
        } else {
            0.0
        };
        if self.game_over || state[0].abs() >= 1.0 {
            return (-100.0, true);
        }
        if self.rest_time >= REST_TIME {
            return (100.0, true);
        }
        (reward, false)
    }
}

impl Env for Lander {
    fn scene(&self) -> super::Scene {
        let ground = self.ground;
        let mut shapes = super::scene::world_shapes(&self.world.colliders, |h| h == ground);
        // The helipad flags, at the helipad's ends as in gym.
        let chunk = W / (CHUNKS - 1) as f32;
        for x in [
            chunk * (CHUNKS / 2 - 1) as f32,
            chunk * (CHUNKS / 2 + 1) as f32,
        ] {
            let (x, y) = (f64::from(x), f64::from(self.helipad_y));
            shapes.push((
                super::Part::Detail,
                super::Shape::Polyline(vec![(x, y), (x, y + 50.0 / 30.0)]),
            ));
            shapes.push((
                super::Part::Detail,
                super::Shape::Polygon(vec![
                    (x, y + 50.0 / 30.0),
                    (x, y + 40.0 / 30.0),
                    (x + 25.0 / 30.0, y + 45.0 / 30.0),
                ]),
            ));
        }
        super::Scene {
            shapes,
            // A margin above the viewport: the lander starts at its top edge.
            center: (f64::from(W) / 2.0, f64::from(H) * 0.55),
            width: f64::from(W),
            height: f64::from(H) * 1.1,
        }
    }

    fn trace(&self, predicted: &[f32]) -> Vec<(f64, f64)> {
        predicted
            .chunks_exact(8)
            .map(|o| {
                let x = o[0] * (W / 2.0) + W / 2.0;
                let y = o[1] * (H / 2.0) + self.helipad_y + LEG_DOWN / SCALE;
                (f64::from(x), f64::from(y))
            })
            .collect()
    }

    fn spec(&self) -> &EnvSpec {
        &self.spec
    }

    fn reset(&mut self, seed: u64, obs: &mut [f32]) -> Result<(), EnvError> {
        check_obs_len(&self.spec, obs)?;
        self.build(seed);
        // gym's reset returns the observation after one step with the engines off.
        self.advance([0.0, 0.0], obs);
        Ok(())
    }

    fn step(&mut self, action: &[f32], obs: &mut [f32]) -> Result<Transition, EnvError> {
        check_obs_len(&self.spec, obs)?;
        let mut clipped = [0.0f32; 2];
        clip_action(&self.spec, action, &mut clipped)?;
        if self.over {
            return Err(EnvError::EpisodeOver);
        }
        let (reward, terminated) = self.advance(clipped, obs);
        self.steps += 1;
        let truncated = !terminated && self.steps >= self.spec.episode_len;
        self.over = terminated || truncated;
        Ok(Transition {
            reward,
            terminated,
            truncated,
        })
    }
}
