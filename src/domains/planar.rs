//! Planar PyBullet-style walkers on rapier2d (the x-z plane of the MuJoCo models): capsule links,
//! hinge joints with limits driven by torques, and PyBullet's WalkerBase task interface
//! (observation, reward terms, termination). Hopper and Walker2D so far.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rapier2d::prelude::*;

use super::{Env, EnvError, EnvSpec, Transition, check_obs_len, clip_action};

const CONTROL_PERIOD: f32 = 0.0165;
const SUBSTEPS: usize = 4;
const GRAVITY: f32 = 9.8;
const FLOOR_FRICTION: f32 = 0.64;
/// PyBullet's walk target, far ahead on x.
const TARGET_X: f32 = 1000.0;
const ELECTRICITY_COST: f64 = -2.0;
const STALL_TORQUE_COST: f64 = -0.1;
const JOINTS_AT_LIMIT_COST: f64 = -0.1;
/// MuJoCo's default density; masses are those of the 3D capsules (a 2D shape's area would give
/// other masses).
const DENSITY: f32 = 1000.0;

/// A capsule link, endpoints at rest in world (x, z).
struct LinkDef {
    a: (f32, f32),
    b: (f32, f32),
    radius: f32,
}

impl LinkDef {
    /// The mass of the 3D capsule, as MuJoCo computes it.
    fn mass(&self) -> f32 {
        use std::f32::consts::PI;
        let length = ((self.b.0 - self.a.0).powi(2) + (self.b.1 - self.a.1).powi(2)).sqrt();
        let r = self.radius;
        DENSITY * (PI * r * r * length + 4.0 / 3.0 * PI * r * r * r)
    }
}

/// A hinge between two links at a world anchor (at rest), with limits (rad) and the torque of a
/// unit action (PyBullet's power x gear).
struct JointDef {
    parent: usize,
    child: usize,
    anchor: (f32, f32),
    range: (f32, f32),
    torque: f32,
}

struct RobotDef {
    name: &'static str,
    links: Vec<LinkDef>,
    /// In order: every parent comes before its children.
    joints: Vec<JointDef>,
    feet: Vec<usize>,
    /// Alive while torso z is above this and |pitch| below 1.
    min_z: f32,
}

fn hopper() -> RobotDef {
    use std::f32::consts::PI;
    let deg = PI / 180.0;
    RobotDef {
        name: "hopper",
        links: vec![
            LinkDef {
                a: (0.0, 1.45),
                b: (0.0, 1.05),
                radius: 0.05,
            }, // torso
            LinkDef {
                a: (0.0, 1.05),
                b: (0.0, 0.6),
                radius: 0.05,
            }, // thigh
            LinkDef {
                a: (0.0, 0.6),
                b: (0.0, 0.1),
                radius: 0.04,
            }, // leg
            LinkDef {
                a: (-0.13, 0.1),
                b: (0.26, 0.1),
                radius: 0.06,
            }, // foot
        ],
        joints: vec![
            JointDef {
                parent: 0,
                child: 1,
                anchor: (0.0, 1.05),
                range: (-150.0 * deg, 0.0),
                torque: 75.0,
            },
            JointDef {
                parent: 1,
                child: 2,
                anchor: (0.0, 0.6),
                range: (-150.0 * deg, 0.0),
                torque: 75.0,
            },
            JointDef {
                parent: 2,
                child: 3,
                anchor: (0.0, 0.1),
                range: (-45.0 * deg, 45.0 * deg),
                torque: 75.0,
            },
        ],
        feet: vec![3],
        min_z: 0.8,
    }
}

