//! 3D PyBullet walkers on rapier3d: Ant and Humanoid. Each robot is one multibody (reduced
//! coordinates, so joints never drift apart) whose links follow the MJCF models PyBullet loads
//! (ant.xml, humanoid_symmetric.xml), with PyBullet's WalkerBase task interface: observation,
//! reward terms and termination.
//!
//! A MuJoCo body with several hinges (the Humanoid's hips, abdomen and shoulders) becomes a chain
//! of one-hinge links, as PyBullet's MJCF importer does; the links in between carry no shape.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rapier3d::glamx::EulerRot;
use rapier3d::prelude::*;

use super::floor_contacts::{self, BoundedShape, FloorContacts};
use super::scene::{Scene, camera};
use super::walker::{Body, Walker};
use super::walker_base::{
    self, BULLET_LIMIT_SPRING, CONTROL_PERIOD, Foot, GRAVITY, MORE, TARGET_X, bullet_drag,
    clip_observation,
};
use super::{EnvSpec, robots, wrap_angle};

/// PyBullet's stadium floor friction (0.8), multiplied by the geom's as Bullet combines them.
pub(super) const FLOOR_FRICTION: f32 = 0.8;
/// Links that only chain several hinges of one MuJoCo body: no shape, and a token mass (massless
/// in PyBullet) so that rapier's multibody gives the link a well-defined inertia; 10 g slowed
/// the Humanoid's hips and abdomen by 0.3-0.5% against PyBullet's under random torques.
const CHAIN_LINK_MASS: f32 = 0.0001;
/// A hinge's free coordinate in rapier's multibody: its angle about its local x axis.
const HINGE_ANGLE: usize = 3;
/// The floor's normal, as the floor contacts take it.
const UP: nalgebra::Vector3<f32> = nalgebra::Vector3::new(0.0, 0.0, 1.0);

#[derive(Clone, Copy)]
pub(super) enum Geom {
    /// Endpoints and radius, in world coordinates at rest.
    Capsule(Vector, Vector, f32),
    /// Centre and radius, in world coordinates at rest.
    Sphere(Vector, f32),
}

/// A mass as PyBullet 3.2.7 simulates it (getDynamicsInfo; the fixture
/// tests/fixtures/pybullet-bodies.json): its centre at rest in world coordinates, its mass (kg)
/// and its principal moments of inertia about the world axes at rest (kg m^2). PyBullet's MJCF
/// importer puts a body's centre at its last geom's middle when that geom is a `fromto` one and
/// at the body's origin when it is placed by `pos`, and takes inertias from the geoms' bounding
/// boxes; several of its links fixed together (the Ant's torso and legs, the Humanoid's shin and
/// foot) are one link here, with their masses summed.
pub(super) struct Inertial {
    pub(super) com: Vector,
    pub(super) mass: f32,
    pub(super) inertia: Vector,
}

pub(super) fn inertial(com: Vector, mass: f32, inertia: (f32, f32, f32)) -> Inertial {
    Inertial {
        com,
        mass,
        inertia: v(inertia.0, inertia.1, inertia.2),
    }
}

/// One link: at rest its frame sits at `origin` (its hinge's anchor), unrotated.
pub(super) struct LinkDef {
    /// None for the root (the torso).
    pub(super) parent: Option<usize>,
    pub(super) origin: Vector,
    /// The hinge axis (unit, the same in world, parent and link frames at rest); unused for the
    /// root.
    pub(super) axis: Vector,
    /// Limits in radians and the torque of a unit action.
    pub(super) range: (f32, f32),
    pub(super) torque: f32,
    /// The length of the model's hinge axis, which Bullet does not normalise (1 for the root).
    pub(super) axis_length: f32,
    /// Shapes, which only collide: the mass is `inertials`.
    pub(super) geoms: Vec<Geom>,
    /// None for a link that only chains hinges of one MuJoCo body.
    pub(super) inertials: Vec<Inertial>,
}

