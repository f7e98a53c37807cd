//! ant.xml as PyBullet's AntBulletEnv loads it.

use crate::domains::spatial::{
    Alive, FLOOR_FRICTION, Geom, LinkDef, RobotDef, capsule, hinge, inertial, v,
};
use crate::domains::walker_base::Foot;
use rapier3d::prelude::Vector;

/// ant.xml: a sphere torso at 0.75 m with four legs of hip (about z, +-40 deg) and ankle hinges;
/// PyBullet's power 2.5 x 100 = 250 N m per unit action.
pub(in crate::domains) fn ant() -> RobotDef {
    let torso = v(0.0, 0.0, 0.75);
    let r = 0.08;
    let torque = 250.0;
    let mut torso_geoms = vec![Geom::Sphere(torso, 0.25)];
    let mut torso_mass = vec![inertial(torso, 65.449847, (1.636246, 1.636246, 1.636246))];
    // A leg segment's box inertia, and a foot's, as PyBullet computes them.
    let segment = (0.16394, 0.16394, 0.252698);
    let foot = (0.526318, 0.526318, 0.922859);
    let mut links = Vec::new();
    // (leg direction in x-y, ankle axis, ankle range): front_left, front_right, left_back,
    // right_back, in the file's order.
    let legs = [
        ((1.0, 1.0), v(-1.0, 1.0, 0.0), (30.0, 100.0)),
        ((-1.0, 1.0), v(1.0, 1.0, 0.0), (-100.0, -30.0)),
        ((-1.0, -1.0), v(-1.0, 1.0, 0.0), (-100.0, -30.0)),
        ((1.0, -1.0), v(1.0, 1.0, 0.0), (30.0, 100.0)),
    ];
    let mut feet = Vec::new();
    for ((dx, dy), ankle_axis, ankle_range) in legs {
        let step = v(0.2 * dx, 0.2 * dy, 0.0);
        let hip = torso + step;
        let ankle = hip + step;
        torso_geoms.push(capsule(torso, hip, r));
        torso_mass.push(inertial(torso + step * 0.5, 7.83155, segment));
        let hip_link = links.len() + 1;
        links.push(
            hinge(
                0,
                hip,
                v(0.0, 0.0, 1.0),
                (-40.0, 40.0),
                torque,
                vec![capsule(hip, ankle, r)],
            )
            .with_mass(vec![inertial(hip + step * 0.5, 7.83155, segment)]),
        );
        feet.push(Foot::new(links.len() + 1, 0.009364));
        links.push(
            hinge(
                hip_link,
                ankle,
                ankle_axis,
                ankle_range,
                torque,
                vec![capsule(ankle, ankle + step * 2.0, r)],
            )
            .with_mass(vec![inertial(ankle + step, 13.51844, foot)]),
        );
    }
    let root = LinkDef {
        parent: None,
        origin: torso,
        axis: Vector::ZERO,
        axis_length: 1.0,
        range: (0.0, 0.0),
        torque: 0.0,
        geoms: torso_geoms,
        inertials: torso_mass,
    };
    links.insert(0, root);
    RobotDef {
        name: "ant",
        links,
        feet,
        // 0.25 is the torso sphere's radius: it dies when it scrapes the ground.
        alive: Alive {
            min_z: 0.26,
            bonus: 1.0,
        },
        initial_z: None,
        cost_scale: 1.0,
        friction: 1.5 * FLOOR_FRICTION,
        self_collision: false,
    }
}
