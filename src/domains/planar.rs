//! Planar PyBullet-style walkers on rapier2d (the x-z plane of the MuJoCo models): capsule links,
//! hinge joints with limits driven by torques, and PyBullet's WalkerBase task interface
//! (observation, reward terms, termination): Hopper, Walker2D and HalfCheetah.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rapier2d::prelude::*;

use super::floor_contacts::{self, BoundedShape, FloorContacts};
use super::scene::Scene;
use super::walker::{Body, Walker};
use super::walker_base::{
    self, BULLET_LIMIT_SPRING, Foot, GRAVITY, MORE, TARGET_X, bullet_drag, clip_observation,
};
use super::{Env, EnvError, EnvSpec, check_obs_len, robots, wrap_angle};

pub(super) const FLOOR_FRICTION: f32 = 0.64;
/// The floor's normal, as the floor contacts take it (the plane is x-y, y up).
const UP: nalgebra::Vector3<f32> = nalgebra::Vector3::new(0.0, 1.0, 0.0);

/// A capsule, endpoints at rest in world (x, z), `a` the end Bullet takes as the lowest point on
/// a tie (a `fromto` geom's first). Capsules only collide: the links' masses are
/// [`Inertial`]s.
pub(super) struct Capsule {
    pub(super) a: (f32, f32),
    pub(super) b: (f32, f32),
    pub(super) radius: f32,
}

/// A link's mass as PyBullet 3.2.7 simulates it (getDynamicsInfo; the fixture
/// tests/fixtures/pybullet-bodies.json): its centre at rest in world (x, z), its mass (kg) and its
/// moment of inertia about the hinge axis y (kg m^2). PyBullet's MJCF importer puts the centre at
/// a `fromto` geom's middle but at the body's origin for a geom placed by `pos` (HalfCheetah),
/// and takes the inertia of the geom's bounding box.
pub(super) struct Inertial {
    pub(super) com: (f32, f32),
    pub(super) mass: f32,
    pub(super) inertia: f32,
}

/// A rigid link: its frame's origin, its capsules and its mass, at rest in world (x, z).
pub(super) struct LinkDef {
    pub(super) origin: (f32, f32),
    pub(super) capsules: Vec<Capsule>,
    pub(super) inertial: Inertial,
}

/// A one-capsule link (MuJoCo's `fromto` geoms) whose origin and centre of mass are the
/// capsule's middle.
pub(super) fn link(a: (f32, f32), b: (f32, f32), radius: f32, mass: f32, inertia: f32) -> LinkDef {
    let middle = ((a.0 + b.0) / 2.0, (a.1 + b.1) / 2.0);
    LinkDef {
        origin: middle,
        capsules: vec![Capsule { a, b, radius }],
        inertial: Inertial {
            com: middle,
            mass,
            inertia,
        },
    }
}

/// A capsule given as MuJoCo does with `pos`, `axisangle="0 1 0 angle"` and `size="radius
/// half_length"`, in a body whose origin is `origin`.
pub(super) fn mj_capsule(
    origin: (f32, f32),
    pos: (f32, f32),
    angle: f32,
    half_length: f32,
    radius: f32,
) -> Capsule {
    let center = (origin.0 + pos.0, origin.1 + pos.1);
    // A rotation about +y turns the capsule's z axis to (sin, cos) in (x, z). Bullet's
    // btCapsuleShapeZ offers its +z end first as the lowest point, as `a` is offered.
    let axis = (angle.sin() * half_length, angle.cos() * half_length);
    Capsule {
        a: (center.0 + axis.0, center.1 + axis.1),
        b: (center.0 - axis.0, center.1 - axis.1),
        radius,
    }
}

/// A hinge between two links at a world anchor (at rest), with limits (rad, in the model's
/// convention) and the torque of a unit action (PyBullet's power x gear). `axis` is +1 for a
/// model hinge about -y (a counter-clockwise angle in the x-z plane), -1 for one about +y.
pub(super) struct JointDef {
    pub(super) parent: usize,
    pub(super) child: usize,
    pub(super) anchor: (f32, f32),
    pub(super) range: (f32, f32),
    pub(super) torque: f32,
    pub(super) axis: f32,
}

