//! The symmetric 7-point stencil the solvers and preconditioners read: the pressure stage
//! builds it, MIC(0) factors it, multigrid coarsens it.

use crate::geometry::grid::NONE;
use crate::math::runs;
use rayon::prelude::*;

/// Rows the product hands to rayon as one piece.
const CHUNK: usize = 4096;

/// The symmetric 7-point stencil over the unknowns.
#[derive(Clone, Debug, Default)]
pub struct Stencil {
    /// Diagonal entries.
    pub diag: Vec<f64>,
    /// Coupling to the +x, +y, +z neighbour row (A_ij = −plus; 0 when there is none).
    pub plus: Vec<[f64; 3]>,
    /// Rows of the −x, +x, −y, +y, −z, +z neighbours, [`NONE`] when not an unknown.
    pub nbr: Vec<[u32; 6]>,
    /// Runs of rows `start..start + len` with all six neighbours, each neighbour the one of
    /// the row before plus one (a row of a deep pool): the product reads their neighbours as
    /// contiguous slices from the first row's instead of 24 bytes of indices a row. Found by
    /// [`Stencil::find_runs`] once the rows are final; empty, every row is read by its
    /// indices.
    pub runs: Vec<(u32, u32)>,
}

impl Stencil {
    /// Fills [`Stencil::runs`] from the neighbours (after any change to them).
    pub fn find_runs(&mut self) {
        let nbr = &self.nbr;
        let full = |r: usize| nbr[r].iter().all(|&n| n != NONE);
        self.runs = runs::find(nbr.len(), |r| {
            full(r) && full(r - 1) && (0..6).all(|k| nbr[r][k] == nbr[r - 1][k] + 1)
        });
    }

    /// y = A x.
    pub fn apply(&self, x: &[f64], y: &mut [f64]) {
        y.par_chunks_mut(CHUNK).enumerate().for_each(|(c, y)| self.apply_rows(c * CHUNK, x, y));
    }

    /// Rows `first..first + y.len()` of `A x` into `y`: row by row outside the runs, from
    /// contiguous slices inside them (the same expression, so the same bits).
    #[inline]
    fn apply_rows(&self, first: usize, x: &[f64], y: &mut [f64]) {
        runs::walk(&self.runs, first, first + y.len(), |run, a, b| {
            let Some(rs) = run else {
                for i in a..b {
                    y[i - first] = self.row(i, x);
                }
                return;
            };
            let n = b - a;
            let at = |k: usize| self.nbr[rs][k] as usize + (a - rs);
            let (xm, xp, ym, yp, zm, zp) = (at(0), at(1), at(2), at(3), at(4), at(5));
            let (dg, pl, xs) = (&self.diag[a..b], &self.plus[a..b], &x[a..b]);
            let (pxm, pym, pzm) =
                (&self.plus[xm..xm + n], &self.plus[ym..ym + n], &self.plus[zm..zm + n]);
            let (x_xm, x_xp) = (&x[xm..xm + n], &x[xp..xp + n]);
            let (x_ym, x_yp) = (&x[ym..ym + n], &x[yp..yp + n]);
            let (x_zm, x_zp) = (&x[zm..zm + n], &x[zp..zp + n]);
            let dst = &mut y[a - first..b - first];
            for t in 0..n {
                let mut v = dg[t] * xs[t];
                v -= pxm[t][0] * x_xm[t];
                v -= pl[t][0] * x_xp[t];
                v -= pym[t][1] * x_ym[t];
                v -= pl[t][1] * x_yp[t];
                v -= pzm[t][2] * x_zm[t];
                v -= pl[t][2] * x_zp[t];
                dst[t] = v;
            }
        });
    }

    /// Row `r` of `A x` from its neighbour indices.
    #[inline]
    fn row(&self, r: usize, x: &[f64]) -> f64 {
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
        v
    }
}

#[cfg(test)]
mod tests {
    use crate::solvers::testing::tank;

    /// The product over the runs (neighbours read as slices) gives the bits of the product
    /// row by row, on a pool with a sloped surface and a solid blob of fractional faces,
    /// whose runs hold most of its rows (so the comparison covers them).
    #[test]
    fn runs_multiply_as_rows_do() {
        let sys = tank([40, 24, 30], 0.45);
        let a = &sys.stencil;
        let in_runs: usize = a.runs.iter().map(|&(_, l)| l as usize).sum();
        assert!(2 * in_runs > a.diag.len(), "{in_runs} of {} rows in runs", a.diag.len());
        let x: Vec<f64> = (0..a.diag.len() as u64)
            .map(|i| ((i.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40) as f64) / 1e7 - 0.8)
            .collect();
        let mut with_runs = vec![0.0; x.len()];
        a.apply(&x, &mut with_runs);
        let mut rows = a.clone();
        rows.runs.clear();
        let mut by_rows = vec![0.0; x.len()];
        rows.apply(&x, &mut by_rows);
        assert!(with_runs.iter().zip(&by_rows).all(|(p, q)| p.to_bits() == q.to_bits()));
    }
}