/// walker2d.xml: a torso on two hopper-like legs (gear 100, feet 30; PyBullet power 0.4).
fn walker() -> RobotDef {
    use std::f32::consts::PI;
    let deg = PI / 180.0;
    let mut links = vec![LinkDef {
        a: (0.0, 1.45),
        b: (0.0, 1.05),
        radius: 0.05,
    }]; // torso
    let mut joints = Vec::new();
    // Right leg (links 1-3), then left leg (links 4-6): the same shape, PyBullet's joint order.
    for first in [1, 4] {
        links.extend([
            LinkDef {
                a: (0.0, 1.05),
                b: (0.0, 0.6),
                radius: 0.05,
            }, // thigh
            LinkDef {
                a: (0.0, 0.6),
                b: (0.0, 0.1),
                radius: 0.04,
            }, // leg
            LinkDef {
                a: (0.0, 0.1),
                b: (0.2, 0.1),
                radius: 0.06,
            }, // foot
        ]);
        joints.extend([
            JointDef {
                parent: 0,
                child: first,
                anchor: (0.0, 1.05),
                range: (-150.0 * deg, 0.0),
                torque: 40.0,
            },
            JointDef {
                parent: first,
                child: first + 1,
                anchor: (0.0, 0.6),
                range: (-150.0 * deg, 0.0),
                torque: 40.0,
            },
            JointDef {
                parent: first + 1,
                child: first + 2,
                anchor: (0.0, 0.1),
                range: (-45.0 * deg, 45.0 * deg),
                torque: 12.0,
            },
        ]);
    }
    RobotDef {
        name: "walker",
        links,
        joints,
        feet: vec![3, 6],
        min_z: 0.8,
    }
}

/// A planar walker (Hopper, Walker2D).
pub struct Planar {
    robot: RobotDef,
    spec: EnvSpec,
    world: PhysicsWorld,
    ground: ColliderHandle,
    bodies: Vec<RigidBodyHandle>,
    colliders: Vec<ColliderHandle>,
    initial_z: f32,
    potential: f64,
    steps: u32,
    over: bool,
    /// Joint positions (normalised) and speeds (x 0.1), PyBullet's `j`.
    joint_state: Vec<f32>,
}

impl Planar {
    pub fn hopper() -> Planar {
        Planar::new(hopper())
    }

    pub fn walker() -> Planar {
        Planar::new(walker())
    }

    fn new(robot: RobotDef) -> Planar {
        let n = robot.joints.len();
        let obs_dim = 8 + 2 * n + robot.feet.len();
        let spec = EnvSpec {
            name: robot.name,
            obs_dim,
            act_dim: n,
            obs_low: vec![-5.0; obs_dim],
            obs_high: vec![5.0; obs_dim],
            action_low: vec![-1.0; n],
            action_high: vec![1.0; n],
            episode_len: 1000,
            control_period: 0.0165,
            engine: "rapier2d",
        };
        let mut env = Planar {
            robot,
            spec,
            world: PhysicsWorld::default(),
            ground: ColliderHandle::invalid(),
            bodies: Vec::new(),
            colliders: Vec::new(),
            initial_z: 0.0,
            potential: 0.0,
            steps: 0,
            over: true,
            joint_state: vec![0.0; 2 * n],
        };
        env.build(&vec![0.0; n]);
        env.over = true;
        env
    }

