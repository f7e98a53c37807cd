//! walker2d.xml as PyBullet's Walker2DBulletEnv loads it.

use crate::domains::planar::{Alive, RobotDef, hinge, link};
use crate::domains::walker_base::Foot;

/// walker2d.xml: a torso on two hopper-like legs (gear 100, feet 30; PyBullet power 0.4).
pub(in crate::domains) fn walker() -> RobotDef {
    let deg = std::f32::consts::PI / 180.0;
    let mut links = vec![link((0.0, 1.45), (0.0, 1.05), 0.05, 3.665192, 0.112644)]; // torso
    let mut joints = Vec::new();
    // Right leg (links 1-3), then left leg (links 4-6): the same shape, PyBullet's joint order.
    for first in [1, 4] {
        links.extend([
            link((0.0, 1.05), (0.0, 0.6), 0.05, 4.05789, 0.145171), // thigh
            link((0.0, 0.6), (0.0, 0.1), 0.04, 2.781357, 0.106897), // leg
            link((0.0, 0.1), (0.2, 0.1), 0.06, 3.166725, 0.052779), // foot
        ]);
        joints.extend([
            hinge(0, first, (0.0, 1.05), (-150.0 * deg, 0.0), 40.0, 1.0),
            hinge(first, first + 1, (0.0, 0.6), (-150.0 * deg, 0.0), 40.0, 1.0),
            hinge(
                first + 1,
                first + 2,
                (0.0, 0.1),
                (-45.0 * deg, 45.0 * deg),
                12.0,
                1.0,
            ),
        ]);
    }
    RobotDef {
        name: "walker",
        links,
        joints,
        feet: vec![Foot::new(3, 0.004899), Foot::new(6, 0.004899)],
        alive: Alive::Upright { min_z: 0.8 },
        root: (0.0, 0.0),
    }
}
