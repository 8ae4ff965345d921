//! The symmetric 7-point stencil the solvers and preconditioners read: the pressure stage
//! builds it, MIC(0) factors it, multigrid coarsens it.

use crate::geometry::grid::NONE;

/// The symmetric 7-point stencil over the unknowns.
#[derive(Clone, Debug, Default)]
pub struct Stencil {
    /// Diagonal entries.
    pub diag: Vec<f64>,
    /// Coupling to the +x, +y, +z neighbour row (A_ij = −plus; 0 when there is none).
    pub plus: Vec<[f64; 3]>,
    /// Rows of the −x, +x, −y, +y, −z, +z neighbours, [`NONE`] when not an unknown.
    pub nbr: Vec<[u32; 6]>,
}

impl Stencil {
    /// y = A x.
    pub fn apply(&self, x: &[f64], y: &mut [f64]) {
        use rayon::prelude::*;
        y.par_iter_mut().enumerate().for_each(|(r, yr)| {
            let mut v = self.diag[r] * x[r];
            for axis in 0..3 {
                let m = self.nbr[r][2 * axis];
                if m != NONE {
                    v -= self.plus[m as usize][axis] * x[m as usize];
                }
                let p = self.nbr[r][2 * axis + 1];
                if p != NONE {
                    v -= self.plus[r][axis] * x[p as usize];
                }
            }
            *yr = v;
        });
    }
}
