//! PyBullet's WalkerBase task interface, shared by the planar (rapier2d) and 3D (rapier3d)
//! walkers: the constants, the potential, the normalised joint state, the observation clip and
//! the effort costs of the reward, and the episode bookkeeping around each physics step.

use super::{EnvError, EnvSpec, Transition, clip_action};

pub(super) const CONTROL_PERIOD: f32 = 0.0165;
pub(super) const GRAVITY: f32 = 9.8;
/// PyBullet's walk target, far ahead on x.
pub(super) const TARGET_X: f32 = 1000.0;
/// rapier's joint-limit softness (natural frequency in Hz, damping ratio) for a joint further
/// than `BULLET_SPLIT_IMPULSE_THRESHOLD` past its limit, as Bullet's multibody limit treats it:
/// the limit stops the joint's speed into it and never pushes the violation back (PyBullet,
/// measured: an Ant ankle reset 0.46 rad outside its range stays exactly there in free fall with
/// zero torque). Frequency 0 makes rapier's ERP 0 (no position correction) and its CFM 0 (a
/// rigid stop). PyBullet does not clamp a reset's joints into their ranges, and neither do we.
pub(super) const BULLET_LIMIT_SPRING: (f32, f32) = (0.0, 1.0);
/// Bullet's non-contact ERP (btContactSolverInfo's default 0.2, which PyBullet keeps): the
/// share of a small joint-limit violation its solver turns into speed back inside, each substep.
pub(super) const BULLET_LIMIT_ERP: f32 = 0.2;
/// Bullet's split-impulse penetration threshold (0.04): a joint further than this past its limit
/// has its positional error split off, which the multibody solver never applies, so it is only
/// stopped there (`BULLET_LIMIT_SPRING`).
pub(super) const BULLET_SPLIT_IMPULSE_THRESHOLD: f32 = 0.04;

/// The contact ERP pybullet_envs sets (`setDefaultContactERP(0.9)` in its scene's World, over
/// Bullet's default `m_erp2` of 0.08): the share of a penetration the multibody solver turns
/// into speed out of the floor each substep, kept as speed (Bullet's multibody contacts have no
/// split impulse).
pub(super) const BULLET_CONTACT_ERP: f32 = 0.9;

/// rapier's softness (natural frequency in Hz, damping ratio) that corrects `erp` of an error
/// each substep of `dt` seconds with almost no CFM, as Bullet's solver does: rapier's ERP is
/// `dt w / (dt w + 2 zeta)`, its CFM `0.8 / zeta^2` at ERP 0.2; a large zeta keeps that CFM near
/// Bullet's 0.
pub(super) fn bullet_erp_spring(erp: f32, dt: f32) -> (f32, f32) {
    const ZETA: f32 = 100.0;
    let dt_omega = 2.0 * ZETA * erp / (1.0 - erp);
    (dt_omega / (dt * std::f32::consts::TAU), ZETA)
}

/// rapier's limit softness for a joint `violation` past its limit, in substeps of `dt` seconds:
/// Bullet's ERP within the split-impulse threshold, else a stop. A hinge on a model axis of
/// length `axis_length` turns 1/`axis_length` as far as rapier moves it (spatial.rs), so its
/// ERP is that much larger here.
pub(super) fn bullet_limit_spring(violation: f32, dt: f32, axis_length: f32) -> (f32, f32) {
    if violation > 0.0 && violation < BULLET_SPLIT_IMPULSE_THRESHOLD {
        bullet_erp_spring((BULLET_LIMIT_ERP * axis_length).min(0.99), dt)
    } else {
        BULLET_LIMIT_SPRING
    }
}

/// Sets every limited joint of a walker's rapier2d or rapier3d multibody (`$world`, the handle
/// `$multibody`) to `bullet_limit_spring` for how far it is past its limits now, for the next
/// substep; `$axis_length(k)` is multibody link k's model axis length (the two crates' types
/// differ, the code does not; `SpringCoefficients` is the caller's crate's).
macro_rules! set_bullet_limit_springs {
    ($world:expr, $multibody:expr, $axis_length:expr) => {{
        let world = &mut $world;
        let dt = world.integration_parameters.dt;
        if let Some((multibody, _)) = $multibody.and_then(|h| world.multibody_joints.get_mut(h)) {
            for k in 0..multibody.num_links() {
                let joint = &mut multibody.link_mut(k).expect("a link").joint;
                let coords = joint.coords();
                let data = &mut joint.data;
                let mut violation = 0.0f32;
                for (i, limits) in data.limits.iter().enumerate() {
                    if data.limit_axes.bits() & (1 << i) != 0 {
                        violation = violation
                            .max(coords[i] - limits.max)
                            .max(limits.min - coords[i]);
                    }
                }
                let (frequency, damping) =
                    walker_base::bullet_limit_spring(violation, dt, $axis_length(k));
                data.softness = SpringCoefficients::new(frequency, damping);
            }
        }
    }};
}
pub(super) use set_bullet_limit_springs;

