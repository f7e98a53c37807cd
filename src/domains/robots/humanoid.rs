//! humanoid_symmetric.xml as PyBullet's HumanoidBulletEnv loads it.

use crate::domains::spatial::{
    Alive, FLOOR_FRICTION, Geom, LinkDef, RobotDef, capsule, hinge, inertial, v,
};
use crate::domains::walker_base::Foot;
use rapier3d::prelude::Vector;

/// humanoid_symmetric.xml with PyBullet's motor powers x 0.41. Positions are the model's, summed
/// down the body tree (its near-identity body quaternions are dropped), from the torso's frame at
/// (0.01, 0, 1.52): PyBullet puts the torso's centre of mass, its last geom's middle at (-0.01, 0,
/// -0.12) in that frame, at the model's (0, 0, 1.4), so the whole body stands 0.12 m higher than
/// MuJoCo's.
pub(in crate::domains) fn humanoid() -> RobotDef {
    let torso = v(0.01, 0.0, 1.52);
    let at = |base: Vector, x: f32, y: f32, z: f32| base + v(x, y, z);
    let power = 0.41;
    let mut links = vec![LinkDef {
        parent: None,
        // The frame at the centre of mass, as Bullet's base: rapier moves a free root's frame
        // origin by its speed, and from (0.01, 0, 1.52) the torso's centre rose against
        // PyBullet's under the hips' torques (0.9 cm after 10 random steps, 0.08 cm here).
        origin: at(torso, -0.01, 0.0, -0.12),
        axis: Vector::ZERO,
        axis_length: 1.0,
        range: (0.0, 0.0),
        torque: 0.0,
        geoms: vec![
            capsule(at(torso, 0.0, -0.07, 0.0), at(torso, 0.0, 0.07, 0.0), 0.07),
            Geom::Sphere(at(torso, 0.0, 0.0, 0.19), 0.09),
            capsule(
                at(torso, -0.01, -0.06, -0.12),
                at(torso, -0.01, 0.06, -0.12),
                0.06,
            ),
        ],
        inertials: vec![inertial(
            at(torso, -0.01, 0.0, -0.12),
            8.907462,
            (0.281773, 0.221499, 0.132127),
        )],
    }];
    let mut add = |link: LinkDef| {
        links.push(link);
        links.len() - 1
    };
    let lwaist = at(torso, -0.01, 0.0, -0.26);
    let abdomen = at(lwaist, 0.0, 0.0, 0.065);
    let abdomen_z = add(hinge(
        0,
        abdomen,
        v(0.0, 0.0, 1.0),
        (-45.0, 45.0),
        100.0 * power,
        vec![],
    ));
    let abdomen_y = add(hinge(
        abdomen_z,
        abdomen,
        v(0.0, 1.0, 0.0),
        (-75.0, 30.0),
        100.0 * power,
        vec![capsule(
            at(lwaist, 0.0, -0.06, 0.0),
            at(lwaist, 0.0, 0.06, 0.0),
            0.06,
        )],
    )
    .with_mass(vec![inertial(
        lwaist,
        2.261947,
        (0.013572, 0.005429, 0.013572),
    )]));
    let pelvis = at(lwaist, 0.0, 0.0, -0.165);
    let abdomen_x = add(hinge(
        abdomen_y,
        at(pelvis, 0.0, 0.0, 0.1),
        v(1.0, 0.0, 0.0),
        (-35.0, 35.0),
        100.0 * power,
        vec![capsule(
            at(pelvis, -0.02, -0.07, 0.0),
            at(pelvis, -0.02, 0.07, 0.0),
            0.09,
        )],
    )
    .with_mass(vec![inertial(
        at(pelvis, -0.02, 0.0, 0.0),
        6.616195,
        (0.125487, 0.074542, 0.125487),
    )]));
    let mut feet = Vec::new();
    // Right leg then left: the left one mirrors y and its hip x and z axes.
    for side in [-1.0f32, 1.0] {
        let thigh = at(pelvis, 0.0, 0.1 * side, -0.04);
        let hip_x = add(hinge(
            abdomen_x,
            thigh,
            v(-side, 0.0, 0.0),
            (-25.0, 5.0),
            100.0 * power,
            vec![],
        ));
        let hip_z = add(hinge(
            hip_x,
            thigh,
            v(0.0, 0.0, -side),
            (-60.0, 35.0),
            100.0 * power,
            vec![],
        ));
        let hip_y = add(hinge(
            hip_z,
            thigh,
            v(0.0, 1.0, 0.0),
            (-120.0, 20.0),
            300.0 * power,
            vec![capsule(thigh, at(thigh, 0.0, -0.01 * side, -0.34), 0.06)],
        )
        .with_mass(vec![inertial(
            at(thigh, 0.0, -0.005 * side, -0.17),
            4.751751,
            (0.13293, 0.131307, 0.033302),
        )]));
        let shin = at(thigh, 0.0, -0.01 * side, -0.403);
        let foot = at(shin, 0.0, 0.0, -0.45);
        let knee = add(hinge(
            hip_y,
            at(shin, 0.0, 0.0, 0.02),
            v(0.0, -1.0, 0.0),
            (-160.0, -2.0),
            200.0 * power,
            // The foot is fixed to the shin (no joint in the model).
            vec![
                capsule(shin, at(shin, 0.0, 0.0, -0.3), 0.049),
                Geom::Sphere(at(foot, 0.0, 0.0, 0.1), 0.075),
            ],
        )
        .with_mass(vec![
            inertial(
                at(shin, 0.0, 0.0, -0.15),
                2.755696,
                (0.059745, 0.059745, 0.014552),
            ),
            // At the foot body's origin: its sphere is placed by `pos`.
            inertial(foot, 1.767146, (0.006627, 0.006627, 0.006627)),
        ]));
        feet.push(Foot::new(knee, 0.004598));
    }
    // Right arm then left: y mirrored, and the model's own axes per side.
    for (side, shoulder1, shoulder2, elbow, range) in [
        (
            -1.0f32,
            v(2.0, 1.0, 1.0),
            v(0.0, -1.0, 1.0),
            v(0.0, -1.0, 1.0),
            (-85.0, 60.0),
        ),
        (
            1.0,
            v(2.0, -1.0, 1.0),
            v(0.0, 1.0, 1.0),
            v(0.0, -1.0, -1.0),
            (-60.0, 85.0),
        ),
    ] {
        let upper = at(torso, 0.0, 0.17 * side, 0.06);
        let first = add(hinge(0, upper, shoulder1, range, 75.0 * power, vec![]));
        let second = add(hinge(
            first,
            upper,
            shoulder2,
            range,
            75.0 * power,
            vec![capsule(upper, at(upper, 0.16, 0.16 * side, -0.16), 0.04)],
        )
        .with_mass(vec![inertial(
            at(upper, 0.08, 0.08 * side, -0.08),
            1.66108,
            (0.028349, 0.028349, 0.028349),
        )]));
        let lower = at(upper, 0.18, 0.18 * side, -0.18);
        add(hinge(
            second,
            lower,
            elbow,
            (-90.0, 50.0),
            75.0 * power,
            vec![
                capsule(
                    at(lower, 0.01, -0.01 * side, 0.01),
                    at(lower, 0.17, -0.17 * side, 0.17),
                    0.031,
                ),
                Geom::Sphere(at(lower, 0.18, -0.18 * side, 0.18), 0.04),
            ],
        )
        // At the elbow: the body's last geom is the hand, placed by `pos`.
        .with_mass(vec![inertial(lower, 1.22954, (0.01869, 0.01869, 0.01869))]));
    }
    RobotDef {
        name: "humanoid",
        links,
        feet,
        alive: Alive {
            min_z: 0.78,
            bonus: 2.0,
        },
        // PyBullet sets it to 0.8 for the Humanoid.
        initial_z: Some(0.8),
        cost_scale: 4.25,
        friction: 0.8 * FLOOR_FRICTION,
        self_collision: true,
    }
}
