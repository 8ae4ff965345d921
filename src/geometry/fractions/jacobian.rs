//! J, a rigid body's coupling to the cells: the pressure force and torque on the body from its
//! covered faces, and, transposed, the flux its motion pushes out of each cell.

use super::body_faces::BodyFaces;
use crate::geometry::grid::Grid;
use crate::geometry::spin::Spin;

/// Column i of J for one body, for every cell next to a covered face:
/// `J_i = Σ_f σ_if·dx²·β_f·[e_f ; r_f × e_f]` with σ = +1 on the cell's + face, −1 on its
/// − face, and `r_f` from the centre of mass to the face centre. `J·p` is then the pressure
/// force and torque on the body (−∇p integrated over the solid part of each face), and
/// `(Jᵀ·[v; ω])_i` the volume flux the body's motion pushes out of cell i. Sorted by cell.
/// The torque rows are projected by the body's [`Spin`] (`P·(r_f × e_f)`: what of its
/// rotation reaches the liquid, see [`crate::geometry::body::RigidBody::spin`]).
pub fn body_jacobian(
    grid: &Grid,
    faces: &BodyFaces,
    com: crate::math::Vec3,
    spin: Spin,
) -> Vec<(usize, [f64; 6])> {
    let area = grid.dx * grid.dx;
    let mut acc: std::collections::BTreeMap<usize, [f64; 6]> = Default::default();
    for axis in 0..3 {
        let lat = grid.faces(axis);
        let e = crate::math::unit(axis);
        for &(f, beta) in &faces.faces[axis] {
            let ijk = lat.ijk(f);
            let r = lat.position(ijk[0], ijk[1], ijk[2]) - com;
            let t = spin.project(r.cross(e));
            let col = [e.x, e.y, e.z, t.x, t.y, t.z].map(|x| x * area * beta);
            let (minus, plus) = grid.face_cells(axis, ijk);
            for (cell, sign) in [(minus, 1.0), (plus, -1.0)] {
                if let Some(c) = cell {
                    let entry = acc.entry(c).or_insert([0.0; 6]);
                    for d in 0..6 {
                        entry[d] += sign * col[d];
                    }
                }
            }
        }
    }
    acc.into_iter().collect()
}