/// Gives every link's body of a walker's rapier2d or rapier3d multibody (`$world`, the handle
/// `$multibody`) the multibody's current speeds (`link_velocity`, `$n` = 3 in 2D, 6 in 3D),
/// written into each body by `$set(body, velocity)`.
macro_rules! sync_link_velocities {
    ($world:expr, $multibody:expr, $n:literal, $set:expr) => {{
        let world = &mut $world;
        if let Some((multibody, _)) = $multibody.and_then(|h| world.multibody_joints.get(h)) {
            let speeds = multibody.generalized_velocity();
            for k in 0..multibody.num_links() {
                let handle = multibody.link(k).expect("a link").rigid_body_handle();
                let velocity: [f32; $n] =
                    walker_base::link_velocity(multibody.body_jacobian(k), speeds);
                $set(super::body_mut(&mut world.bodies, handle), velocity);
            }
        }
    }};
}
pub(super) use sync_link_velocities;

/// PyBullet's numSubSteps: Bullet steps per control period. Each is one rapier step of one solver
/// substep (rapier's default of four would make sixteen; docs/domains.md).
pub(super) const BULLET_SUBSTEPS: usize = 4;
/// PyBullet's numSolverIterations: constraint-solver iterations per Bullet substep.
pub(super) const BULLET_SOLVER_ITERATIONS: usize = 5;
/// Bullet's time discretisation and solver on a rapier2d or rapier3d world's integration
/// parameters: `BULLET_SUBSTEPS` steps per period of one solver substep each, with
/// `BULLET_SOLVER_ITERATIONS` iterations, and no stabilization pass: Bullet's multibody solver
/// keeps the speed that corrects a contact's penetration or a small limit violation (its
/// right-hand side adds them), where rapier's stabilization pass would take it away again;
/// contacts corrected at Bullet's contact ERP.
macro_rules! set_bullet_solver {
    ($params:expr) => {{
        let params = &mut $params;
        params.dt = walker_base::CONTROL_PERIOD / walker_base::BULLET_SUBSTEPS as f32;
        params.num_solver_iterations = 1;
        params.num_internal_pgs_iterations = walker_base::BULLET_SOLVER_ITERATIONS;
        params.num_internal_stabilization_iterations = 0;
        // Bullet finds every contact anew each substep; rapier would keep a pair's points
        // until it moved 5 cm.
        params.contact_recycling = false;
        // Bullet's contact ERP, floor or not, and no cap on the speed it gives.
        let (frequency, damping) =
            walker_base::bullet_erp_spring(walker_base::BULLET_CONTACT_ERP, params.dt);
        params.contact_softness = SpringCoefficients::new(frequency, damping);
        params.static_contact_softness = params.contact_softness;
        params.normalized_max_corrective_velocity = f32::MAX;
        // Bullet starts multibody contacts and limits from zero impulse each substep (its
        // articulated warm starting is off unless asked for); in rapier this covers every
        // constraint.
        params.warmstart_coefficient = 0.0;
    }};
}
pub(super) use set_bullet_solver;

/// A link whose ground contact the robot observes, and the distance within which PyBullet
/// reports it: Bullet keeps a contact point while the surfaces are closer than the link's
/// contact breaking threshold, 0.02 times its shape's angular motion disc (so 4.6 mm for the
/// Humanoid's foot, 9.4 mm for the Ant's), and pybullet_envs counts any point as touching.
/// Measured per link by scripts/conformance/contact_thresholds.py.
pub(super) struct Foot {
    pub(super) link: usize,
    pub(super) contact_threshold: f32,
}

impl Foot {
    pub(super) fn new(link: usize, contact_threshold: f32) -> Self {
        Foot {
            link,
            contact_threshold,
        }
    }
}

/// A link's contact breaking threshold: an observed foot's as measured in PyBullet, else
/// `bounded()`, its shapes' as Bullet bounds them (floor_contacts.rs).
pub(super) fn link_contact_threshold(
    feet: &[Foot],
    link: usize,
    bounded: impl FnOnce() -> f32,
) -> f32 {
    feet.iter()
        .find(|f| f.link == link)
        .map_or_else(bounded, |f| f.contact_threshold)
}

