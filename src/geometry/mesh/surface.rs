//! Triangle meshes of any shape, for output: a shape's surface in its local frame
//! ([`surface_mesh`]) or placed in the world ([`placed_surface`], a [`TriangleMesh`]).

use crate::math::{Pose, SharedShape, Vec3};
use parry3d_f64::shape::TypedShape;

/// Subdivisions around the axis of round shapes in [`surface_mesh`] (22.5° steps); the
/// meridians of balls and capsule caps use the same angular step.
const ROUND_SUBDIV: u32 = 16;

/// A triangle mesh in world coordinates.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriangleMesh {
    /// Vertices, m.
    pub vertices: Vec<Vec3>,
    /// Triangles, counter-clockwise seen from outside.
    pub triangles: Vec<[u32; 3]>,
}

impl TriangleMesh {
    /// The volume the mesh encloses (divergence theorem), m³.
    pub fn volume(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| self.vertices[i as usize]);
                a.dot(b.cross(c))
            })
            .sum::<f64>()
            / 6.0
    }

    /// Edges in other than two triangles (0 for a closed mesh).
    pub fn open_edges(&self) -> usize {
        let mut count = std::collections::HashMap::new();
        for t in &self.triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                *count.entry((a.min(b), a.max(b))).or_insert(0u32) += 1;
            }
        }
        count.values().filter(|&&n| n != 2).count()
    }
}

/// The surface of `shape` placed at `pose`, in world coordinates (see [`surface_mesh`]).
pub fn placed_surface(shape: &SharedShape, pose: &Pose) -> TriangleMesh {
    let (vertices, triangles) = surface_mesh(shape);
    TriangleMesh {
        vertices: vertices.iter().map(|v| pose.transform_point(*v)).collect(),
        triangles,
    }
}

/// A triangle mesh of the surface of `shape` in its local frame, for output: cuboids,
/// balls, capsules, cylinders, cones, convex polyhedra and triangle meshes (and compounds
/// of these, parts placed at their poses). Round shapes use `ROUND_SUBDIV` subdivisions
/// around their axis. Triangles are counter-clockwise seen from outside. Shapes with no
/// finite closed surface or not used by diffluid (half-spaces, segments, polylines, rounded
/// shapes, custom shapes) give an empty mesh.
pub fn surface_mesh(shape: &SharedShape) -> (Vec<Vec3>, Vec<[u32; 3]>) {
    let n = ROUND_SUBDIV;
    match shape.as_typed_shape() {
        TypedShape::Cuboid(s) => s.to_trimesh(),
        TypedShape::Ball(s) => s.to_trimesh(n, n / 2),
        TypedShape::Capsule(s) => s.to_trimesh(n, n / 2),
        TypedShape::Cylinder(s) => s.to_trimesh(n),
        TypedShape::Cone(s) => s.to_trimesh(n),
        TypedShape::ConvexPolyhedron(s) => s.to_trimesh(),
        TypedShape::TriMesh(s) => (s.vertices().to_vec(), s.indices().to_vec()),
        TypedShape::Triangle(s) => (vec![s.a, s.b, s.c], vec![[0, 1, 2]]),
        TypedShape::HeightField(s) => s.to_trimesh(),
        TypedShape::Voxels(s) => s.to_trimesh(),
        TypedShape::Compound(s) => {
            let mut vertices = Vec::new();
            let mut triangles = Vec::new();
            for (pose, part) in s.shapes() {
                append_placed(&mut vertices, &mut triangles, pose, surface_mesh(part));
            }
            (vertices, triangles)
        }
        _ => (Vec::new(), Vec::new()),
    }
}

/// Appends a part's mesh, moved by `pose`, to a mesh being assembled.
fn append_placed(
    vertices: &mut Vec<Vec3>,
    triangles: &mut Vec<[u32; 3]>,
    pose: &Pose,
    (part_vertices, part_triangles): (Vec<Vec3>, Vec<[u32; 3]>),
) {
    let base = vertices.len() as u32;
    vertices.extend(part_vertices.into_iter().map(|p| pose.transform_point(p)));
    triangles.extend(part_triangles.into_iter().map(|t| t.map(|i| i + base)));
}
