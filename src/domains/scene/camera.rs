//! The 3D walkers' camera: a fixed oblique view, and the scene it shows.

use rapier3d::prelude::*;

use super::{Part, Scene, Shape};

/// A limb whose centre is this far (metres) to one side of the torso is drawn in that side's
/// colour.
const SIDE: f32 = 0.03;

/// The fixed camera: an oblique view from the robot's right, y receding up and to the right.
pub(in crate::domains) fn project(p: Vector) -> (f64, f64) {
    let depth = 0.35;
    (
        f64::from(p.x + depth * p.y),
        f64::from(p.z + 0.5 * depth * p.y),
    )
}

/// The scene the camera shows: a 1 m floor grid around the torso, and the robot's links
/// (`links`, each its colliders in `world`) drawn far to near, in the colour of their side.
pub(in crate::domains) fn scene(
    world: &ColliderSet,
    links: &[Vec<ColliderHandle>],
    torso_pose: &Pose,
) -> Scene {
    let centre = torso_pose.translation;
    let mut shapes = Vec::new();
    // A 1 m floor grid around the robot.
    let (x0, y0) = (centre.x.floor(), centre.y.floor());
    for i in -3..=3 {
        let d = i as f32;
        shapes.push((
            Part::Ground,
            Shape::Polyline(vec![
                project(Vector::new(x0 + d, y0 - 3.0, 0.0)),
                project(Vector::new(x0 + d, y0 + 3.0, 0.0)),
            ]),
        ));
        shapes.push((
            Part::Ground,
            Shape::Polyline(vec![
                project(Vector::new(x0 - 3.0, y0 + d, 0.0)),
                project(Vector::new(x0 + 3.0, y0 + d, 0.0)),
            ]),
        ));
    }
    // Far links first, so nearer ones are drawn over them; limbs coloured by the side of the
    // torso they are on.
    let mut parts: Vec<(f32, Part, Shape)> = Vec::new();
    for handles in links {
        let side = |centre: Vector| match torso_pose.inverse_transform_point(centre).y {
            y if y > SIDE => Part::Left,
            y if y < -SIDE => Part::Right,
            _ => Part::Body,
        };
        for &h in handles {
            let collider = &world[h];
            let pose = collider.position();
            match collider.shape().as_typed_shape() {
                TypedShape::Capsule(c) => {
                    let (a, b) = (
                        pose.transform_point(c.segment.a),
                        pose.transform_point(c.segment.b),
                    );
                    let shape = Shape::Capsule(project(a), project(b), f64::from(c.radius));
                    parts.push((a.y.max(b.y), side((a + b) * 0.5), shape));
                }
                TypedShape::Ball(b) => {
                    let c = pose.transform_point(Vector::ZERO);
                    let shape = Shape::Circle(project(c), f64::from(b.radius));
                    parts.push((c.y, side(c), shape));
                }
                _ => {}
            }
        }
    }
    parts.sort_by(|a, b| b.0.total_cmp(&a.0));
    shapes.extend(parts.into_iter().map(|(_, part, s)| (part, s)));
    let (cx, cy) = project(Vector::new(centre.x, centre.y, 0.0));
    Scene {
        shapes,
        center: (cx, cy + 0.7),
        width: 4.0,
        height: 2.4,
    }
}