/// Whether `$foot` (a `Foot`) of a 2D or 3D walker (`$env`, with `world`, `colliders` per link
/// and `ground`) is touching the floor: a contact point of the last collision detection closer
/// than its threshold.
macro_rules! touching_ground {
    ($env:expr, $foot:expr) => {{
        let env = &$env;
        let foot: &walker_base::Foot = $foot;
        env.colliders[foot.link].iter().any(|&c| {
            env.world.contact_pair(c, env.ground).is_some_and(|pair| {
                let mut points = pair.manifolds().iter().flat_map(|m| &m.points);
                points.any(|p| p.dist < foot.contact_threshold)
            })
        })
    }};
}
pub(super) use touching_ground;

/// Sets `$env.feet_contact` (`$env` a walker's `&mut self`) to whether each observed foot
/// touches the ground now. PyBullet measures the contacts after it has observed and scored a
/// step, so its next observation (and the HalfCheetah's next alive bonus) shows them: one step
/// late, and 0 after a reset.
macro_rules! measure_feet_contact {
    ($env:expr) => {{
        let env = &mut *$env;
        for k in 0..env.robot.feet.len() {
            let touching = walker_base::touching_ground!(env, &env.robot.feet[k]);
            env.feet_contact[k] = f32::from(u8::from(touching));
        }
    }};
}
pub(super) use measure_feet_contact;

/// Joint angles and speeds, then feet contacts, follow these 8 "more" values.
pub(super) const MORE: usize = 8;

const ELECTRICITY_COST: f64 = -2.0;
const STALL_TORQUE_COST: f64 = -0.1;
const JOINTS_AT_LIMIT_COST: f64 = -0.1;
/// PyBullet clips every observation value to this magnitude.
const OBSERVATION_CLIP: f32 = 5.0;
/// btMultiBody's default linear and angular damping, which PyBullet keeps.
const BULLET_DRAG: f32 = 0.04;

/// A multibody link's velocity, linear then angular (`N` = 3 in 2D, 6 in 3D): its body jacobian
/// times the generalised speeds, without allocating. rapier writes a multibody's speeds into
/// its links' bodies before its last solver substep, so the walkers read them from here.
pub(super) fn link_velocity<const N: usize>(
    jacobian: &nalgebra::OMatrix<f32, nalgebra::Const<N>, nalgebra::Dyn>,
    speeds: nalgebra::DVectorView<'_, f32>,
) -> [f32; N] {
    let mut velocity = [0.0; N];
    for (row, v) in velocity.iter_mut().enumerate() {
        *v = (0..speeds.len())
            .map(|dof| jacobian[(row, dof)] * speeds[dof])
            .sum();
    }
    velocity
}

/// PyBullet's potential: minus the distance to the target per control period.
pub(super) fn potential(distance_to_target: f32) -> f64 {
    -f64::from(distance_to_target) / f64::from(CONTROL_PERIOD)
}

/// PyBullet's joint state: the angle mapped to [-1, 1] over its range, and 0.1 x the speed.
pub(super) fn joint_state(q: f32, qdot: f32, (lo, hi): (f32, f32)) -> [f32; 2] {
    let mid = 0.5 * (lo + hi);
    [2.0 * (q - mid) / (hi - lo), 0.1 * qdot]
}

/// btMultiBody's drag on every link, per unit of momentum: a link moving at `speed` (m/s, or rad/s
/// for its spin) feels `-drag(speed)` times its momentum (`m v`, or `I w`) as force (or torque).
pub(super) fn bullet_drag(speed: f32) -> f32 {
    BULLET_DRAG * (1.0 + speed)
}

pub(super) fn clip_observation(obs: &mut [f32]) {
    for x in obs.iter_mut() {
        *x = x.clamp(-OBSERVATION_CLIP, OBSERVATION_CLIP);
    }
}

/// The reward's cost terms: electricity and stall (means over joints, times `cost_scale`, 4.25
/// for PyBullet's Humanoid) and the joints-at-limit count. `joint_state` interleaves angles and
/// speeds as [`joint_state`] gives them.
pub(super) fn effort_cost_terms(
    action: &[f32],
    joint_state: &[f32],
    cost_scale: f64,
) -> (f64, f64) {
    let n = action.len() as f64;
    let speeds = joint_state.iter().skip(1).step_by(2);
    let electricity = ELECTRICITY_COST
        * action
            .iter()
            .zip(speeds)
            .map(|(u, s)| f64::from((u * s).abs()))
            .sum::<f64>()
        / n;
    let stall = STALL_TORQUE_COST * action.iter().map(|u| f64::from(u * u)).sum::<f64>() / n;
    let at_limit = joint_state
        .iter()
        .step_by(2)
        .filter(|q| q.abs() > 0.99)
        .count() as f64;
    (
        cost_scale * (electricity + stall),
        JOINTS_AT_LIMIT_COST * at_limit,
    )
}