    /// A fresh world with the robot posed at the given joint angles.
    fn build(&mut self, angles: &[f32]) {
        let mut world = PhysicsWorld {
            gravity: Vector::new(0.0, -GRAVITY),
            ..Default::default()
        };
        world.integration_parameters.dt = CONTROL_PERIOD / SUBSTEPS as f32;
        let robot_group =
            InteractionGroups::new(Group::GROUP_1, Group::GROUP_2, InteractionTestMode::And);
        let ground_group =
            InteractionGroups::new(Group::GROUP_2, Group::ALL, InteractionTestMode::And);
        let (_, ground) = world.insert(
            RigidBodyBuilder::fixed().translation(Vector::new(0.0, -0.5)),
            ColliderBuilder::cuboid(2000.0, 0.5)
                .friction(FLOOR_FRICTION)
                .collision_groups(ground_group),
        );
        // Forward kinematics from the torso: each link turned by its joint about its anchor.
        let centers: Vec<Vector> = self
            .robot
            .links
            .iter()
            .map(|l| Vector::new((l.a.0 + l.b.0) / 2.0, (l.a.1 + l.b.1) / 2.0))
            .collect();
        let mut poses: Vec<(f32, Vector)> = vec![(0.0, centers[0]); self.robot.links.len()];
        for (joint, &q) in self.robot.joints.iter().zip(angles) {
            let (parent_angle, parent_pos) = poses[joint.parent];
            let anchor = Vector::new(joint.anchor.0, joint.anchor.1);
            let anchor_world = parent_pos + rotate(anchor - centers[joint.parent], parent_angle);
            let angle = parent_angle + q;
            poses[joint.child] = (
                angle,
                anchor_world + rotate(centers[joint.child] - anchor, angle),
            );
        }
        let mut bodies = Vec::new();
        let mut colliders = Vec::new();
        for (link, (&(angle, pos), center)) in
            self.robot.links.iter().zip(poses.iter().zip(&centers))
        {
            let a = Vector::new(link.a.0, link.a.1) - *center;
            let b = Vector::new(link.b.0, link.b.1) - *center;
            let (body, collider) = world.insert(
                RigidBodyBuilder::dynamic()
                    .translation(pos)
                    .rotation(angle)
                    .can_sleep(false),
                ColliderBuilder::capsule_from_endpoints(a, b, link.radius)
                    .mass(link.mass())
                    .friction(FLOOR_FRICTION)
                    .collision_groups(robot_group),
            );
            bodies.push(body);
            colliders.push(collider);
        }
        for joint in &self.robot.joints {
            let anchor = Vector::new(joint.anchor.0, joint.anchor.1);
            let hinge = RevoluteJointBuilder::new()
                .local_anchor1(anchor - centers[joint.parent])
                .local_anchor2(anchor - centers[joint.child])
                .limits([joint.range.0, joint.range.1])
                .contacts_enabled(false);
            world.insert_impulse_joint(bodies[joint.parent], bodies[joint.child], hinge);
        }
        self.world = world;
        self.ground = ground;
        self.bodies = bodies;
        self.colliders = colliders;
    }

    /// The robot's mass in kg.
    pub fn total_mass(&self) -> f32 {
        self.bodies
            .iter()
            .map(|&b| self.world.bodies[b].mass())
            .sum()
    }

    fn torso(&self) -> &RigidBody {
        &self.world.bodies[self.bodies[0]]
    }

    /// PyBullet's potential: minus the distance to the target per control period.
    fn potential(&self) -> f64 {
        let x = self.torso().translation().x;
        -f64::from((TARGET_X - x).abs()) / f64::from(CONTROL_PERIOD)
    }

    fn read_joints(&mut self) {
        for (k, joint) in self.robot.joints.iter().enumerate() {
            let parent = &self.world.bodies[self.bodies[joint.parent]];
            let child = &self.world.bodies[self.bodies[joint.child]];
            let q = wrap(child.rotation().angle() - parent.rotation().angle());
            let qdot = child.angvel() - parent.angvel();
            let (lo, hi) = joint.range;
            let mid = 0.5 * (lo + hi);
            self.joint_state[2 * k] = 2.0 * (q - mid) / (hi - lo);
            self.joint_state[2 * k + 1] = 0.1 * qdot;
        }
    }

