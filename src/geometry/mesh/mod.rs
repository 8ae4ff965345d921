//! Triangle meshes: OBJ loading into a parry shape that answers inside/outside queries, and
//! triangle meshes of any shape for output.
//!
//! A loaded mesh must be a closed, consistently oriented surface: every undirected edge is
//! shared by exactly two triangles and every directed edge appears once. parry's
//! [`TriMesh`](parry3d_f64::shape::TriMesh) then gives a signed distance (negative inside)
//! when it is built with [`TriMeshFlags::ORIENTED`]: that flag makes parry compute the
//! angle-weighted vertex and edge pseudo-normals and use them (and the face normals) to
//! decide on which side of the closest feature a point lies. Without it,
//! `distance_to_point(pose, p, false)` is the unsigned distance to the surface.
//!
//! [`TriMeshFlags::ORIENTED`]: parry3d_f64::shape::TriMeshFlags::ORIENTED
//!
//! The files, each one concern: `read.rs` (an OBJ file's vertices and triangles, the shipped
//! meshes), `closed.rs` (`ClosedMesh`: merged vertices, closed edges, one orientation, the
//! volume), `check.rs` (vertex fans, self-intersections, nested shells), `shell.rs` (an open
//! surface thickened into a closed shell), `load.rs` (the public loaders and their errors) and
//! `surface.rs` (the surface of any shape, for output).

mod check;
mod closed;
mod load;
mod read;
mod shell;
mod surface;
#[cfg(test)]
mod tests;

#[cfg(feature = "surface")]
pub(crate) use check::link_fans;
pub use load::{load_obj, load_obj_hull, load_obj_or_shell};
pub use surface::{placed_surface, surface_mesh, TriangleMesh};