impl LinkDef {
    pub(super) fn with_mass(mut self, inertials: Vec<Inertial>) -> LinkDef {
        self.inertials = inertials;
        self
    }
}

/// PyBullet's alive bonus: `bonus` while the torso is above `min_z`, else -1 and the episode ends.
pub(super) struct Alive {
    pub(super) min_z: f32,
    pub(super) bonus: f64,
}

pub(super) struct RobotDef {
    pub(super) name: &'static str,
    /// Root first; every parent before its children. Links 1.. are the actuated joints in
    /// PyBullet's order.
    pub(super) links: Vec<LinkDef>,
    /// Per observed foot (PyBullet's foot_list order): the link whose shapes count as that foot.
    pub(super) feet: Vec<Foot>,
    pub(super) alive: Alive,
    /// PyBullet's initial_z: None takes the torso's height after reset.
    pub(super) initial_z: Option<f32>,
    /// Multiplies PyBullet's electricity and stall costs (Humanoid: 4.25).
    pub(super) cost_scale: f64,
    /// Bullet's combined friction of the robot's geoms on the floor.
    pub(super) friction: f32,
    /// The links collide with each other, except with their ancestors (PyBullet's
    /// URDF_USE_SELF_COLLISION_EXCLUDE_ALL_PARENTS; only the Humanoid's geoms have conaffinity).
    pub(super) self_collision: bool,
}

pub(super) fn v(x: f32, y: f32, z: f32) -> Vector {
    Vector::new(x, y, z)
}

/// A hinge link; `geoms` are given relative to `origin` (the MJCF body's frame when the joint
/// sits at the body's origin).
#[allow(clippy::too_many_arguments)]
pub(super) fn hinge(
    parent: usize,
    origin: Vector,
    axis: Vector,
    range_deg: (f32, f32),
    torque: f32,
    geoms: Vec<Geom>,
) -> LinkDef {
    let deg = std::f32::consts::PI / 180.0;
    LinkDef {
        parent: Some(parent),
        origin,
        axis: axis.normalize(),
        axis_length: axis.length(),
        range: (range_deg.0 * deg, range_deg.1 * deg),
        torque,
        geoms,
        inertials: Vec::new(),
    }
}

pub(super) fn capsule(a: Vector, b: Vector, r: f32) -> Geom {
    Geom::Capsule(a, b, r)
}

/// A 3D walker (Ant, Humanoid).
pub type Spatial = Walker<SpatialBody>;

/// A 3D walker's links in a rapier3d world.
pub struct SpatialBody {
    robot: RobotDef,
    world: PhysicsWorld,
    ground: ColliderHandle,
    bodies: Vec<RigidBodyHandle>,
    /// Per link, its colliders.
    colliders: Vec<Vec<ColliderHandle>>,
    initial_z: f32,
    /// Joint positions (normalised) and speeds (x 0.1), PyBullet's `j`.
    joint_state: Vec<f32>,
    /// btMultiBody's drag on the links; off only for the free-floating momentum test.
    drag: bool,
    /// The robot's multibody (any of its joints names it).
    multibody: Option<MultibodyJointHandle>,
    /// The links' contacts with the floor, as Bullet keeps them.
    floor_contacts: FloorContacts,
    /// Whether some hinge's model axis is longer than 1 ([`Spatial::turn_joints_as_bullet`]).
    long_axes: bool,
    /// Per link, its joint's angle before the substep, and the multibody's displacement
    /// (reused: a step allocates nothing).
    angles_before: Vec<f32>,
    displacement: Vec<f32>,
    /// The observed feet's contacts as the last step ended
    /// ([`walker_base::measure_feet_contact`]).
    feet_contact: Vec<f32>,
    /// Every link's pose before the step's last substep moved it: PyBullet's getLinkState
    /// returns the transforms Bullet cached then, and its body x and y (the progress reward)
    /// read them for every link but the torso, which is its base and current.
    seen_poses: Vec<Pose>,
}

