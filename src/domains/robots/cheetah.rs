//! half_cheetah.xml as PyBullet's HalfCheetahBulletEnv loads it.

use crate::domains::planar::{Alive, Capsule, Inertial, LinkDef, RobotDef, hinge, mj_capsule};
use crate::domains::walker_base::Foot;

/// PyBullet's own half_cheetah.xml (pybullet_data, not gym's): a torso with a head, back and front
/// legs of three links each, hinges about +y, feet of 10 kg, the front leg's wider ranges; every
/// link's mass sits at its joint (the importer ignores the geoms' `pos`). PyBullet's power 0.9 x
/// its power_coef (120, 90, 60, 140, 60, 30).
pub(in crate::domains) fn cheetah() -> RobotDef {
    let torso = (0.0, 0.7);
    let at = |base: (f32, f32), offset: (f32, f32)| (base.0 + offset.0, base.1 + offset.1);
    let (bthigh, fthigh) = (at(torso, (-0.5, 0.0)), at(torso, (0.5, 0.0)));
    let bshin = at(bthigh, (0.16, -0.25));
    let bfoot = at(bshin, (-0.28, -0.14));
    let fshin = at(fthigh, (-0.14, -0.24));
    let ffoot = at(fshin, (0.13, -0.18));
    let r = 0.046;
    let body = |origin: (f32, f32), capsules: Vec<Capsule>, mass: f32, inertia: f32| LinkDef {
        origin,
        capsules,
        inertial: Inertial {
            com: origin,
            mass,
            inertia,
        },
    };
    RobotDef {
        name: "cheetah",
        links: vec![
            body(
                torso,
                vec![
                    Capsule {
                        a: (-0.5, 0.7),
                        b: (0.5, 0.7),
                        radius: r,
                    },
                    mj_capsule(torso, (0.6, 0.1), 0.87, 0.15, r), // head
                ],
                9.457333,
                1.564635,
            ),
            body(
                bthigh,
                vec![mj_capsule(bthigh, (0.1, -0.13), -3.8, 0.145, r)],
                2.335527,
                0.043289,
            ),
            body(
                bshin,
                vec![mj_capsule(bshin, (-0.14, -0.07), -2.03, 0.15, r)],
                2.402003,
                0.043925,
            ),
            body(
                bfoot,
                vec![mj_capsule(bfoot, (0.03, -0.097), -0.27, 0.094, r)],
                10.0,
                0.09446,
            ),
            body(
                fthigh,
                vec![mj_capsule(fthigh, (-0.07, -0.12), 0.52, 0.133, r)],
                2.175984,
                0.035076,
            ),
            body(
                fshin,
                vec![mj_capsule(fshin, (0.065, -0.09), -0.6, 0.106, r)],
                1.817013,
                0.023169,
            ),
            body(
                ffoot,
                vec![mj_capsule(ffoot, (0.045, -0.07), -0.6, 0.07, r)],
                10.0,
                0.085062,
            ),
        ],
        joints: vec![
            hinge(0, 1, bthigh, (-0.52, 1.05), 0.9 * 120.0, -1.0),
            hinge(1, 2, bshin, (-0.785, 0.785), 0.9 * 90.0, -1.0),
            hinge(2, 3, bfoot, (-0.4, 0.785), 0.9 * 60.0, -1.0),
            hinge(0, 4, fthigh, (-1.5, 0.8), 0.9 * 140.0, -1.0),
            hinge(4, 5, fshin, (-1.2, 1.1), 0.9 * 60.0, -1.0),
            hinge(5, 6, ffoot, (-3.1, -0.3), 0.9 * 30.0, -1.0),
        ],
        // PyBullet's foot_list: ffoot, fshin, fthigh, bfoot, bshin, bthigh.
        feet: vec![
            Foot::new(6, 0.004989),
            Foot::new(5, 0.006239),
            Foot::new(4, 0.007272),
            Foot::new(3, 0.005521),
            Foot::new(2, 0.007904),
            Foot::new(1, 0.008085),
        ],
        alive: Alive::NoContact {
            forbidden: vec![1, 2, 4, 5],
        },
        root: torso,
    }
}
