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
