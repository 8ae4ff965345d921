//! Shapes as scene files write them, and their parry counterparts: one path from a TOML
//! table to a [`Solid`], for every kind of shape.

use crate::geometry::shape::Solid;
use crate::math::{v3, Arr3, Pose, Rotation, SharedShape, Vec3};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// A shape as written in a scene file. All lengths in metres, in the shape's local frame
/// (capsules and cylinders have their axis along local y, as in parry).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum ShapeSpec {
    /// An axis-aligned box given by two corners (before `position`/rotation are applied).
    Box {
        /// Lower corner.
        min: Arr3,
        /// Upper corner.
        max: Arr3,
    },
    /// A box centred on the local origin.
    Cuboid {
        /// Half the side lengths.
        half_extents: Arr3,
    },
    /// A sphere.
    Ball {
        /// Radius.
        radius: f64,
    },
    /// A capsule along local y.
    Capsule {
        /// Half the length of the axis segment.
        half_height: f64,
        /// Radius.
        radius: f64,
    },
    /// A cylinder along local y.
    Cylinder {
        /// Half the height.
        half_height: f64,
        /// Radius.
        radius: f64,
    },
    /// The convex hull of the given points.
    ConvexHull {
        /// Points in the local frame.
        points: Vec<Arr3>,
    },
    /// A closed triangle mesh from a Wavefront OBJ file. A relative path is taken from the
    /// scene file's folder (for built-in scenes, `assets/scenes/`).
    Mesh {
        /// Path of the OBJ file.
        obj: String,
        /// Uniform scale applied to the vertices.
        #[serde(default = "one")]
        scale: f64,
        /// What to do with a mesh that fails its checks (not closed, inconsistently wound,
        /// non-manifold, self-intersecting, wrongly nested shells): `"none"` (default) refuses
        /// it; `"convex_hull"` uses the convex hull of its vertices instead, with a warning
        /// (right for a convex object exported with holes, wrong for a concave one).
        #[serde(default)]
        repair: MeshRepair,
    },
}

/// The fallback for a mesh that fails its checks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MeshRepair {
    /// Refuse the mesh.
    #[default]
    None,
    /// Use the convex hull of its vertices.
    ConvexHull,
}

fn one() -> f64 {
    1.0
}

/// Orientation given as an axis and an angle in degrees.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AxisAngle {
    /// Rotation axis (need not be normalised, must not be zero).
    pub axis: Arr3,
    /// Angle in degrees.
    pub degrees: f64,
}

/// A shape with a pose: `position` moves the local origin, the orientation is either a
/// unit quaternion `[w, x, y, z]` or an axis–angle (not both; neither means identity).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Placed {
    /// The shape.
    pub shape: ShapeSpec,
    /// Translation of the local origin, metres.
    #[serde(default)]
    pub position: Arr3,
    /// Orientation as a quaternion `[w, x, y, z]`; normalised on load.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub quaternion: Option<[f64; 4]>,
    /// Orientation as axis and angle.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis_angle: Option<AxisAngle>,
}

fn all_finite(xs: &[f64]) -> bool {
    xs.iter().all(|x| x.is_finite())
}

fn positive(name: &str, x: f64) -> Result<(), String> {
    if x.is_finite() && x > 0.0 {
        Ok(())
    } else {
        Err(format!("{name} must be a positive number, got {x}"))
    }
}

impl ShapeSpec {
    /// The parry shape and the offset of its local origin (non-zero only for `box`).
    /// `base` is the folder relative mesh paths start from.
    pub fn build(&self, base: &Path) -> Result<(SharedShape, Vec3), String> {
        self.build_noting(base, &mut Vec::new())
    }

    /// [`ShapeSpec::build`], adding to `notes` what was repaired (see [`MeshRepair`]).
    pub fn build_noting(
        &self,
        base: &Path,
        notes: &mut Vec<String>,
    ) -> Result<(SharedShape, Vec3), String> {
        match self {
            ShapeSpec::Box { min, max } => {
                if !all_finite(min) || !all_finite(max) {
                    return Err("box corners must be finite numbers".into());
                }
                let (lo, hi) = (v3(*min), v3(*max));
                let half = (hi - lo) * 0.5;
                if half.min_element() <= 0.0 {
                    return Err(format!("box max {max:?} must exceed min {min:?} on every axis"));
                }
                Ok((SharedShape::cuboid(half.x, half.y, half.z), (lo + hi) * 0.5))
            }
            ShapeSpec::Cuboid { half_extents: h } => {
                for (a, x) in h.iter().enumerate() {
                    positive(&format!("cuboid half_extents[{a}]"), *x)?;
                }
                Ok((SharedShape::cuboid(h[0], h[1], h[2]), Vec3::ZERO))
            }
            ShapeSpec::Ball { radius } => {
                positive("ball radius", *radius)?;
                Ok((SharedShape::ball(*radius), Vec3::ZERO))
            }
            ShapeSpec::Capsule { half_height, radius } => {
                positive("capsule half_height", *half_height)?;
                positive("capsule radius", *radius)?;
                Ok((SharedShape::capsule_y(*half_height, *radius), Vec3::ZERO))
            }
            ShapeSpec::Cylinder { half_height, radius } => {
                positive("cylinder half_height", *half_height)?;
                positive("cylinder radius", *radius)?;
                Ok((SharedShape::cylinder(*half_height, *radius), Vec3::ZERO))
            }
            ShapeSpec::ConvexHull { points } => {
                if points.len() < 4 || !points.iter().all(|p| all_finite(p)) {
                    return Err("convex_hull needs at least 4 finite points".into());
                }
                let pts: Vec<Vec3> = points.iter().map(|p| v3(*p)).collect();
                let hull = SharedShape::convex_hull(&pts).ok_or_else(|| {
                    "convex_hull points are degenerate (coplanar or repeated)".to_string()
                })?;
                // parry returns a flat hull for coplanar points: reject what has no volume.
                let extent = hull.compute_local_aabb().extents().max_element();
                if hull.mass_properties(1.0).mass() <= 1e-9 * extent.powi(3) {
                    return Err(
                        "convex_hull points are degenerate (coplanar: the hull has no volume)"
                            .into(),
                    );
                }
                Ok((hull, Vec3::ZERO))
            }
            ShapeSpec::Mesh { obj, scale, repair } => {
                positive("mesh scale", *scale)?;
                let path = base.join(obj);
                match (crate::geometry::mesh::load_obj(&path, *scale), repair) {
                    (Ok(s), _) => Ok((s, Vec3::ZERO)),
                    (Err(e), MeshRepair::ConvexHull) => {
                        let hull = crate::geometry::mesh::load_obj_hull(&path, *scale)
                            .map_err(|h| format!("{e}; and its convex hull failed too: {h}"))?;
                        notes.push(format!(
                            "{e}: its convex hull is used instead (repair = \"convex_hull\")"
                        ));
                        Ok((hull, Vec3::ZERO))
                    }
                    (Err(e), MeshRepair::None) => Err(format!(
                        "{e} (repair = \"convex_hull\" would use its convex hull instead)"
                    )),
                }
            }
        }
    }
}