pub(super) fn hinge(
    parent: usize,
    child: usize,
    anchor: (f32, f32),
    range: (f32, f32),
    torque: f32,
    axis: f32,
) -> JointDef {
    JointDef {
        parent,
        child,
        anchor,
        range,
        torque,
        axis,
    }
}

/// PyBullet's alive bonus: +1 while alive, -1 otherwise.
pub(super) enum Alive {
    /// Torso z above this and |pitch| below 1 (Hopper, Walker2D); the episode ends when not alive.
    Upright { min_z: f32 },
    /// |pitch| below 1 and none of these feet entries touching the ground (HalfCheetah's shins
    /// and thighs); never ends the episode.
    NoContact { forbidden: Vec<usize> },
}

pub(super) struct RobotDef {
    pub(super) name: &'static str,
    pub(super) links: Vec<LinkDef>,
    /// In order: every parent comes before its children.
    pub(super) joints: Vec<JointDef>,
    /// Links whose ground contact is observed (PyBullet's foot_list order).
    pub(super) feet: Vec<Foot>,
    pub(super) alive: Alive,
    /// Where the root's three joints (x and z slides, the pitch hinge) sit at rest, fixed to the
    /// torso: PyBullet's importer makes each a link there, and they count among the parts.
    pub(super) root: (f32, f32),
}

/// A planar walker's state in PyBullet's coordinates: the root's x and z slides and its pitch
/// hinge (the models' `ignorex`, `ignorez` and `ignorey` joints, which pivot where the torso's
/// frame is at rest), their speeds, and every actuated joint's angle and speed (rad, rad/s) in
/// PyBullet's joint order and sign. Read from PyBullet with getJointState, it poses our robot as
/// PyBullet's was ([`Planar::set_state`]). `feet_contact` is PyBullet's `robot.feet_contact`
/// there, the contacts its last step measured, which its next observation shows; empty, none
/// touch (as after a reset).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PlanarState {
    pub(crate) root: [f32; 3],
    pub(crate) root_velocity: [f32; 3],
    pub(crate) joints: Vec<f32>,
    pub(crate) joint_velocities: Vec<f32>,
    #[serde(default)]
    pub(crate) feet_contact: Vec<f32>,
}

/// A planar walker (Hopper, Walker2D, HalfCheetah).
pub type Planar = Walker<PlanarBody>;

/// A planar walker's links in a rapier2d world.
pub struct PlanarBody {
    robot: RobotDef,
    world: PhysicsWorld,
    ground: ColliderHandle,
    bodies: Vec<RigidBodyHandle>,
    /// Per link, its capsules' colliders.
    colliders: Vec<Vec<ColliderHandle>>,
    initial_z: f32,
    /// Joint positions (normalised) and speeds (x 0.1), PyBullet's `j`.
    joint_state: Vec<f32>,
    /// The robot's multibody (any of its joints names it).
    multibody: Option<MultibodyJointHandle>,
    /// The links' contacts with the floor, as Bullet keeps them.
    floor_contacts: FloorContacts,
    /// The observed feet's contacts as the last step ended
    /// ([`walker_base::measure_feet_contact`]).
    feet_contact: Vec<f32>,
    /// Every link's pose before the step's last substep moved it: PyBullet's getLinkState
    /// returns the transforms Bullet cached then, and its observation and reward read them.
    seen_poses: Vec<Pose>,
}

impl Planar {
    pub(crate) fn hopper() -> Planar {
        Planar::of(robots::hopper())
    }

    // Walker2D, the domain "walker"; not a constructor of the skeleton `Walker`.
    #[allow(clippy::self_named_constructors)]
    pub(crate) fn walker() -> Planar {
        Planar::of(robots::walker())
    }

    pub(crate) fn cheetah() -> Planar {
        Planar::of(robots::cheetah())
    }

    /// The planar walker of that domain name.
    pub fn named(name: &str) -> Option<Planar> {
        match name {
            "hopper" => Some(Planar::hopper()),
            "walker" => Some(Planar::walker()),
            "cheetah" => Some(Planar::cheetah()),
            _ => None,
        }
    }

