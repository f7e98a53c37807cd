//! The floor's contacts as Bullet keeps them for PyBullet's walkers, through rapier's
//! contact-modification hook. Bullet collides a link's capsule or sphere with the floor plane
//! by adding one point per substep, the shape's lowest, to a persistent manifold of at most four
//! that it refreshes each substep and whose every point the solver takes. A capsule landing level
//! thus touches down at one end first and tilts onto the other a substep later, where rapier's
//! manifold holds both ends at once. Each point we hand the solver stands in for one of rapier's
//! (its warm-start and lever-arm slot), so a pair gets at most as many as rapier found within its
//! 2 cm prediction distance (the deepest): one for a sphere, where Bullet's rolling ball could
//! hold several. Facts from bullet3 (btConvexPlaneCollisionAlgorithm,
//! btPersistentManifold, btMultiSphereShape, BulletMJCFImporter); docs/domains.md measures what
//! they change.

use std::collections::HashMap;
use std::sync::Mutex;

use nalgebra::Vector3;

type V3 = Vector3<f32>;

/// Bullet's MANIFOLD_CACHE_SIZE.
const MANIFOLD_POINTS: usize = 4;
/// gContactBreakingThreshold: a shape's contact breaking threshold is this times its angular
/// motion disc.
const CONTACT_BREAKING_FRACTION: f32 = 0.02;
/// The collision margin of the btMultiSphereShape PyBullet's MJCF importer makes of a `fromto`
/// capsule (CONVEX_DISTANCE_MARGIN), which its bounding box adds to the spheres' extents.
const MULTI_SPHERE_MARGIN: f32 = 0.04;
/// Capsule ends at heights this close (metres) are level.
const LEVEL_TOLERANCE: f32 = 1e-6;

/// A link's shape as Bullet bounds it: a `fromto` capsule (two spheres with a margin) or a
/// sphere, in the link's centre-of-mass frame.
pub(super) enum BoundedShape {
    Capsule(V3, V3, f32),
    Sphere(V3, f32),
}

/// A link's contact breaking threshold, `0.02 x` its angular motion disc (the half-diagonal of
/// its shapes' bounding box plus the box centre's distance from the centre of mass). A planar
/// walker's capsule is a 3D one in its plane.
pub(super) fn contact_breaking_threshold(shapes: &[BoundedShape]) -> f32 {
    let mut low = V3::repeat(f32::INFINITY);
    let mut high = V3::repeat(f32::NEG_INFINITY);
    for shape in shapes {
        let (ends, pad) = match *shape {
            BoundedShape::Capsule(a, b, r) => ([a, b], r + MULTI_SPHERE_MARGIN),
            BoundedShape::Sphere(c, r) => ([c, c], r),
        };
        for end in ends {
            low = low.inf(&end.add_scalar(-pad));
            high = high.sup(&end.add_scalar(pad));
        }
    }
    let disc = 0.5 * (high - low).norm() + (0.5 * (high + low)).norm();
    CONTACT_BREAKING_FRACTION * disc
}

#[derive(Clone, Copy, Debug)]
struct ManifoldPoint {
    /// On the link, in its collider's frame.
    on_link: V3,
    /// On the floor, in world coordinates.
    on_floor: V3,
    /// Along the floor's normal, negative when penetrating.
    distance: f32,
}

/// One link collider's manifold with the floor.
#[derive(Clone, Debug)]
struct FloorManifold {
    threshold: f32,
    points: Vec<ManifoldPoint>,
    /// The substep whose collision detection last saw the pair.
    seen: u64,
}

impl FloorManifold {
    fn new(threshold: f32) -> FloorManifold {
        FloorManifold {
            threshold,
            points: Vec::with_capacity(MANIFOLD_POINTS),
            seen: 0,
        }
    }

    /// btPersistentManifold::refreshContactPoints: each point's distance at the link's pose,
    /// before the new point joins, as Bullet's compound shapes (every MJCF link whose geom is
    /// off its centre of mass) refresh their children's manifolds;
    /// then, last first, those beyond the threshold or drifted along the floor by more than it
    /// leave (the last point taking the slot).
    fn refresh(&mut self, to_world: impl Fn(V3) -> V3, up: V3) {
        for point in &mut self.points {
            point.distance = (to_world(point.on_link) - point.on_floor).dot(&up);
        }
        let limit = self.threshold;
        for i in (0..self.points.len()).rev() {
            let point = self.points[i];
            let projected = to_world(point.on_link) - up * point.distance;
            let drift = (point.on_floor - projected).norm_squared();
            if point.distance > limit || drift > limit * limit {
                self.points.swap_remove(i);
            }
        }
    }