/// A walker's task around its physics, the same in 2D and 3D: the action check, PyBullet's
/// reward (alive bonus, progress towards the target, effort costs) and the episode's end.
#[derive(Clone, Debug)]
pub(super) struct WalkerEpisode {
    /// The clipped action, reused so that a step allocates nothing.
    action: Vec<f32>,
    potential: f64,
    steps: u32,
    over: bool,
    episode_len: u32,
    /// Scales the electricity and stall costs (4.25 for PyBullet's Humanoid, else 1).
    cost_scale: f64,
    /// The last step's reward by term, in PyBullet's order.
    terms: [(&'static str, f64); 4],
}

/// Names of the reward terms, as PyBullet's `rewards` list holds them (without the feet
/// collision cost, which PyBullet sets to 0).
pub(super) const REWARD_TERMS: [&str; 4] = ["alive", "progress", "electricity", "joints_at_limit"];

impl WalkerEpisode {
    pub(super) fn new(spec: &EnvSpec, cost_scale: f64) -> WalkerEpisode {
        WalkerEpisode {
            action: vec![0.0; spec.act_dim],
            potential: 0.0,
            steps: 0,
            over: true,
            episode_len: spec.episode_len,
            cost_scale,
            terms: REWARD_TERMS.map(|name| (name, 0.0)),
        }
    }

    /// The last step's reward by term; they sum to its reward.
    pub(super) fn reward_terms(&self) -> &[(&'static str, f64)] {
        &self.terms
    }

    /// A new episode whose robot starts at `potential`.
    pub(super) fn start(&mut self, potential: f64) {
        self.potential = potential;
        self.steps = 0;
        self.over = false;
    }

    /// The action clipped to the bounds, for the physics to apply; hand it back to
    /// [`WalkerEpisode::finish_step`]. A refused step changes nothing.
    pub(super) fn begin_step(
        &mut self,
        spec: &EnvSpec,
        action: &[f32],
    ) -> Result<Vec<f32>, EnvError> {
        let mut clipped = std::mem::take(&mut self.action);
        let checked = match clip_action(spec, action, &mut clipped) {
            Ok(()) if self.over => Err(EnvError::EpisodeOver),
            other => other,
        };
        match checked {
            Ok(()) => Ok(clipped),
            Err(e) => {
                self.action = clipped;
                Err(e)
            }
        }
    }

    /// The step's reward and end, once the physics has run: `alive` is the bonus (negative when
    /// the robot fell), which ends the episode when `falling_ends`; `potential` is the robot's
    /// new one and `joint_state` its joints as [`joint_state`] gives them.
    pub(super) fn finish_step(
        &mut self,
        action: Vec<f32>,
        alive: f64,
        falling_ends: bool,
        potential: f64,
        joint_state: &[f32],
    ) -> Transition {
        let progress = potential - self.potential;
        self.potential = potential;
        let (power, at_limit) = effort_cost_terms(&action, joint_state, self.cost_scale);
        // Summed in this order, as before the terms were kept apart: the reward's bits stay.
        let reward = alive + progress + (power + at_limit);
        self.terms = [
            (REWARD_TERMS[0], alive),
            (REWARD_TERMS[1], progress),
            (REWARD_TERMS[2], power),
            (REWARD_TERMS[3], at_limit),
        ];
        self.action = action;
        self.steps += 1;
        let terminated = falling_ends && alive < 0.0;
        let truncated = !terminated && self.steps >= self.episode_len;
        self.over = terminated || truncated;
        Transition {
            reward,
            terminated,
            truncated,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn effort_costs_follow_pybullets_formula() {
        // Two joints: the first at its upper limit moving at 10 rad/s (state 1.0), the second
        // at rest mid-range.
        let state = [1.0, 1.0, 0.0, 0.0];
        let action = [0.5, -1.0];
        // electricity -2 x mean(|0.5 x 1|, |-1 x 0|) = -0.5; stall -0.1 x mean(0.25, 1) =
        // -0.0625; one joint at its limit: -0.1.
        let (power, at_limit) = effort_cost_terms(&action, &state, 1.0);
        assert!((power - (-0.5 - 0.0625)).abs() < 1e-12, "{power}");
        assert_eq!(at_limit, -0.1);
        let (scaled, _) = effort_cost_terms(&action, &state, 4.25);
        assert!((scaled - 4.25 * (-0.5 - 0.0625)).abs() < 1e-12, "{scaled}");
    }

    #[test]
    fn joint_state_maps_the_range_to_plus_minus_one() {
        assert_eq!(joint_state(-0.5, 3.0, (-0.5, 1.5)), [-1.0, 0.3]);
        assert_eq!(joint_state(1.5, 0.0, (-0.5, 1.5)), [1.0, 0.0]);
        assert_eq!(joint_state(0.5, 0.0, (-0.5, 1.5)), [0.0, 0.0]);
    }
}
