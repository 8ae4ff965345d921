//! The fluid weight of every face among static solids: one minus its control volume's solid
//! fraction, and every face a thin solid crosses closed so that a plate is watertight.

use super::control_volume::{cv_fine_lattice, cv_fraction};
use super::node_sdf::far;
use crate::geometry::grid::{Grid, Lattice};
use crate::geometry::shape::Solid;

/// Static solids thinner than this many cells everywhere are sealed (see [`face_weights`]
/// and [`is_thin`]). A plate at least 2 cells thick fills some face's whole control volume
/// wherever it sits, and seals by its fractions alone.
pub const SEAL_BELOW_CELLS: f64 = 2.0;

/// Whether `solid` is thinner than [`SEAL_BELOW_CELLS`] everywhere: no point of it, sampled
/// every dx/2 over its bounds within the tank, lies a cell or more inside (its inscribed
/// radius is under a cell, to within the sampling). A plate under 2 cells thick is thin; a
/// ball or a box with a part 2 cells across or more is not, whatever its size.
pub fn is_thin(grid: &Grid, solid: &Solid) -> bool {
    use rayon::prelude::*;
    let half = Lattice { n: grid.n.map(|n| 2 * n + 1), off: [0.0; 3], dx: grid.dx / 2.0 };
    let (lo, hi) = solid.bounds();
    let (lo, hi) = (lo.to_array(), hi.to_array());
    let range = |d: usize| {
        let a = (lo[d] / half.dx).floor().max(0.0) as usize;
        let b = ((hi[d] / half.dx).ceil().max(0.0) as usize + 1).min(half.n[d]);
        a..b.max(a)
    };
    let (ri, rj, rk) = (range(0), range(1), range(2));
    !rk.into_par_iter().any(|k| {
        rj.clone().any(|j| ri.clone().any(|i| solid.sdf(half.position(i, j, k)) <= -grid.dx))
    })
}

/// Fluid weight (open fraction) of every face: one minus the solid fraction of its control
/// volume in the union of `solids`; domain-boundary faces are walls (weight 0).
///
/// A solid thinner than [`SEAL_BELOW_CELLS`] everywhere ([`is_thin`]) also closes (weight 0)
/// every face whose segment between the two cell centres it joins meets the solid
/// ([`seal_thin_solid`]). Volume
/// fractions alone do not seal a thin plate: a quarter-cell plate inside a face's control
/// volume leaves three quarters of it open, and the face carries flow across the plate as if
/// it were a grid of holes (98% of the flow got through). The crossed segments are a cut of
/// the grid's cell-to-cell graph along the plate (every path of cell centres from one side to
/// the other meets it), so a plate of any orientation and any thickness is watertight; the
/// cells whose centre it holds are closed off. Thicker solids keep their volume fractions
/// unchanged, and so do thin parts of a thick solid (give a thin fin as its own obstacle).
pub fn face_weights(grid: &Grid, solids: &[Solid]) -> [Vec<f64>; 3] {
    let mut weights = volume_weights(grid, solids);
    for s in solids {
        if is_thin(grid, s) {
            seal_thin_solid(grid, s, &mut weights);
        }
    }
    weights
}

/// Closes (weight 0) every interior face whose segment from cell centre to cell centre
/// meets `solid` (a ray cast, exact for any thickness).
pub fn seal_thin_solid(grid: &Grid, solid: &Solid, weights: &mut [Vec<f64>; 3]) {
    use crate::math::Vec3;
    use parry3d_f64::query::Ray;
    let (lo, hi) = solid.bounds();
    let (lo, hi) = (lo.to_array(), hi.to_array());
    for (axis, w) in weights.iter_mut().enumerate() {
        let lat = grid.faces(axis);
        // Faces whose segment (along `axis`) or whose centre (across it) may meet the bounds.
        let range = |d: usize| {
            let a = ((lo[d] / grid.dx).floor() - 1.0).max(0.0) as usize;
            let b = (((hi[d] / grid.dx).ceil() + 2.0).max(0.0) as usize).min(lat.n[d]);
            a..b
        };
        let dir = crate::math::unit(axis);
        for k in range(2) {
            for j in range(1) {
                for i in range(0) {
                    let f = [i, j, k];
                    if f[axis] == 0 || f[axis] == grid.n[axis] {
                        continue;
                    }
                    let origin: Vec3 = lat.position(i, j, k) - 0.5 * grid.dx * dir;
                    let ray = Ray::new(origin, dir);
                    if solid.sdf(origin) < 0.0
                        || solid.shape.intersects_ray(&solid.pose, &ray, grid.dx)
                    {
                        w[lat.index(i, j, k)] = 0.0;
                    }
                }
            }
        }
    }
}

/// [`face_weights`] from volume fractions alone.
pub(super) fn volume_weights(grid: &Grid, solids: &[Solid]) -> [Vec<f64>; 3] {
    let far = far(grid);
    [0, 1, 2].map(|axis| {
        let cv = cv_fine_lattice(grid, axis);
        let mut sdf = Vec::new();
        if !solids.is_empty() {
            sdf = vec![far; cv.len()];
            cv.fill_par(&mut sdf, |i, j, k| {
                let x = cv.position(i, j, k);
                solids.iter().map(|s| s.sdf(x)).fold(far, f64::min)
            });
        }
        let lat = grid.faces(axis);
        let mut w = vec![0.0; lat.len()];
        lat.fill_par(&mut w, |i, j, k| {
            let f = [i, j, k];
            if f[axis] == 0 || f[axis] == grid.n[axis] {
                return 0.0;
            }
            if sdf.is_empty() {
                return 1.0;
            }
            let c = cv_fraction(axis, f, |p| sdf[cv.index(p[0], p[1], p[2])]);
            (1.0 - c).clamp(0.0, 1.0)
        });
        w
    })
}