impl Spatial {
    pub(crate) fn ant() -> Spatial {
        Spatial::of(robots::ant())
    }

    pub(crate) fn humanoid() -> Spatial {
        Spatial::of(robots::humanoid())
    }

    fn of(robot: RobotDef) -> Spatial {
        let n = robot.links.len() - 1;
        let obs_dim = MORE + 2 * n + robot.feet.len();
        let spec = EnvSpec {
            name: robot.name,
            obs_dim,
            act_dim: n,
            obs_low: vec![-5.0; obs_dim],
            obs_high: vec![5.0; obs_dim],
            action_low: vec![-1.0; n],
            action_high: vec![1.0; n],
            episode_len: 1000,
            control_period: f64::from(CONTROL_PERIOD),
            engine: "rapier3d",
        };
        let cost_scale = robot.cost_scale;
        let mut body = SpatialBody {
            robot,
            world: PhysicsWorld::default(),
            ground: ColliderHandle::invalid(),
            bodies: Vec::new(),
            colliders: Vec::new(),
            initial_z: 0.0,
            joint_state: vec![0.0; 2 * n],
            drag: true,
            multibody: None,
            floor_contacts: FloorContacts::new((0, 0), UP),
            long_axes: false,
            angles_before: Vec::new(),
            displacement: Vec::new(),
            seen_poses: Vec::new(),
            feet_contact: Vec::new(),
        };
        body.build(&vec![0.0; n]);
        Walker::new(body, spec, cost_scale)
    }
}

