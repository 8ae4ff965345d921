//! Face fractions from signed-distance samples.
//!
//! The solid fraction of a face is the solid part of the face's *control volume*: the box
//! that spans the face and reaches from the cell centre on one side to the cell centre on
//! the other, the volume a face velocity stands for in the variational pressure solve
//! (Batty et al. 2007). It is computed from the signed distance sampled every dx/2 (the
//! control volume is 2×2×2 sub-boxes, [`SUBSAMPLE`]), each sub-box split into 24 congruent
//! tetrahedra (box centre, a face centre, an edge of that face; see
//! [`box_fraction_inside`]) with the distance taken linear on each, where the volume of
//! `{phi < 0}` has a closed form. The result is continuous and piecewise smooth in the
//! samples for every orientation of the boundary.
//!
//! (An earlier version used the *area* fraction of the face from its 4 corners, as Batty's
//! 2D code does. That jumps from 0 to 1 when a body's face lies in the plane of a grid face
//! and moves by a hair: the pressure force on a box floating at a grid-aligned depth
//! flickered by 10% from step to step. Control volumes have no such plane.)
//!
//! A body thinner than half a cell would fall between samples dx/2 apart (a quarter-cell plate
//! lost 75% of its volume, and its buoyancy): its fractions sample the distance more finely,
//! at a level chosen once from its thickness ([`samples_per_cell`]).
//!
//! The fluid weight of a face is `1 - fraction`; faces on the domain boundary are walls
//! and have weight 0. A static solid thinner than 2 cells also closes the faces between the
//! cell centres it separates ([`face_weights`]), which volume fractions alone do not.
//!
//! The files: `volume.rs` (the closed-form fraction of a tetrahedron and of a box, and the
//! snap of round-off dust), `control_volume.rs` (a face's control volume and its sample
//! lattices, how finely a body is sampled), `node_sdf.rs` (the static solids' distance at
//! the nodes), `static_faces.rs` (the static solids' face weights, thin ones sealed),
//! `body_faces.rs` (a body's fractions β, volume-corrected, with their pose derivatives) and
//! `jacobian.rs` (J, a body's coupling to the cells).

mod body_faces;
mod control_volume;
mod jacobian;
mod node_sdf;
mod static_faces;
#[cfg(test)]
mod tests;
mod volume;

pub use body_faces::{body_faces, body_faces_generic, BodyFaces, DualFaces};
pub use control_volume::{
    cv_corners, cv_fine_lattice, cv_fraction, cv_lattice, samples_per_cell, MAX_SAMPLES_PER_CELL,
    SUBSAMPLE,
};
pub use jacobian::body_jacobian;
pub use node_sdf::{cell_centre_in_solid, cells_within, far, node_sdf, NodeSdf};
pub use static_faces::{face_weights, is_thin, seal_thin_solid, SEAL_BELOW_CELLS};
pub use volume::{box_fraction_inside, snap, tet_fraction_inside};
