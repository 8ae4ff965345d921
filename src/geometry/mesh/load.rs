//! Loading an OBJ file as a body's shape: closed ([`load_obj`]), closed or thickened into a
//! shell ([`load_obj_or_shell`]), or its convex hull ([`load_obj_hull`]); each error an
//! [`Error::Mesh`] that names the file.

use super::closed::{merge_vertices, ClosedMesh};
use super::read::read_obj;
use super::shell::shell_mesh;
use crate::error::{Error, Result};
use crate::math::{SharedShape, Vec3};
use parry3d_f64::shape::TriMeshFlags;
use std::path::Path;

/// Loads a closed, consistently oriented triangle mesh from a Wavefront OBJ file, scaled
/// uniformly by `scale`, as a parry `TriMesh` whose signed distance is negative inside.
///
/// All objects and groups of the file are merged into one mesh; polygons are triangulated
/// as fans, points and lines are ignored, and vertices with identical coordinates are
/// merged (so objects sharing vertices are stitched). Coordinates are read with tobj (single
/// precision) and recovered as the shortest decimal that reads back to the same `f32`, so
/// a coordinate written with up to 7 significant digits (`0.1`) is exact in `f64`.
/// Triangles with a repeated vertex (what a polygon with a doubled vertex triangulates
/// into) are dropped.
///
/// Errors, each one line naming the file: the file cannot be read or is not valid OBJ; it
/// has no triangles; a vertex is not finite; a triangle has zero area; the mesh is not
/// closed (some edges belong to one triangle, or to more than two); the orientation is
/// inconsistent (a directed edge appears twice); the mesh encloses no volume.
///
/// A closed mesh whose triangles all face inward (negative enclosed volume) is **flipped**,
/// not rejected: its orientation is unambiguous, only reversed. A mesh with several shells
/// is flipped as a whole, so a hollow body (outer shell outward, inner shell inward) is kept
/// as it is.
///
/// A mesh so large once scaled that its volume or inertia is not a finite number is refused
/// too. Each error is [`Error::Mesh`], whose message names the file.
///
/// ```
/// use diffluid::geometry::mesh::load_obj;
///
/// let path = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/meshes/cube.obj");
/// let cube = load_obj(path.as_ref(), 0.5)?;
/// assert!(cube.mass_properties(1.0).mass() > 0.0);
/// # Ok::<(), diffluid::Error>(())
/// ```
pub fn load_obj(path: &Path, scale: f64) -> Result<SharedShape> {
    closed_obj(path, scale).map_err(|message| mesh_error(path, message))
}

/// [`Error::Mesh`] for the mesh at `path`.
fn mesh_error(path: &Path, message: String) -> Error {
    Error::Mesh { path: path.to_path_buf(), message }
}

/// [`load_obj`], its error a message.
fn closed_obj(path: &Path, scale: f64) -> std::result::Result<SharedShape, String> {
    let name = path.display();
    if !(scale.is_finite() && scale > 0.0) {
        return Err(format!("mesh {name}: scale must be a positive number, got {scale}"));
    }
    let (positions, triangles) = read_obj(path)?;

    let mut closed =
        ClosedMesh::new(&positions, &triangles).map_err(|e| format!("mesh {name} {e}"))?.outward();
    for v in &mut closed.vertices {
        *v *= scale;
    }
    let shape =
        SharedShape::trimesh_with_flags(closed.vertices, closed.triangles, TriMeshFlags::ORIENTED)
            .map_err(|e| format!("mesh {name}: parry rejected the triangles: {e}"))?;
    finite_mass(&shape, scale).map_err(|e| format!("mesh {name} {e}"))?;
    Ok(shape)
}