impl SpatialBody {
    /// A fresh world with the robot posed at the given joint angles.
    fn build(&mut self, angles: &[f32]) {
        let mut world = PhysicsWorld {
            gravity: v(0.0, 0.0, -GRAVITY),
            ..Default::default()
        };
        walker_base::set_bullet_solver!(world.integration_parameters);
        // The floor is the last group; link k is group k and collides with the floor and, with
        // self-collision, with every link but itself and its ancestors.
        let floor = Group::GROUP_32;
        let ground_group = InteractionGroups::new(floor, Group::ALL, InteractionTestMode::And);
        let link_groups: Vec<InteractionGroups> = (0..self.robot.links.len())
            .map(|k| {
                let mut touches = floor;
                if self.robot.self_collision {
                    let mut excluded = Group::from_bits_truncate(1 << k);
                    let mut ancestor = self.robot.links[k].parent;
                    while let Some(a) = ancestor {
                        excluded |= Group::from_bits_truncate(1 << a);
                        ancestor = self.robot.links[a].parent;
                    }
                    touches |= Group::ALL.difference(floor | excluded);
                }
                InteractionGroups::new(
                    Group::from_bits_truncate(1 << k),
                    touches,
                    InteractionTestMode::And,
                )
            })
            .collect();
        let (_, ground) = world.insert(
            RigidBodyBuilder::fixed(),
            ColliderBuilder::halfspace(rapier3d::na::Unit::new_unchecked(v(0.0, 0.0, 1.0)))
                .friction(self.robot.friction)
                .collision_groups(ground_group)
                .active_hooks(ActiveHooks::MODIFY_SOLVER_CONTACTS),
        );
        let mut floor_contacts = FloorContacts::new(ground.into_raw_parts(), UP);
        let mut bodies = Vec::new();
        let mut colliders = Vec::new();
        for (k, (link, &groups)) in self.robot.links.iter().zip(&link_groups).enumerate() {
            let threshold = walker_base::link_contact_threshold(&self.robot.feet, k, || {
                self.bounded_threshold(k)
            });
            let mut builder = RigidBodyBuilder::dynamic()
                .translation(link.origin)
                .can_sleep(false);
            let mass = if link.inertials.is_empty() {
                let inertia = CHAIN_LINK_MASS * 0.01;
                MassProperties::new(Vector::ZERO, CHAIN_LINK_MASS, Vector::splat(inertia))
            } else {
                link.inertials
                    .iter()
                    .map(|i| MassProperties::new(i.com - link.origin, i.mass, i.inertia))
                    .fold(MassProperties::default(), |sum, m| sum + m)
            };
            builder = builder.additional_mass_properties(mass);
            let body = world.insert_body(builder);
            let handles = link
                .geoms
                .iter()
                .map(|geom| {
                    let shape = match *geom {
                        Geom::Capsule(a, b, r) => ColliderBuilder::capsule_from_endpoints(
                            a - link.origin,
                            b - link.origin,
                            r,
                        ),
                        Geom::Sphere(c, r) => ColliderBuilder::ball(r).translation(c - link.origin),
                    };
                    world.insert_collider(
                        shape
                            .density(0.0)
                            .friction(self.robot.friction)
                            .collision_groups(groups),
                        Some(body),
                    )
                })
                .collect::<Vec<_>>();
            for &handle in &handles {
                floor_contacts.add_link_collider(handle.into_raw_parts(), threshold);
            }
            // Now, not at the first step: reset reads the centres of mass.
            world.bodies[body].recompute_mass_properties_from_colliders(&world.colliders);
            bodies.push(body);
            colliders.push(handles);
        }
        let mut joint_handles = Vec::new();
        for (k, link) in self.robot.links.iter().enumerate().skip(1) {
            let parent = link.parent.expect("links after the root have a parent");
            let hinge = RevoluteJointBuilder::new(link.axis)
                .local_anchor1(link.origin - self.robot.links[parent].origin)
                .local_anchor2(Vector::ZERO)
                .limits([link.range.0, link.range.1])
                .softness(SpringCoefficients::new(
                    BULLET_LIMIT_SPRING.0,
                    BULLET_LIMIT_SPRING.1,
                ))
                .contacts_enabled(false);
            let handle = world
                .insert_multibody_joint(bodies[parent], bodies[k], hinge)
                .expect("the robot is a tree");
            joint_handles.push(handle);
        }
        // Joint angles and no damping (PyBullet has none), then the links' poses from them.
        if let Some(&first) = joint_handles.first() {
            let (multibody, _) = world
                .multibody_joints
                .get_mut(first)
                .expect("the joint was just inserted");
            multibody.forward_kinematics(&world.bodies, true);
            let mut displacement = vec![0.0; multibody.ndofs()];
            multibody.damping_mut().fill(0.0);
            // Coriolis and gyroscopic forces explicit, as Bullet's.
            multibody.set_implicit_coriolis(false);
            for k in 1..self.robot.links.len() {
                let dof = multibody
                    .link(k)
                    .expect("links are numbered in insertion order")
                    .assembly_id();
                displacement[dof] = angles[k - 1];
            }
            multibody.apply_displacements(&displacement);
            multibody.forward_kinematics(&world.bodies, true);
            multibody.update_rigid_bodies(&mut world.bodies, true);
        }
        self.world = world;
        self.ground = ground;
        self.bodies = bodies;
        self.colliders = colliders;
        self.multibody = joint_handles.first().copied();
        self.floor_contacts = floor_contacts;
        self.long_axes = self.robot.links.iter().any(|l| l.axis_length != 1.0);
        self.angles_before = vec![0.0; self.robot.links.len()];
        let ndofs = self
            .multibody
            .and_then(|h| self.world.multibody_joints.get(h));
        self.displacement = vec![0.0; ndofs.map_or(0, |(m, _)| m.ndofs())];
        self.feet_contact = vec![0.0; self.robot.feet.len()];
        self.remember_link_poses();
    }

