//! What a domain looks like, for drawing (`prac render`, `prac-sim play --render`): shapes in
//! world coordinates (metres, y up) and where to look.

use rapier2d::prelude::*;

pub(super) mod camera;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Part {
    /// The robot (or lander, or pendulum); a 3D robot's torso and middle.
    Body,
    /// A 3D robot's limbs on its left and right sides (seen from its torso).
    Left,
    Right,
    /// Terrain and floor.
    Ground,
    /// Markers such as the helipad flags.
    Detail,
}

#[derive(Clone, Debug, PartialEq)]
pub enum Shape {
    Polygon(Vec<(f64, f64)>),
    Circle((f64, f64), f64),
    /// A segment swept by a disc.
    Capsule((f64, f64), (f64, f64), f64),
    Polyline(Vec<(f64, f64)>),
}

#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    pub shapes: Vec<(Part, Shape)>,
    /// Centre of the view and the extent that must be visible, in world units.
    pub center: (f64, f64),
    pub(crate) width: f64,
    pub height: f64,
}

fn point(pose: &Pose, p: Vector) -> (f64, f64) {
    let q = pose.transform_point(p);
    (f64::from(q.x), f64::from(q.y))
}

/// Every collider of a rapier world as shapes; `ground` ones are marked as ground.
pub(crate) fn world_shapes(
    colliders: &ColliderSet,
    is_ground: impl Fn(ColliderHandle) -> bool,
) -> Vec<(Part, Shape)> {
    let mut shapes = Vec::new();
    for (handle, collider) in colliders.iter() {
        let part = if is_ground(handle) {
            Part::Ground
        } else {
            Part::Body
        };
        let pose = collider.position();
        let shape = match collider.shape().as_typed_shape() {
            TypedShape::Ball(b) => Shape::Circle(point(pose, Vector::ZERO), f64::from(b.radius)),
            TypedShape::Cuboid(c) => {
                let (hx, hy) = (c.half_extents.x, c.half_extents.y);
                Shape::Polygon(
                    [(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)]
                        .iter()
                        .map(|&(x, y)| point(pose, Vector::new(x, y)))
                        .collect(),
                )
            }
            TypedShape::Capsule(c) => Shape::Capsule(
                point(pose, c.segment.a),
                point(pose, c.segment.b),
                f64::from(c.radius),
            ),
            TypedShape::ConvexPolygon(p) => {
                Shape::Polygon(p.points().iter().map(|&v| point(pose, v)).collect())
            }
            TypedShape::Polyline(p) => {
                Shape::Polyline(p.vertices().iter().map(|&v| point(pose, v)).collect())
            }
            TypedShape::Segment(s) => Shape::Polyline(vec![point(pose, s.a), point(pose, s.b)]),
            TypedShape::HalfSpace(_) => {
                let (x, y) = point(pose, Vector::ZERO);
                Shape::Polyline(vec![(x - 1e3, y), (x + 1e3, y)])
            }
            _ => continue,
        };
        shapes.push((part, shape));
    }
    shapes
}