impl Placed {
    /// The orientation, validated.
    pub fn rotation(&self) -> Result<Rotation, String> {
        match (&self.quaternion, &self.axis_angle) {
            (Some(_), Some(_)) => Err("give either quaternion or axis_angle, not both".into()),
            (Some(q), None) => {
                let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
                if !all_finite(q) || n < 1e-12 {
                    return Err(format!("quaternion {q:?} must be finite and non-zero"));
                }
                Ok(Rotation::from_xyzw(q[1] / n, q[2] / n, q[3] / n, q[0] / n))
            }
            (None, Some(aa)) => {
                let axis = v3(aa.axis);
                if !all_finite(&aa.axis) || !aa.degrees.is_finite() || axis.length() < 1e-12 {
                    return Err("axis_angle needs a finite non-zero axis and finite degrees".into());
                }
                Ok(Rotation::from_axis_angle(axis.normalize(), aa.degrees.to_radians()))
            }
            (None, None) => Ok(Rotation::IDENTITY),
        }
    }

    /// Builds the parry shape at its pose; `base` is the folder relative mesh paths start from.
    pub fn build(&self, base: &Path) -> Result<Solid, String> {
        self.build_noting(base, &mut Vec::new())
    }

    /// [`Placed::build`] of a `mesh` shape whose file may be an open surface: loaded as a
    /// shell `thickness` thick when it is ([`crate::geometry::mesh::load_obj_or_shell`]).
    pub fn build_shell(&self, base: &Path, thickness: f64) -> Result<Solid, String> {
        let ShapeSpec::Mesh { obj, scale, .. } = &self.shape else {
            return Err("a shell thickness applies to a mesh only".into());
        };
        if !all_finite(&self.position) {
            return Err(format!("position {:?} must be finite", self.position));
        }
        positive("mesh scale", *scale)?;
        let shape = crate::geometry::mesh::load_obj_or_shell(&base.join(obj), *scale, thickness)
            .map_err(|e| e.to_string())?;
        let rot = self.rotation()?;
        Ok(Solid { shape, pose: Pose::from_parts(v3(self.position), rot) })
    }

    /// [`Placed::build`], adding to `notes` what was repaired.
    pub fn build_noting(&self, base: &Path, notes: &mut Vec<String>) -> Result<Solid, String> {
        if !all_finite(&self.position) {
            return Err(format!("position {:?} must be finite", self.position));
        }
        let (shape, offset) = self.shape.build_noting(base, notes)?;
        let rot = self.rotation()?;
        let pose = Pose::from_parts(v3(self.position) + rot * offset, rot);
        Ok(Solid { shape, pose })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_sdf_is_negative_inside_and_exact_outside() {
        let p = Placed {
            shape: ShapeSpec::Box { min: [0.0, 0.0, 0.0], max: [1.0, 2.0, 1.0] },
            position: [0.0; 3],
            quaternion: None,
            axis_angle: None,
        };
        let s = p.build(Path::new(".")).unwrap();
        assert!((s.sdf(Vec3::new(0.5, 1.0, 0.5)) + 0.5).abs() < 1e-12);
        assert!((s.sdf(Vec3::new(1.5, 1.0, 0.5)) - 0.5).abs() < 1e-12);
    }

    #[test]
    fn degenerate_shapes_are_rejected() {
        assert!(ShapeSpec::Ball { radius: 0.0 }.build(Path::new(".")).is_err());
        let nan = ShapeSpec::Cuboid { half_extents: [1.0, f64::NAN, 1.0] };
        assert!(nan.build(Path::new(".")).is_err());
        let flat = ShapeSpec::ConvexHull {
            points: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]],
        };
        assert!(flat.build(Path::new(".")).is_err());
    }
}