    /// Each hinge's angle before a substep, for [`Spatial::turn_joints_as_bullet`] after it.
    fn record_joint_angles(&mut self) {
        let world = &self.world;
        let Some((multibody, _)) = self.multibody.and_then(|h| world.multibody_joints.get(h))
        else {
            return;
        };
        for (k, angle) in self.angles_before.iter_mut().enumerate().skip(1) {
            if let Some(link) = multibody.link(k) {
                *angle = link.joint.coords()[HINGE_ANGLE];
            }
        }
    }

    /// Bullet's multibody takes a hinge's model axis as given, not normalised: a joint whose
    /// axis is longer than 1 (the Ant's ankles, sqrt 2; the Humanoid's arms, sqrt 2 and sqrt 6)
    /// spins its link `axis_length` times its joint speed, which makes it that much heavier to
    /// turn (torques above, speeds observed), while the link turns by the joint angle about the
    /// unit axis. rapier turns the link as far as it spins; after each substep this takes back
    /// the difference from the angles [`Spatial::record_joint_angles`] kept, and moves the links'
    /// bodies (and so their colliders) to the poses that gives.
    fn turn_joints_as_bullet(&mut self) {
        let links = &self.robot.links;
        let world = &mut self.world;
        let Some((multibody, _)) = self
            .multibody
            .and_then(|h| world.multibody_joints.get_mut(h))
        else {
            return;
        };
        self.displacement.fill(0.0);
        for (k, link) in links.iter().enumerate().skip(1) {
            if let Some(joint_link) = multibody.link(k) {
                let turned = joint_link.joint.coords()[HINGE_ANGLE] - self.angles_before[k];
                self.displacement[joint_link.assembly_id()] =
                    turned * (1.0 / link.axis_length - 1.0);
            }
        }
        multibody.apply_displacements(&self.displacement);
        multibody.forward_kinematics(&world.bodies, true);
        // `set_position` marks the pose changed, so the colliders follow before the next
        // collision detection (writing the poses in place would leave them behind).
        for link in multibody.links() {
            let pose = *link.local_to_world();
            super::body_mut(&mut world.bodies, link.rigid_body_handle()).set_position(pose, false);
        }
    }

    /// The observed feet.
    #[cfg(test)]
    pub(super) fn feet(&self) -> &[Foot] {
        &self.robot.feet
    }

    /// Link `k`'s contact breaking threshold from its geoms as Bullet bounds them.
    pub(super) fn bounded_threshold(&self, k: usize) -> f32 {
        let link = &self.robot.links[k];
        let mass: f32 = link.inertials.iter().map(|i| i.mass).sum();
        let com = if mass > 0.0 {
            link.inertials
                .iter()
                .fold(Vector::ZERO, |sum, i| sum + i.com * (i.mass / mass))
        } else {
            link.origin
        };
        let at = |p: Vector| {
            let d = p - com;
            nalgebra::Vector3::new(d.x, d.y, d.z)
        };
        let shapes: Vec<BoundedShape> = link
            .geoms
            .iter()
            .map(|geom| match *geom {
                Geom::Capsule(a, b, r) => BoundedShape::Capsule(at(a), at(b), r),
                Geom::Sphere(c, r) => BoundedShape::Sphere(at(c), r),
            })
            .collect();
        floor_contacts::contact_breaking_threshold(&shapes)
    }

    /// Gives every link's body the multibody's current speeds ([`walker_base::link_velocity`]).
    fn sync_link_velocities(&mut self) {
        let set = |body: &mut RigidBody, v: [f32; 6]| {
            body.set_linvel(Vector::new(v[0], v[1], v[2]), false);
            body.set_angvel(Vector::new(v[3], v[4], v[5]), false);
        };
        walker_base::sync_link_velocities!(self.world, self.multibody, 6, set);
    }

