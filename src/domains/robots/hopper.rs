//! hopper.xml as PyBullet's HopperBulletEnv loads it.

use crate::domains::planar::{Alive, RobotDef, hinge, link};
use crate::domains::walker_base::Foot;

pub(in crate::domains) fn hopper() -> RobotDef {
    let deg = std::f32::consts::PI / 180.0;
    RobotDef {
        name: "hopper",
        links: vec![
            link((0.0, 1.45), (0.0, 1.05), 0.05, 3.665192, 0.112644), // torso
            link((0.0, 1.05), (0.0, 0.6), 0.05, 4.05789, 0.145171),   // thigh
            link((0.0, 0.6), (0.0, 0.1), 0.04, 2.781357, 0.106897),   // leg
            link((-0.13, 0.1), (0.26, 0.1), 0.06, 5.315574, 0.171915), // foot
        ],
        joints: vec![
            hinge(0, 1, (0.0, 1.05), (-150.0 * deg, 0.0), 75.0, 1.0),
            hinge(1, 2, (0.0, 0.6), (-150.0 * deg, 0.0), 75.0, 1.0),
            hinge(2, 3, (0.0, 0.1), (-45.0 * deg, 45.0 * deg), 75.0, 1.0),
        ],
        feet: vec![Foot::new(3, 0.006543)],
        alive: Alive::Upright { min_z: 0.8 },
        root: (0.0, 0.0),
    }
}
