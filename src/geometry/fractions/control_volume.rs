//! A face's control volume (cell centre to cell centre along its axis, node to node across
//! it): the lattices its corners are sampled on, how finely a body is sampled for its
//! thickness, and the solid fraction of one control volume.

use super::volume::{box_fraction_inside, snap};
use crate::geometry::grid::{Grid, Lattice};
use crate::math::dual::Scalar;

/// The sample lattice of face control-volume corners for `axis`: cell-centre coordinates
/// along `axis`, node coordinates across it.
pub fn cv_lattice(grid: &Grid, axis: usize) -> Lattice {
    let mut n = [grid.n[0] + 1, grid.n[1] + 1, grid.n[2] + 1];
    n[axis] = grid.n[axis];
    let mut off = [0.0; 3];
    off[axis] = 0.5;
    Lattice { n, off, dx: grid.dx }
}

/// The 8 control-volume corners of interior face `f` of `axis` in `cv_lattice`
/// coordinates, indexed `x + 2y + 4z`.
#[inline]
pub fn cv_corners(axis: usize, f: [usize; 3]) -> [[usize; 3]; 8] {
    let mut out = [[0usize; 3]; 8];
    for (c, o) in out.iter_mut().enumerate() {
        for d in 0..3 {
            let bit = (c >> d) & 1;
            o[d] = if d == axis { f[d] - 1 + bit } else { f[d] + bit };
        }
    }
    out
}

/// Sub-boxes per axis of a control volume: the signed distance is sampled every dx/2, so a
/// control volume is 2×2×2 boxes. Linear interpolation misses a sliver wherever a sample sits
/// on a body's flat face next to an edge (the distance has a kink there); at one sample per
/// dx that lost 5% of a 4-cell cube's volume, and with it 5% of its buoyancy. A body thinner
/// than half a cell is sampled more finely ([`samples_per_cell`]).
pub const SUBSAMPLE: usize = 2;

/// The finest sampling [`samples_per_cell`] chooses: every dx/16, for bodies down to a
/// sixteenth of a cell (a 0.1-cell plate's fractions then cost 512 distance samples per
/// dx/2 box within a box's diagonal of its surface, against one for a thick body).
pub const MAX_SAMPLES_PER_CELL: usize = 16;

/// Sub-boxes per cell side for a body `thickness` thick (m) on cells of side `dx`:
/// [`SUBSAMPLE`] for bodies at least half a cell thick, else doubled until a sample spacing
/// is no more than the thickness, up to [`MAX_SAMPLES_PER_CELL`]. A plate between two samples
/// along its normal, both outside it, vanishes from linearly interpolated fractions (a
/// quarter-cell plate sampled every dx/2 lost 75% of its volume); with samples at most its
/// thickness apart, one always lies inside, and the volume correction of [`body_faces`]
/// takes up the rest. Chosen once per body from its shape, never from its pose, so the
/// fractions stay continuous as the body moves.
///
/// [`body_faces`]: super::body_faces
pub fn samples_per_cell(thickness: f64, dx: f64) -> usize {
    let mut r = SUBSAMPLE;
    while r < MAX_SAMPLES_PER_CELL && dx / r as f64 > thickness {
        r *= 2;
    }
    r
}

/// The refined control-volume corner lattice of `axis` (spacing dx / [`SUBSAMPLE`]).
pub fn cv_fine_lattice(grid: &Grid, axis: usize) -> Lattice {
    let cv = cv_lattice(grid, axis);
    let r = SUBSAMPLE;
    Lattice {
        n: cv.n.map(|n| r * (n - 1) + 1),
        off: cv.off.map(|o| o * r as f64),
        dx: grid.dx / r as f64,
    }
}

/// Solid fraction of the control volume of interior face `f` of `axis`, from the signed
/// distance on the refined lattice (`at` takes refined lattice coordinates).
#[inline]
pub fn cv_fraction<T: Scalar>(axis: usize, f: [usize; 3], at: impl Fn([usize; 3]) -> T) -> T {
    let r = SUBSAMPLE;
    let base = cv_corners(axis, f)[0].map(|x| x * r);
    let mut sum = T::cst(0.0);
    for sk in 0..r {
        for sj in 0..r {
            for si in 0..r {
                let c: [T; 8] = std::array::from_fn(|b| {
                    at([
                        base[0] + si + (b & 1),
                        base[1] + sj + ((b >> 1) & 1),
                        base[2] + sk + ((b >> 2) & 1),
                    ])
                });
                sum = sum + box_fraction_inside(c);
            }
        }
    }
    snap(sum / T::cst((r * r * r) as f64))
}