    /// One Bullet substep under `torques`: forces, this substep's limit springs, the physics
    /// step, and the links' speeds from the multibody's.
    fn bullet_substep(&mut self, torques: &[f32]) {
        self.apply_forces(torques);
        let links = &self.robot.links;
        walker_base::set_bullet_limit_springs!(self.world, self.multibody, |k: usize| {
            links.get(k).map_or(1.0, |l| l.axis_length)
        });
        self.floor_contacts.next_substep();
        if self.long_axes {
            self.record_joint_angles();
        }
        super::engine(|| self.world.step_with_events(&self.floor_contacts, &()));
        if self.long_axes {
            super::engine(|| self.turn_joints_as_bullet());
        }
        self.sync_link_velocities();
    }

    fn torso(&self) -> &RigidBody {
        &self.world.bodies[self.bodies[0]]
    }

    /// PyBullet's body_xyz: x and y averaged over the robot's parts, which are every one of its
    /// links' centres of mass, the link its importer makes at each hinge, and the floor (at the
    /// origin), the torso's current and the other links' at their `seen_poses`; z is the
    /// torso's centre of mass.
    fn body_xyz(&self) -> Vector {
        let mut sum = Vector::ZERO;
        let mut parts = 1; // the floor
        for (k, (link, &body)) in self.robot.links.iter().zip(&self.bodies).enumerate() {
            let pose = match k {
                0 => self.world.bodies[body].position(),
                _ => &self.seen_poses[k],
            };
            let anchor = link.parent.map(|_| link.origin);
            for point in anchor
                .into_iter()
                .chain(link.inertials.iter().map(|i| i.com))
            {
                sum += pose.transform_point(point - link.origin);
                parts += 1;
            }
        }
        let mean = sum / parts as f32;
        v(mean.x, mean.y, self.torso().center_of_mass().z)
    }

    /// Whether links `a` and `b` may touch (a test of the collision groups).
    #[cfg(test)]
    pub(crate) fn links_collide(&self, a: usize, b: usize) -> bool {
        let groups = |k: usize| self.world.colliders[self.colliders[k][0]].collision_groups();
        groups(a).test(groups(b))
    }

    /// Touching pairs of the robot's own colliders now.
    #[cfg(test)]
    pub(crate) fn self_contacts(&self) -> usize {
        self.world
            .narrow_phase
            .contact_pairs()
            .filter(|pair| {
                pair.has_any_active_contact()
                    && pair.collider1 != self.ground
                    && pair.collider2 != self.ground
            })
            .count()
    }

    fn read_joints(&mut self) {
        for (k, link) in self.robot.links.iter().enumerate().skip(1) {
            let parent = &self.world.bodies[self.bodies[link.parent.unwrap_or(0)]];
            let child = &self.world.bodies[self.bodies[k]];
            // Every link is unrotated at rest, so the relative rotation is about the axis.
            let relative = parent.rotation().inverse() * *child.rotation();
            let along =
                relative.x * link.axis.x + relative.y * link.axis.y + relative.z * link.axis.z;
            let q = wrap_angle(f64::from(2.0 * along.atan2(relative.w))) as f32;
            let world_axis = *child.rotation() * link.axis;
            // Bullet's joint speed: the link spins `axis_length` times faster (below).
            let qdot = (child.angvel() - parent.angvel()).dot(world_axis) / link.axis_length;
            self.joint_state[2 * (k - 1)..2 * k]
                .copy_from_slice(&walker_base::joint_state(q, qdot, link.range));
        }
    }