    /// btConvexPlaneCollisionAlgorithm's one point: the shape's lowest (`lowest`, in the
    /// collider's frame) joins the manifold if closer than the threshold, replacing a point
    /// within the threshold of it on the link, else added, else (four already) in the slot
    /// btPersistentManifold::sortCachedPoints picks.
    fn add_lowest(&mut self, lowest: V3, to_world: impl Fn(V3) -> V3, up: V3) {
        let world = to_world(lowest);
        let distance = world.dot(&up);
        if distance >= self.threshold {
            return;
        }
        let point = ManifoldPoint {
            on_link: lowest,
            on_floor: world - up * distance,
            distance,
        };
        let mut nearest = None;
        let mut shortest = self.threshold * self.threshold;
        for (i, old) in self.points.iter().enumerate() {
            let d = (old.on_link - lowest).norm_squared();
            if d < shortest {
                shortest = d;
                nearest = Some(i);
            }
        }
        match nearest {
            Some(i) => self.points[i] = point,
            None if self.points.len() < MANIFOLD_POINTS => self.points.push(point),
            None => {
                let slot = self.replaced_slot(&point);
                self.points[slot] = point;
            }
        }
    }

    /// sortCachedPoints: keep the deepest point and the largest area the other three span with
    /// the new one (Bullet's three-point area), the first slot on ties.
    fn replaced_slot(&self, new: &ManifoldPoint) -> usize {
        let p = |i: usize| self.points[i].on_link;
        let mut deepest = None;
        let mut depth = new.distance;
        for (i, old) in self.points.iter().enumerate() {
            if old.distance < depth {
                depth = old.distance;
                deepest = Some(i);
            }
        }
        let area = |skip: usize, a: usize, b: usize, c: usize| {
            if deepest == Some(skip) {
                0.0
            } else {
                (new.on_link - p(a)).cross(&(p(b) - p(c))).norm_squared()
            }
        };
        let areas = [
            area(0, 1, 3, 2),
            area(1, 0, 3, 2),
            area(2, 0, 3, 1),
            area(3, 0, 2, 1),
        ];
        let mut slot = 0;
        for (i, &a) in areas.iter().enumerate() {
            if a > areas[slot] {
                slot = i;
            }
        }
        slot
    }

    /// The `n` deepest points, in the manifold's order.
    fn deepest(&self, n: usize) -> impl Iterator<Item = &ManifoldPoint> {
        let cutoff = if n == 0 {
            f32::NEG_INFINITY
        } else if n >= self.points.len() {
            f32::INFINITY
        } else {
            let mut depths = [f32::INFINITY; MANIFOLD_POINTS];
            for (d, p) in depths.iter_mut().zip(&self.points) {
                *d = p.distance;
            }
            depths.sort_by(f32::total_cmp);
            depths[n - 1]
        };
        self.points
            .iter()
            .filter(move |p| p.distance <= cutoff)
            .take(n)
    }
}

/// The hook: every link collider's manifold with the floor (a half-space through the origin
/// with normal `up`), keyed by the collider's raw handle.
#[derive(Debug)]
pub(super) struct FloorContacts {
    floor: (u32, u32),
    up: V3,
    state: Mutex<FloorState>,
}

#[derive(Debug, Default)]
struct FloorState {
    substep: u64,
    manifolds: HashMap<(u32, u32), FloorManifold>,
}

impl FloorContacts {
    /// `floor` is the floor collider's raw handle.
    pub(super) fn new(floor: (u32, u32), up: V3) -> FloorContacts {
        FloorContacts {
            floor,
            up,
            state: Mutex::new(FloorState::default()),
        }
    }

    /// A link collider (raw handle) and its link's contact breaking threshold.
    pub(super) fn add_link_collider(&mut self, collider: (u32, u32), threshold: f32) {
        self.state_mut()
            .manifolds
            .insert(collider, FloorManifold::new(threshold));
    }

    /// Call before each physics step.
    pub(super) fn next_substep(&mut self) {
        self.state_mut().substep += 1;
    }