    fn of(robot: RobotDef) -> Planar {
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
        let mut body = PlanarBody {
            robot,
            world: PhysicsWorld::default(),
            ground: ColliderHandle::invalid(),
            bodies: Vec::new(),
            colliders: Vec::new(),
            initial_z: 0.0,
            joint_state: vec![0.0; 2 * n],
            multibody: None,
            floor_contacts: FloorContacts::new((0, 0), UP),
            seen_poses: Vec::new(),
            feet_contact: Vec::new(),
        };
        body.build(&PlanarState {
            joints: vec![0.0; n],
            joint_velocities: vec![0.0; n],
            ..PlanarState::default()
        });
        Walker::new(body, spec, 1.0)
    }

    /// Starts an episode from PyBullet's state (as the reset would, initial height included) and
    /// writes its observation (with the state's feet contacts). A state of the wrong shape or
    /// with a non-finite value changes nothing.
    pub fn set_state(&mut self, state: &PlanarState, obs: &mut [f32]) -> Result<(), EnvError> {
        check_obs_len(self.spec(), obs)?;
        self.body.check_state(state)?;
        self.body.build(state);
        // Where a reset's torso starts (the root does not move at reset).
        self.body.initial_z = self.body.robot.links[0].inertial.com.1;
        self.start(obs);
        Ok(())
    }
}