    /// Joint torques as equal and opposite torques on child and parent (no spurious momentum),
    /// and Bullet's default multibody drag on every link (unless floating freely for a test).
    fn apply_forces(&mut self, action: &[f32]) {
        for &body in &self.bodies {
            let body = super::body_mut(&mut self.world.bodies, body);
            body.reset_forces(false);
            body.reset_torques(false);
            if self.drag {
                let (v, w) = (body.linvel(), body.angvel());
                let local = &body.mass_properties().local_mprops;
                let frame = *body.rotation() * local.principal_inertia_local_frame;
                let spin = frame * (local.principal_inertia() * (frame.inverse() * w));
                let force = -body.mass() * v * bullet_drag(v.length());
                let torque = -spin * bullet_drag(w.length());
                body.add_force(force, true);
                body.add_torque(torque, true);
            }
        }
        for (k, link) in self.robot.links.iter().enumerate().skip(1) {
            let parent = self.bodies[link.parent.unwrap_or(0)];
            let child = self.bodies[k];
            let world_axis = *self.world.bodies[child].rotation() * link.axis;
            // The joint's generalised force, on Bullet's axis of length `axis_length`.
            let tau = world_axis * (link.torque * action[k - 1] / link.axis_length);
            super::body_mut(&mut self.world.bodies, child).add_torque(tau, true);
            super::body_mut(&mut self.world.bodies, parent).add_torque(-tau, true);
        }
    }
}

impl Body for SpatialBody {
    fn reset(&mut self, rng: &mut ChaCha8Rng) {
        // PyBullet draws U(-0.1, 0.1) per joint, inside the limits or not (the Ant's ankles
        // start up to 40 degrees outside theirs and stay there until torques or contacts move
        // them: the limits never push back).
        let angles: Vec<f32> = (1..self.robot.links.len())
            .map(|_| rng.random_range(-0.1f32..0.1))
            .collect();
        self.build(&angles);
        self.initial_z = self
            .robot
            .initial_z
            .unwrap_or_else(|| self.torso().center_of_mass().z);
    }

    fn substep(&mut self, action: &[f32]) {
        self.bullet_substep(action);
    }

    /// Keeps the links' current poses as those the progress reward reads (`seen_poses`).
    fn remember_link_poses(&mut self) {
        self.seen_poses.clear();
        let bodies = &self.world.bodies;
        self.seen_poses
            .extend(self.bodies.iter().map(|&b| *bodies[b].position()));
    }

    /// PyBullet's calc_state, written into obs, the feet contacts those of the step before;
    /// returns (torso z, pitch).
    fn observe(&mut self, obs: &mut [f32]) -> (f32, f32) {
        self.read_joints();
        let p = self.body_xyz();
        let torso = self.torso();
        let (yaw, pitch, roll) = torso.rotation().to_euler(EulerRot::ZYX);
        let angle_to_target = (-p.y).atan2(TARGET_X - p.x) - yaw;
        let speed = torso.linvel();
        let (s, c) = (-yaw).sin_cos();
        let more = [
            p.z - self.initial_z,
            angle_to_target.sin(),
            angle_to_target.cos(),
            0.3 * (c * speed.x - s * speed.y),
            0.3 * (s * speed.x + c * speed.y),
            0.3 * speed.z,
            roll,
            pitch,
        ];
        obs[..MORE].copy_from_slice(&more);
        let joints = self.joint_state.len();
        obs[MORE..MORE + joints].copy_from_slice(&self.joint_state);
        obs[MORE + joints..].copy_from_slice(&self.feet_contact);
        clip_observation(obs);
        (p.z, pitch)
    }

    fn alive(&self, z: f32, _pitch: f32) -> (f64, bool) {
        let alive = if z > self.robot.alive.min_z {
            self.robot.alive.bonus
        } else {
            -1.0
        };
        (alive, true)
    }

    /// PyBullet's potential: minus the distance to the target per control period.
    fn potential(&self) -> f64 {
        let p = self.body_xyz();
        walker_base::potential((TARGET_X - p.x).hypot(p.y))
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
        camera::scene(
            &self.world.colliders,
            &self.colliders,
            self.torso().position(),
        )
    }

    fn trace(&self, predicted: &[f32], spec: &EnvSpec) -> Vec<(f64, f64)> {
        let dt = CONTROL_PERIOD;
        let torso = self.torso().center_of_mass();
        let (mut x, mut y) = (torso.x, torso.y);
        predicted
            .chunks_exact(spec.obs_dim)
            .map(|o| {
                // "more" holds 0.3 x the yaw-rotated speed; heading stays near x for a walker.
                x += o[3] / 0.3 * dt;
                y += o[4] / 0.3 * dt;
                camera::project(v(x, y, o[0] + self.initial_z))
            })
            .collect()
    }
}

