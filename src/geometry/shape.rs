//! A solid: a parry shape at a pose, with its signed distance. Obstacles, liquid regions and
//! (with mass properties) rigid bodies are solids.

use crate::math::{Pose, SharedShape, Vec3};

/// A built shape: parry geometry plus pose. Its signed distance is negative inside.
#[derive(Clone)]
pub struct Solid {
    /// parry geometry in its local frame.
    pub shape: SharedShape,
    /// Local-to-world pose.
    pub pose: Pose,
}

impl std::fmt::Debug for Solid {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Solid").field("pose", &self.pose).finish_non_exhaustive()
    }
}

impl Solid {
    /// Signed distance at `x` (negative inside).
    #[inline]
    pub fn sdf(&self, x: Vec3) -> f64 {
        self.shape.distance_to_point(&self.pose, x, false)
    }

    /// World-space axis-aligned bounds `(min, max)`.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let aabb = self.shape.compute_aabb(&self.pose);
        (aabb.mins, aabb.maxs)
    }
}

/// Thickness of a shape, m: 2·V/S, its volume over half its surface area (from its surface
/// mesh). Exact for a plate, two thirds of a ball's radius; infinite for a shape without a
/// closed surface (a half-space).
pub fn thickness(shape: &SharedShape) -> f64 {
    let (verts, tris) = crate::geometry::mesh::surface_mesh(shape);
    let area: f64 = tris
        .iter()
        .map(|t| {
            let [a, c, d] = t.map(|i| verts[i as usize]);
            0.5 * (c - a).cross(d - a).length()
        })
        .sum();
    if area > 0.0 {
        2.0 * shape.mass_properties(1.0).mass() / area
    } else {
        f64::INFINITY
    }
}

/// Depth of a shape, m: the largest distance from its surface of a point inside it (the
/// radius of its largest inscribed ball). Exact for cuboids (the smallest half extent),
/// balls, capsules and cylinders; otherwise the largest depth of a lattice of at most about
/// 10⁵ points over its bounds, spaced at most a quarter of its [`thickness`] (2·V/S) apart
/// (under by at most that spacing). A body thinner than a cell everywhere (depth under half
/// a cell) seals the liquid as it moves (see `geometry::seal`).
pub fn depth(shape: &SharedShape) -> f64 {
    if let Some(c) = shape.as_cuboid() {
        return c.half_extents.min_element();
    }
    if let Some(b) = shape.as_ball() {
        return b.radius;
    }
    if let Some(c) = shape.as_capsule() {
        return c.radius;
    }
    if let Some(c) = shape.as_cylinder() {
        return c.half_height.min(c.radius);
    }
    let aabb = shape.compute_local_aabb();
    let ext = aabb.maxs - aabb.mins;
    if !ext.is_finite() {
        return f64::INFINITY;
    }
    let coarse = (ext.x * ext.y * ext.z / 1e5).cbrt();
    let h = (0.25 * thickness(shape)).max(coarse).max(1e-12);
    let c = (ext / h).ceil();
    let n = [c.x as u32, c.y as u32, c.z as u32];
    let identity = Pose::IDENTITY;
    let mut deepest: f64 = 0.0;
    for k in 0..=n[2] {
        for j in 0..=n[1] {
            for i in 0..=n[0] {
                let p = aabb.mins + Vec3::new(i as f64, j as f64, k as f64) * h;
                deepest = deepest.max(-shape.distance_to_point(&identity, p, false));
            }
        }
    }
    deepest
}

impl Solid {
    /// A shape at a pose.
    pub fn new(shape: SharedShape, pose: Pose) -> Solid {
        Solid { shape, pose }
    }

    /// The axis-aligned box from `min` to `max`.
    pub fn aabb(min: Vec3, max: Vec3) -> Solid {
        let half = 0.5 * (max - min);
        Solid {
            shape: SharedShape::cuboid(half.x, half.y, half.z),
            pose: Pose::from_translation(0.5 * (min + max)),
        }
    }
}