/// A shape's volume and inertia (at unit density) must be finite numbers: a mesh scaled by
/// 1e300 has vertices in range and neither. The error completes a sentence starting with the
/// mesh's name.
fn finite_mass(shape: &SharedShape, scale: f64) -> std::result::Result<(), String> {
    let mp = shape.mass_properties(1.0);
    let volume = mp.mass();
    if !(volume.is_finite() && mp.principal_inertia().is_finite() && mp.local_com.is_finite()) {
        return Err(format!(
            "scaled by {scale} has a volume of {volume} m³ and inertia {:?}: not finite numbers \
             (scale it down)",
            mp.principal_inertia().to_array()
        ));
    }
    Ok(())
}

/// Loads an OBJ as [`load_obj`] does when it is closed (today's rules, `thickness` unused);
/// an open one (with boundary edges: a sail, a leaf, a hull without a deck) as a shell
/// `thickness` thick (m, after scaling): the surface offset by ±thickness/2 along its vertex
/// normals, the two sheets joined along the boundary, checked as a closed mesh. Its volume,
/// so a body's mass at a density, is thickness × area (to first order in thickness over the
/// surface's curvature radius). An open surface must be consistently wound and manifold, and
/// the thickness small against its curvature (the sheets must not cross).
///
/// Errors as [`load_obj`]'s ([`Error::Mesh`]).
pub fn load_obj_or_shell(path: &Path, scale: f64, thickness: f64) -> Result<SharedShape> {
    shell_obj(path, scale, thickness).map_err(|message| mesh_error(path, message))
}

/// [`load_obj_or_shell`], its error a message.
fn shell_obj(path: &Path, scale: f64, thickness: f64) -> std::result::Result<SharedShape, String> {
    let name = path.display();
    if !(thickness.is_finite() && thickness > 0.0) {
        return Err(format!(
            "mesh {name}: shell_thickness must be a positive number, got {thickness}"
        ));
    }
    let closed = closed_obj(path, scale);
    if closed.is_ok() {
        return closed;
    }
    let (positions, triangles) = read_obj(path)?;
    let (mut vertices, tris) =
        merge_vertices(&positions, &triangles).map_err(|e| format!("mesh {name} {e}"))?;
    for v in &mut vertices {
        *v *= scale;
    }
    let shell = shell_mesh(&vertices, &tris, thickness)
        .map_err(|e| format!("mesh {name} as a shell {thickness} m thick {e}"))?;
    // Not an open surface (closed, but failing another check): the closed mesh's error.
    let shell = shell.ok_or_else(|| closed.err().unwrap_or_default())?;
    let solid = ClosedMesh::new(&shell.0, &shell.1)
        .map_err(|e| format!("mesh {name} as a shell {thickness} m thick {e}"))?
        .outward();
    let shape =
        SharedShape::trimesh_with_flags(solid.vertices, solid.triangles, TriMeshFlags::ORIENTED)
            .map_err(|e| format!("mesh {name}: parry rejected the shell's triangles: {e}"))?;
    finite_mass(&shape, scale).map_err(|e| format!("mesh {name} {e}"))?;
    Ok(shape)
}

/// The convex hull of an OBJ file's vertices (the fallback of a mesh that fails the checks
/// of [`load_obj`]). Errors as [`load_obj`]'s ([`Error::Mesh`]).
pub fn load_obj_hull(path: &Path, scale: f64) -> Result<SharedShape> {
    hull_obj(path, scale).map_err(|message| mesh_error(path, message))
}

/// [`load_obj_hull`], its error a message.
fn hull_obj(path: &Path, scale: f64) -> std::result::Result<SharedShape, String> {
    let name = path.display();
    let (positions, _) = read_obj(path)?;
    let points: Vec<Vec3> =
        positions.into_iter().filter(|p| p.is_finite()).map(|p| p * scale).collect();
    let hull = SharedShape::convex_hull(&points)
        .ok_or_else(|| format!("mesh {name}: its vertices have no convex hull (degenerate)"))?;
    finite_mass(&hull, scale).map_err(|e| format!("mesh {name} {e}"))?;
    Ok(hull)
}