#[cfg(test)]
impl SpatialBody {
    /// The feet contacts the last step measured (the next observation shows them).
    pub(super) fn feet_contact_for_test(&self) -> &[f32] {
        &self.feet_contact
    }

    /// Takes the floor away and lets the robot fall for `seconds` without torques; returns the
    /// torso's vertical speed.
    pub(super) fn drop_for_test(&mut self, seconds: f32) -> f32 {
        self.world.remove_collider(self.ground);
        let zero = vec![0.0; self.robot.links.len() - 1];
        let steps = (seconds / CONTROL_PERIOD) as usize * walker_base::BULLET_SUBSTEPS;
        for _ in 0..steps {
            self.bullet_substep(&zero);
        }
        self.torso().linvel().z
    }

    /// No gravity, floor or drag: nothing outside the robot acts on it.
    pub(super) fn float_freely_for_test(&mut self) {
        self.world.gravity = Vector::ZERO;
        self.world.remove_collider(self.ground);
        self.drag = false;
    }

    /// The sum of |torque| over the joints for one step of `action`, times the control period.
    pub(super) fn torque_impulse_for_test(&self, action: &[f32]) -> f32 {
        let links = &self.robot.links[1..];
        links
            .iter()
            .zip(action)
            .map(|(link, u)| (link.torque * u).abs() * CONTROL_PERIOD)
            .sum()
    }

    /// The robot's mass (kg) and centre of mass (world, m).
    pub(super) fn mass_and_centre_for_test(&self) -> (f32, [f32; 3]) {
        let (mut mass, mut moment) = (0.0, Vector::ZERO);
        for &h in &self.bodies {
            let body = &self.world.bodies[h];
            mass += body.mass();
            moment += body.center_of_mass() * body.mass();
        }
        let c = moment / mass;
        (mass, [c.x, c.y, c.z])
    }

    /// Per actuated joint in PyBullet's motor order: its limits (rad) and unit-action torque.
    pub(super) fn joints_for_test(&self) -> Vec<((f32, f32), f32)> {
        let links = &self.robot.links[1..];
        links.iter().map(|l| (l.range, l.torque)).collect()
    }

    /// How many parts PyBullet's body position averages over (the floor included).
    pub(super) fn parts_for_test(&self) -> usize {
        let links = &self.robot.links;
        1 + links.iter().map(|l| l.inertials.len()).sum::<usize>() + links.len() - 1
    }

    /// The robot's total linear momentum and its angular momentum about the origin.
    pub(super) fn momentum_for_test(&self) -> (Vector, Vector) {
        let (mut linear, mut angular) = (Vector::ZERO, Vector::ZERO);
        for &h in &self.bodies {
            let body = &self.world.bodies[h];
            let p = body.linvel() * body.mass();
            linear += p;
            let local = &body.mass_properties().local_mprops;
            let frame = *body.rotation() * local.principal_inertia_local_frame;
            let spin = frame * (local.principal_inertia() * (frame.inverse() * body.angvel()));
            angular += body.center_of_mass().cross(p) + spin;
        }
        (linear, angular)
    }

    /// The largest distance between a hinge's anchor as seen from the parent and the child.
    pub(super) fn largest_joint_gap_for_test(&self) -> f32 {
        let links = &self.robot.links;
        links
            .iter()
            .enumerate()
            .skip(1)
            .map(|(k, link)| {
                let parent = link.parent.unwrap_or(0);
                let from_parent = self.world.bodies[self.bodies[parent]]
                    .position()
                    .transform_point(link.origin - links[parent].origin);
                (from_parent - self.world.bodies[self.bodies[k]].translation()).length()
            })
            .fold(0.0, f32::max)
    }
}