    /// PyBullet's calc_state, written into obs; returns (torso z, pitch).
    fn observe(&mut self, obs: &mut [f32]) -> (f32, f32) {
        self.read_joints();
        let torso = self.torso();
        let (pos, vel) = (torso.translation(), torso.linvel());
        // The models turn about -y: a counter-clockwise angle in the x-z plane is minus pitch.
        let pitch = -torso.rotation().angle();
        let angle_to_target = (0.0f32).atan2(TARGET_X - pos.x);
        let more = [
            pos.y - self.initial_z,
            angle_to_target.sin(),
            angle_to_target.cos(),
            0.3 * vel.x,
            0.0,
            0.3 * vel.y,
            0.0,
            pitch,
        ];
        obs[..8].copy_from_slice(&more);
        obs[8..8 + self.joint_state.len()].copy_from_slice(&self.joint_state);
        for (k, &foot) in self.robot.feet.iter().enumerate() {
            let touching = self
                .world
                .contact_pair(self.colliders[foot], self.ground)
                .is_some_and(|pair| pair.has_any_active_contact());
            obs[8 + self.joint_state.len() + k] = f32::from(u8::from(touching));
        }
        for v in obs.iter_mut() {
            *v = v.clamp(-5.0, 5.0);
        }
        (pos.y, pitch)
    }
}

fn rotate(v: Vector, angle: f32) -> Vector {
    let (s, c) = angle.sin_cos();
    Vector::new(c * v.x - s * v.y, s * v.x + c * v.y)
}

fn wrap(angle: f32) -> f32 {
    use std::f32::consts::PI;
    (angle + PI).rem_euclid(2.0 * PI) - PI
}

impl Env for Planar {
    fn spec(&self) -> &EnvSpec {
        &self.spec
    }

    fn reset(&mut self, seed: u64, obs: &mut [f32]) -> Result<(), EnvError> {
        check_obs_len(&self.spec, obs)?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let angles: Vec<f32> = (0..self.robot.joints.len())
            .map(|_| rng.random_range(-0.1..0.1))
            .collect();
        self.build(&angles);
        self.initial_z = self.torso().translation().y;
        self.potential = self.potential();
        self.steps = 0;
        self.over = false;
        self.observe(obs);
        Ok(())
    }

    fn step(&mut self, action: &[f32], obs: &mut [f32]) -> Result<Transition, EnvError> {
        check_obs_len(&self.spec, obs)?;
        let mut a = vec![0.0f32; self.spec.act_dim];
        clip_action(&self.spec, action, &mut a)?;
        if self.over {
            return Err(EnvError::EpisodeOver);
        }
        // Joint torques as equal and opposite torques on child and parent: no spurious momentum.
        for (joint, &u) in self.robot.joints.iter().zip(&a) {
            let tau = joint.torque * u;
            self.world.bodies[self.bodies[joint.child]].add_torque(tau, true);
            self.world.bodies[self.bodies[joint.parent]].add_torque(-tau, true);
        }
        for _ in 0..SUBSTEPS {
            self.world.step();
        }
        for &body in &self.bodies {
            self.world.bodies[body].reset_forces(false);
        }
        let (z, pitch) = self.observe(obs);
        let alive = if z > self.robot.min_z && pitch.abs() < 1.0 {
            1.0
        } else {
            -1.0
        };
        let old_potential = self.potential;
        self.potential = self.potential();
        let progress = self.potential - old_potential;
        let n = a.len() as f64;
        let speeds = self.joint_state.iter().skip(1).step_by(2);
        let electricity = ELECTRICITY_COST
            * a.iter()
                .zip(speeds)
                .map(|(u, s)| f64::from((u * s).abs()))
                .sum::<f64>()
            / n
            + STALL_TORQUE_COST * a.iter().map(|u| f64::from(u * u)).sum::<f64>() / n;
        let at_limit = self
            .joint_state
            .iter()
            .step_by(2)
            .filter(|q| q.abs() > 0.99)
            .count() as f64;
        let reward = alive + progress + electricity + JOINTS_AT_LIMIT_COST * at_limit;
        self.steps += 1;
        let terminated = alive < 0.0;
        let truncated = !terminated && self.steps >= self.spec.episode_len;
        self.over = terminated || truncated;
        Ok(Transition {
            reward,
            terminated,
            truncated,
        })
    }
}