impl PlanarBody {
    /// A fresh world with the robot in the given state (its lengths checked by the caller).
    fn build(&mut self, state: &PlanarState) {
        let mut world = PhysicsWorld {
            gravity: Vector::new(0.0, -GRAVITY),
            ..Default::default()
        };
        walker_base::set_bullet_solver!(world.integration_parameters);
        let robot_group =
            InteractionGroups::new(Group::GROUP_1, Group::GROUP_2, InteractionTestMode::And);
        let ground_group =
            InteractionGroups::new(Group::GROUP_2, Group::ALL, InteractionTestMode::And);
        let (_, ground) = world.insert(
            RigidBodyBuilder::fixed(),
            ColliderBuilder::halfspace(rapier2d::na::Unit::new_unchecked(Vector::new(0.0, 1.0)))
                .friction(FLOOR_FRICTION)
                .collision_groups(ground_group)
                .active_hooks(ActiveHooks::MODIFY_SOLVER_CONTACTS),
        );
        let mut floor_contacts = FloorContacts::new(ground.into_raw_parts(), UP);
        // The links at rest; the multibody below poses them from the state.
        let origins: Vec<Vector> = self
            .robot
            .links
            .iter()
            .map(|l| Vector::new(l.origin.0, l.origin.1))
            .collect();
        let mut bodies = Vec::new();
        let mut colliders = Vec::new();
        for (link, origin) in self.robot.links.iter().zip(&origins) {
            let inertial = &link.inertial;
            let com = Vector::new(inertial.com.0, inertial.com.1) - *origin;
            let body = world.insert_body(
                RigidBodyBuilder::dynamic()
                    .translation(*origin)
                    .additional_mass_properties(MassProperties::new(
                        com,
                        inertial.mass,
                        inertial.inertia,
                    ))
                    .can_sleep(false),
            );
            let threshold =
                walker_base::link_contact_threshold(&self.robot.feet, bodies.len(), || {
                    self.bounded_threshold(bodies.len())
                });
            let mut handles = Vec::new();
            for capsule in &link.capsules {
                let a = Vector::new(capsule.a.0, capsule.a.1) - *origin;
                let b = Vector::new(capsule.b.0, capsule.b.1) - *origin;
                handles.push(
                    world.insert_collider(
                        ColliderBuilder::capsule_from_endpoints(a, b, capsule.radius)
                            .density(0.0)
                            .friction(FLOOR_FRICTION)
                            .collision_groups(robot_group),
                        Some(body),
                    ),
                );
            }
            for &handle in &handles {
                floor_contacts.add_link_collider(handle.into_raw_parts(), threshold);
            }
            // Now, not at the first step: reset reads the centres of mass.
            world.bodies[body].recompute_mass_properties_from_colliders(&world.colliders);
            bodies.push(body);
            colliders.push(handles);
        }
        // One multibody (reduced coordinates, like PyBullet's btMultiBody) rooted as PyBullet
        // roots it: a fixed base, massless links sliding along x and z, and a hinge at the pivot
        // turning the torso. Bullet integrates these coordinates, and with the Hopper's and
        // Walker's pivot 1.25 m below the torso that differs from integrating a free torso
        // (docs/domains.md, "From matched states").
        let pivot = Vector::new(self.robot.root.0, self.robot.root.1);
        let base = world.insert_body(RigidBodyBuilder::fixed().translation(pivot));
        let massless = || {
            RigidBodyBuilder::dynamic()
                .translation(pivot)
                .can_sleep(false)
        };
        let (slide_x, slide_z) = (world.insert_body(massless()), world.insert_body(massless()));
        let multibody = world
            .insert_multibody_joint(base, slide_x, PrismaticJointBuilder::new(Vector::X))
            .expect("the root is a chain");
        let root_joints = [
            (
                slide_x,
                slide_z,
                GenericJoint::from(PrismaticJointBuilder::new(Vector::Y)),
            ),
            (
                slide_z,
                bodies[0],
                RevoluteJointBuilder::new()
                    .local_anchor2(pivot - origins[0])
                    .into(),
            ),
        ];
        for (parent, child, joint) in root_joints {
            world
                .insert_multibody_joint(parent, child, joint)
                .expect("the root is a chain");
        }
        for joint in &self.robot.joints {
            let anchor = Vector::new(joint.anchor.0, joint.anchor.1);
            // Limits in the plane's counter-clockwise convention.
            let (lo, hi) = joint.range;
            let range = if joint.axis > 0.0 {
                [lo, hi]
            } else {
                [-hi, -lo]
            };
            let hinge = RevoluteJointBuilder::new()
                .local_anchor1(anchor - origins[joint.parent])
                .local_anchor2(anchor - origins[joint.child])
                .limits(range)
                .softness(SpringCoefficients::new(
                    BULLET_LIMIT_SPRING.0,
                    BULLET_LIMIT_SPRING.1,
                ))
                .contacts_enabled(false);
            world
                .insert_multibody_joint(bodies[joint.parent], bodies[joint.child], hinge)
                .expect("the robot is a tree");
        }
        // The state's coordinates, in the plane's counter-clockwise convention, at their
        // degrees of freedom; the reset's joint angles as drawn, inside the limits or not, as
        // PyBullet sets them (the limits only stop them going further out).
        world
            .multibody_joints
            .get_mut(multibody)
            .expect("the root was just inserted")
            .0
            .forward_kinematics(&world.bodies, true);
        let [x, z, pitch] = state.root;
        let [vx, vz, pitch_rate] = state.root_velocity;
        let mut coordinates = vec![
            (slide_x, x, vx),
            (slide_z, z, vz),
            (bodies[0], -pitch, -pitch_rate),
        ];
        for (k, joint) in self.robot.joints.iter().enumerate() {
            coordinates.push((
                bodies[joint.child],
                joint.axis * state.joints[k],
                joint.axis * state.joint_velocities[k],
            ));
        }
        let dofs: Vec<usize> = coordinates
            .iter()
            .map(|&(body, _, _)| {
                let link = world
                    .multibody_joints
                    .rigid_body_link(body)
                    .expect("a link");
                let (multibody, _) = world.multibody_joints.get(multibody).expect("inserted");
                multibody.link(link.id).expect("a link").assembly_id()
            })
            .collect();
        let (multibody_ref, _) = world
            .multibody_joints
            .get_mut(multibody)
            .expect("the root was just inserted");
        // No joint damping: PyBullet has none. Coriolis forces explicit, as Bullet's.
        multibody_ref.damping_mut().fill(0.0);
        multibody_ref.set_implicit_coriolis(false);
        let mut displacement = vec![0.0; multibody_ref.ndofs()];
        for (&dof, &(_, value, _)) in dofs.iter().zip(&coordinates) {
            displacement[dof] = value;
        }
        multibody_ref.apply_displacements(&displacement);
        multibody_ref.forward_kinematics(&world.bodies, false);
        multibody_ref.update_rigid_bodies(&mut world.bodies, true);
        let mut speeds = multibody_ref.generalized_velocity_mut();
        for (&dof, &(_, _, speed)) in dofs.iter().zip(&coordinates) {
            speeds[dof] = speed;
        }
        self.world = world;
        self.ground = ground;
        self.bodies = bodies;
        self.colliders = colliders;
        self.multibody = Some(multibody);
        self.floor_contacts = floor_contacts;
        self.sync_link_velocities();
        self.remember_link_poses();
        self.feet_contact = vec![0.0; self.robot.feet.len()];
        if !state.feet_contact.is_empty() {
            self.feet_contact.copy_from_slice(&state.feet_contact);
        }
    }