    fn state_mut(&mut self) -> &mut FloorState {
        self.state.get_mut().unwrap_or_else(|e| e.into_inner())
    }

    /// The link collider of a pair with the floor, and whether the floor is the first.
    fn link_of(&self, first: (u32, u32), second: (u32, u32)) -> Option<((u32, u32), bool)> {
        if first == self.floor {
            Some((second, true))
        } else if second == self.floor {
            Some((first, false))
        } else {
            None
        }
    }

    /// Updates the link collider's manifold for this substep, if the hook keeps one for it:
    /// `lowest` is its shape's lowest point (in its frame), `to_world` its pose. Returns at most
    /// `capacity` of its points (the deepest) in world coordinates with their distances; None
    /// for a collider without a manifold.
    fn update(
        &self,
        collider: (u32, u32),
        lowest: V3,
        to_world: impl Fn(V3) -> V3 + Copy,
        capacity: usize,
    ) -> Option<FloorPoints> {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        let substep = state.substep;
        let manifold = state.manifolds.get_mut(&collider)?;
        // A pair rapier did not see last substep was over 2 cm apart: Bullet's points are gone.
        if manifold.seen + 1 != substep {
            manifold.points.clear();
        }
        manifold.seen = substep;
        manifold.refresh(to_world, self.up);
        manifold.add_lowest(lowest, to_world, self.up);
        let mut out = FloorPoints::default();
        for point in manifold.deepest(capacity) {
            out.points[out.len] = (to_world(point.on_link), point.distance);
            out.len += 1;
        }
        Some(out)
    }
}

/// Up to a manifold's worth of contact points on a link (world coordinates) with their
/// distances to the floor, kept on the stack: a step allocates nothing.
#[derive(Default)]
struct FloorPoints {
    points: [(V3, f32); MANIFOLD_POINTS],
    len: usize,
}

impl FloorPoints {
    fn as_slice(&self) -> &[(V3, f32)] {
        &self.points[..self.len]
    }
}

/// The hook for one rapier crate (`$rapier`: rapier2d or rapier3d, whose solver takes at most
/// `$max_contacts` points per manifold); `$to3` and `$from3` turn its vectors into and out of 3D
/// ones (a 2D walker's plane is z = 0).
macro_rules! floor_contact_hooks {
    ($rapier:ident, $max_contacts:expr, $to3:expr, $from3:expr) => {
        impl $rapier::pipeline::PhysicsHooks for FloorContacts {
            fn modify_solver_contacts(
                &self,
                context: &mut $rapier::pipeline::ContactModificationContext,
            ) {
                use $rapier::prelude::TypedShape;
                let to3 = $to3;
                let from3 = $from3;
                let raw = |h: $rapier::prelude::ColliderHandle| h.into_raw_parts();
                let Some((link, floor_first)) =
                    self.link_of(raw(context.collider1), raw(context.collider2))
                else {
                    return;
                };
                let Some(collider) =
                    context
                        .colliders
                        .get($rapier::prelude::ColliderHandle::from_raw_parts(
                            link.0, link.1,
                        ))
                else {
                    return;
                };
                let pose = *collider.position();
                let down = to3(pose.inverse_transform_vector(from3(-self.up)));
                // btMultiSphereShape's support: the first sphere unless the second is lower,
                // then its surface point straight down. A capsule level to within float noise
                // is level (Bullet's ties are exact, and its level feet stay exactly level).
                let (centre, radius) = match collider.shape().as_typed_shape() {
                    TypedShape::Capsule(c) => {
                        let (a, b) = (to3(c.segment.a), to3(c.segment.b));
                        let lower = (b - a).dot(&down) > LEVEL_TOLERANCE;
                        (if lower { b } else { a }, c.radius)
                    }
                    TypedShape::Ball(b) => (V3::zeros(), b.radius),
                    _ => return,
                };
                let lowest = centre + down * radius;
                let to_world = |p: V3| to3(pose.transform_point(from3(p)));
                let Some(rigid) = context.rigid_mut() else {
                    return;
                };
                let Some(&template) = rigid.solver_contacts.first() else {
                    return;
                };
                // Each solver contact names a distinct point of rapier's manifold. Rewritten in
                // place: the container keeps its capacity, so a step allocates nothing.
                let capacity = rigid.manifold.points.len().min($max_contacts);
                let up = self.up;
                let Some(points) = self.update(link, lowest, to_world, capacity) else {
                    return;
                };
                let contacts = &mut *rigid.solver_contacts;
                contacts.clear();
                for (k, &(on_link, distance)) in points.as_slice().iter().enumerate() {
                    let on_floor = on_link - up * distance;
                    let (first, second) = if floor_first {
                        (on_floor, on_link)
                    } else {
                        (on_link, on_floor)
                    };
                    let mut contact = template;
                    contact.anchor1 = from3(first);
                    contact.anchor2 = from3(second);
                    contact.dist = distance;
                    contact.contact_id = [k as _];
                    contacts.push(contact);
                }
            }
        }
    };
}