    /// Gives every link's body the multibody's current speeds ([`walker_base::link_velocity`]).
    fn sync_link_velocities(&mut self) {
        let set = |body: &mut RigidBody, v: [f32; 3]| {
            body.set_linvel(Vector::new(v[0], v[1]), false);
            body.set_angvel(v[2], false);
        };
        walker_base::sync_link_velocities!(self.world, self.multibody, 3, set);
    }

    /// The observed feet.
    #[cfg(test)]
    pub(super) fn feet(&self) -> &[Foot] {
        &self.robot.feet
    }

    /// Link `k`'s contact breaking threshold from its capsules as Bullet bounds them.
    pub(super) fn bounded_threshold(&self, k: usize) -> f32 {
        let link = &self.robot.links[k];
        let com = link.inertial.com;
        let at = |(x, z): (f32, f32)| nalgebra::Vector3::new(x - com.0, 0.0, z - com.1);
        let shapes: Vec<BoundedShape> = link
            .capsules
            .iter()
            .map(|c| BoundedShape::Capsule(at(c.a), at(c.b), c.radius))
            .collect();
        floor_contacts::contact_breaking_threshold(&shapes)
    }

    /// One Bullet substep under `torques`: forces, this substep's limit springs, the physics
    /// step, and the links' speeds from the multibody's.
    fn bullet_substep(&mut self, torques: &[f32]) {
        self.apply_forces(torques);
        walker_base::set_bullet_limit_springs!(self.world, self.multibody, |_| 1.0);
        self.floor_contacts.next_substep();
        super::engine(|| self.world.step_with_events(&self.floor_contacts, &()));
        self.sync_link_velocities();
    }

    /// Checks a state's shape and values against this robot.
    fn check_state(&self, state: &PlanarState) -> Result<(), EnvError> {
        let n = self.robot.joints.len();
        let feet = match state.feet_contact.len() {
            0 => 0,
            _ => self.robot.feet.len(),
        };
        let fields: [(&'static str, &[f32], usize); 5] = [
            ("root values", &state.root, 3),
            ("root speeds", &state.root_velocity, 3),
            ("joint angles", &state.joints, n),
            ("joint speeds", &state.joint_velocities, n),
            ("feet contacts", &state.feet_contact, feet),
        ];
        for (what, values, expected) in fields {
            if values.len() != expected {
                return Err(EnvError::StateLength {
                    domain: self.robot.name,
                    what,
                    got: values.len(),
                    expected,
                });
            }
            if let Some(index) = values.iter().position(|v| !v.is_finite()) {
                return Err(EnvError::NonFiniteState {
                    what,
                    index,
                    value: values[index],
                });
            }
        }
        Ok(())
    }

    fn torso(&self) -> &RigidBody {
        &self.world.bodies[self.bodies[0]]
    }

    /// PyBullet's body x, which the progress reward measures: the mean x of the robot's parts,
    /// which are every link's centre of mass, the link PyBullet's importer makes at each hinge and
    /// at each of the root's three joints, and the floor (at x = 0), at their `seen_poses`.
    fn body_x(&self) -> f32 {
        let at = |link: usize, rest: (f32, f32)| {
            let origin = self.robot.links[link].origin;
            let local = Vector::new(rest.0 - origin.0, rest.1 - origin.1);
            self.seen_poses[link].transform_point(local).x
        };
        let mut sum = 3.0 * at(0, self.robot.root);
        for (k, link) in self.robot.links.iter().enumerate() {
            sum += at(k, link.inertial.com);
        }
        for joint in &self.robot.joints {
            sum += at(joint.child, joint.anchor);
        }
        let parts = 3 + self.robot.links.len() + self.robot.joints.len() + 1;
        sum / parts as f32
    }

    fn read_joints(&mut self) {
        for (k, joint) in self.robot.joints.iter().enumerate() {
            let parent = &self.world.bodies[self.bodies[joint.parent]];
            let child = &self.world.bodies[self.bodies[joint.child]];
            let q = joint.axis
                * wrap_angle(f64::from(
                    child.rotation().angle() - parent.rotation().angle(),
                )) as f32;
            let qdot = joint.axis * (child.angvel() - parent.angvel());
            self.joint_state[2 * k..2 * k + 2].copy_from_slice(&walker_base::joint_state(
                q,
                qdot,
                joint.range,
            ));
        }
    }

    /// Joint torques as equal and opposite torques on child and parent (no spurious momentum),
    /// and Bullet's default multibody drag on every link.
    fn apply_forces(&mut self, action: &[f32]) {
        for &body in &self.bodies {
            let body = super::body_mut(&mut self.world.bodies, body);
            body.reset_forces(false);
            body.reset_torques(false);
            let (v, w) = (body.linvel(), body.angvel());
            let inertia = body.mass_properties().local_mprops.principal_inertia();
            let drag = -body.mass() * v * bullet_drag(v.length());
            let spin_drag = -inertia * w * bullet_drag(w.abs());
            body.add_force(drag, true);
            body.add_torque(spin_drag, true);
        }
        for (joint, &u) in self.robot.joints.iter().zip(action) {
            let tau = joint.axis * joint.torque * u;
            super::body_mut(&mut self.world.bodies, self.bodies[joint.child]).add_torque(tau, true);
            super::body_mut(&mut self.world.bodies, self.bodies[joint.parent])
                .add_torque(-tau, true);
        }
    }

    /// PyBullet's alive bonus (+1, or -1 once fallen) at torso height `z`, `pitch` and the
    /// observed feet `contacts`, and whether falling ends the episode.
    fn alive_bonus(&self, z: f32, pitch: f32, contacts: &[f32]) -> (f64, bool) {
        let (alive, ends) = match &self.robot.alive {
            Alive::Upright { min_z } => (*min_z < z && pitch.abs() < 1.0, true),
            Alive::NoContact { forbidden } => (
                pitch.abs() < 1.0 && forbidden.iter().all(|&k| contacts[k] == 0.0),
                false,
            ),
        };
        (if alive { 1.0 } else { -1.0 }, ends)
    }
}

impl Body for PlanarBody {
    fn reset(&mut self, rng: &mut ChaCha8Rng) {
        let n = self.robot.joints.len();
        self.build(&PlanarState {
            joints: (0..n).map(|_| rng.random_range(-0.1..0.1)).collect(),
            joint_velocities: vec![0.0; n],
            ..PlanarState::default()
        });
        self.initial_z = self.robot.links[0].inertial.com.1;
    }

    fn substep(&mut self, action: &[f32]) {
        self.bullet_substep(action);
    }

    /// Keeps the links' current poses as those the observation and reward read
    /// (`seen_poses`).
    fn remember_link_poses(&mut self) {
        self.seen_poses.clear();
        let bodies = &self.world.bodies;
        self.seen_poses
            .extend(self.bodies.iter().map(|&b| *bodies[b].position()));
    }

    /// PyBullet's calc_state, written into obs: the joints as they are, the torso at its
    /// `seen_poses` one, the feet contacts of the step before; returns that (torso z, pitch),
    /// which the alive bonus reads.
    fn observe(&mut self, obs: &mut [f32]) -> (f32, f32) {
        self.read_joints();
        let torso = self.torso();
        let seen = &self.seen_poses[0];
        let pos = seen.transform_point(torso.mass_properties().local_mprops.local_com);
        // Bullet turns a link's speed in its own frame, current, by the cached rotation.
        let vel = seen
            .rotation
            .transform_vector(torso.rotation().inverse_transform_vector(torso.linvel()));
        // The models turn about -y: a counter-clockwise angle in the x-z plane is minus pitch.
        let pitch = -seen.rotation.angle();
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
        obs[..MORE].copy_from_slice(&more);
        obs[MORE..MORE + self.joint_state.len()].copy_from_slice(&self.joint_state);
        obs[MORE + self.joint_state.len()..].copy_from_slice(&self.feet_contact);
        clip_observation(obs);
        (pos.y, pitch)
    }