floor_contact_hooks!(
    rapier2d,
    2,
    |v: rapier2d::math::Vector| V3::new(v.x, v.y, 0.0),
    |v: V3| rapier2d::math::Vector::new(v.x, v.y)
);
floor_contact_hooks!(
    rapier3d,
    MANIFOLD_POINTS,
    |v: rapier3d::math::Vector| V3::new(v.x, v.y, v.z),
    |v: V3| rapier3d::math::Vector::new(v.x, v.y, v.z)
);

#[cfg(test)]
mod tests {
    use super::*;

    const UP: V3 = V3::new(0.0, 0.0, 1.0);

    #[test]
    fn the_threshold_is_bullets_for_the_hoppers_foot() {
        // PyBullet: half-extents (0.295, 0.1, 0.1) about the centre of mass, 6.543 mm.
        let foot = [BoundedShape::Capsule(
            V3::new(-0.195, 0.0, 0.0),
            V3::new(0.195, 0.0, 0.0),
            0.06,
        )];
        assert!((contact_breaking_threshold(&foot) - 0.006543).abs() < 1e-6);
    }

    #[test]
    fn one_point_joins_per_substep_and_leaves_past_the_threshold() {
        let mut manifold = FloorManifold::new(0.0065);
        // A level capsule 1 mm above the floor: its first sphere's bottom joins.
        let heel = V3::new(-0.2, 0.0, -0.06);
        let at = |z: f32| move |p: V3| p + V3::new(0.0, 0.0, z);
        manifold.refresh(at(0.061), UP);
        manifold.add_lowest(heel, at(0.061), UP);
        assert_eq!(manifold.points.len(), 1);
        assert!((manifold.points[0].distance - 0.001).abs() < 1e-6);
        // The toe, lower now, joins as a second point; the heel stays.
        let tilted = |p: V3| p + V3::new(0.0, 0.0, 0.06 + 0.01 * p.x);
        manifold.refresh(tilted, UP);
        manifold.add_lowest(V3::new(0.2, 0.0, -0.06), tilted, UP);
        assert_eq!(manifold.points.len(), 2);
        // Lifted 1 cm: both leave.
        manifold.refresh(at(0.07), UP);
        assert!(manifold.points.is_empty());
    }

    #[test]
    fn a_point_slid_along_the_floor_past_the_threshold_leaves() {
        let mut manifold = FloorManifold::new(0.0065);
        let heel = V3::new(0.0, 0.0, -0.06);
        manifold.add_lowest(heel, |p| p + V3::new(0.0, 0.0, 0.06), UP);
        manifold.refresh(|p| p + V3::new(0.006, 0.0, 0.06), UP);
        assert_eq!(manifold.points.len(), 1);
        manifold.refresh(|p| p + V3::new(0.007, 0.0, 0.06), UP);
        assert!(manifold.points.is_empty());
    }

    #[test]
    fn a_full_manifold_keeps_its_deepest_point() {
        let mut manifold = FloorManifold::new(0.01);
        let corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)];
        for (i, (x, y)) in corners.into_iter().enumerate() {
            let depth = if i == 1 { -0.005 } else { 0.0 };
            manifold.add_lowest(V3::new(x, y, depth), |p| p, UP);
        }
        assert_eq!(manifold.points.len(), 4);
        manifold.add_lowest(V3::new(0.9, -0.9, 0.0), |p| p, UP);
        // Within the threshold of no point: it replaces one, never the deepest.
        assert_eq!(manifold.points.len(), 4);
        assert!(manifold.points.iter().any(|p| p.distance == -0.005));
        assert!(manifold.points.iter().any(|p| p.on_link.x == 0.9));
    }
}