    fn alive(&self, z: f32, pitch: f32) -> (f64, bool) {
        self.alive_bonus(z, pitch, &self.feet_contact)
    }

    /// PyBullet's potential: minus the distance to the target per control period.
    fn potential(&self) -> f64 {
        walker_base::potential((TARGET_X - self.body_x()).abs())
    }

    fn measure_feet_contact(&mut self) {
        walker_base::measure_feet_contact!(self);
    }

    fn joint_state(&self) -> &[f32] {
        &self.joint_state
    }

    fn forward_x(&self) -> f32 {
        self.torso().center_of_mass().x
    }

    /// The robot's mass in kg.
    fn total_mass(&self) -> f32 {
        self.bodies
            .iter()
            .map(|&b| self.world.bodies[b].mass())
            .sum()
    }

    fn scene(&self) -> Scene {
        let ground = self.ground;
        let shapes = super::scene::world_shapes(&self.world.colliders, |h| h == ground);
        let x = self.torso().center_of_mass().x;
        Scene {
            shapes,
            center: (f64::from(x), 1.0),
            width: 4.0,
            height: 2.4,
        }
    }

    fn trace(&self, predicted: &[f32], spec: &EnvSpec) -> Vec<(f64, f64)> {
        let dt = spec.control_period as f32;
        let mut x = self.torso().center_of_mass().x;
        predicted
            .chunks_exact(spec.obs_dim)
            .map(|o| {
                // "more" holds 0.3 vx; the speed after a step times the period approximates it.
                x += o[3] / 0.3 * dt;
                (f64::from(x), f64::from(o[0] + self.initial_z))
            })
            .collect()
    }
}

#[cfg(test)]
impl PlanarBody {
    /// The robot's mass (kg) and centre of mass (world x, 0, z; m).
    pub(super) fn mass_and_centre_for_test(&self) -> (f32, [f32; 3]) {
        let (mut mass, mut moment) = (0.0, Vector::ZERO);
        for &h in &self.bodies {
            let body = &self.world.bodies[h];
            mass += body.mass();
            moment += body.center_of_mass() * body.mass();
        }
        let c = moment / mass;
        (mass, [c.x, 0.0, c.y])
    }

    /// Per actuated joint in PyBullet's motor order: its limits (rad, the model's convention) and
    /// unit-action torque.
    pub(super) fn joints_for_test(&self) -> Vec<((f32, f32), f32)> {
        let joints = &self.robot.joints;
        joints.iter().map(|j| (j.range, j.torque)).collect()
    }

    /// What the reward reads at the current state: the parts' mean x, the alive bonus with the
    /// given feet contacts, and the effort costs of `action`.
    pub(super) fn scores_for_test(&self, contacts: &[f32], action: &[f32]) -> [f64; 4] {
        let torso = self.torso();
        let (z, pitch) = (torso.center_of_mass().y, -torso.rotation().angle());
        let (alive, _) = self.alive_bonus(z, pitch, contacts);
        let (power, at_limit) = walker_base::effort_cost_terms(action, &self.joint_state, 1.0);
        [f64::from(self.body_x()), alive, power, at_limit]
    }

    /// The feet contacts the last step measured (the next observation shows them).
    pub(super) fn feet_contact_for_test(&self) -> &[f32] {
        &self.feet_contact
    }

    /// How many parts PyBullet's body x averages over (the floor included).
    pub(super) fn parts_for_test(&self) -> usize {
        3 + self.robot.links.len() + self.robot.joints.len() + 1
    }

    /// Takes the floor away and lets the robot fall for `seconds` without torques; returns the
    /// torso's vertical speed.
    pub(super) fn drop_for_test(&mut self, seconds: f32) -> f32 {
        self.world.remove_collider(self.ground);
        let zero = vec![0.0; self.robot.joints.len()];
        for _ in 0..(seconds / walker_base::CONTROL_PERIOD) as usize * walker_base::BULLET_SUBSTEPS
        {
            self.bullet_substep(&zero);
        }
        self.torso().linvel().y
    }
}
