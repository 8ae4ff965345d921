//! The particles' density on the grid (their deposit), its adjoint, and the liquid volume.

use super::*;
use crate::geometry::grid::Grid;
use crate::math::par::min_pieces;
use crate::math::{comp, Vec3};
use rayon::prelude::*;

/// Marker particle number density at cell centres, in full cells (1 = as dense as freshly
/// seeded): each particle is deposited on its 8 nearest cell centres with trilinear weights,
/// and a weight that would fall on a cell beyond a tank wall lands on its mirror image inside
/// (reflection), so every particle deposits exactly one unit. The scatter runs in particle
/// order on one thread, so the sums do not depend on the thread count. They add to `base`
/// (a narrow band's deep cells' deposit) when given.
pub fn particle_density(pos: &[Vec3], grid: &Grid, ppc: usize, base: Option<&[f64]>) -> Vec<f64> {
    let mut out =
        base.map_or_else(|| vec![0.0; grid.num_cells()], |b| b.par_iter().copied().collect());
    let unit = 1.0 / ppc as f64;
    let deposit = |x: Vec3, out: &mut [f64], first: usize| {
        let (idx, w, _) = deposit_weights(grid, x);
        for c in 0..8 {
            let (bi, bj, bk) = (c & 1, (c >> 1) & 1, (c >> 2) & 1);
            out[grid.cell(idx[0][bi], idx[1][bj], idx[2][bk]) - first] +=
                w[0][bi] * w[1][bj] * w[2][bk] * unit;
        }
    };
    let (nz, slab) = (grid.n[2], grid.n[0] * grid.n[1]);
    if nz < 2 {
        pos.iter().for_each(|x| deposit(*x, &mut out, 0));
        return out;
    }
    // A particle in bucket b deposits on z-slabs b and b + 1 only, so the buckets of one
    // parity write disjoint pairs of slabs: even buckets in parallel, then odd ones, each in
    // particle order. A particle outside the tank (whose folded slabs are not adjacent) is
    // deposited last, on one thread.
    let bucket = |x: &Vec3| {
        let [k0, k1] = deposit_axis(grid, comp(*x, 2), 2).0;
        let b = k0.min(k1).min(nz - 2);
        if k0.max(k1) <= b + 1 {
            b
        } else {
            nz - 1
        }
    };
    let keys: Vec<u32> = pos.par_iter().map(|x| bucket(x) as u32).collect();
    let buckets = SlabBuckets::new(&keys, |b| b as usize, nz);
    for parity in 0..2 {
        let pairs =
            out[parity * slab..].par_chunks_mut(2 * slab).with_min_len(min_pieces(2 * slab));
        pairs.enumerate().for_each(|(m, pair)| {
            let b = 2 * m + parity;
            if b + 1 < nz {
                buckets.of(b).iter().for_each(|&p| deposit(pos[p as usize], pair, b * slab));
            }
        });
    }
    buckets.of(nz - 1).iter().for_each(|&p| deposit(pos[p as usize], &mut out, 0));
    out
}

/// Per axis: the two cells, their weights and the weights' derivatives.
type Deposit = ([[usize; 2]; 3], [[f64; 2]; 3], [[f64; 2]; 3]);

/// The cells a particle at `x` deposits on, per axis (folded back at the walls), their 1D
/// weights and the weights' derivatives. Always inlined: a caller that reads only the
/// indices or the weights computes nothing else (the deposit of the particles calls it
/// twice a particle; as a function it returned all 144 bytes through memory).
#[inline(always)]
pub(super) fn deposit_weights(grid: &Grid, x: Vec3) -> Deposit {
    // Written out: an array map here stays a call.
    let a = x.to_array();
    let (i0, w0) = deposit_axis(grid, a[0], 0);
    let (i1, w1) = deposit_axis(grid, a[1], 1);
    let (i2, w2) = deposit_axis(grid, a[2], 2);
    let dw = [[-1.0 / grid.dx, 1.0 / grid.dx]; 3];
    ([i0, i1, i2], [w0, w1, w2], dw)
}

/// Along axis `d`, the two cells a particle at coordinate `a` deposits on (folded back at
/// the walls) and their weights.
#[inline(always)]
fn deposit_axis(grid: &Grid, a: f64, d: usize) -> ([usize; 2], [f64; 2]) {
    let g = a / grid.dx - 0.5;
    let i0 = crate::math::floor(g);
    let t = g - i0;
    let n = grid.n[d] as i64;
    let i = i0 as i64;
    // Away from the walls (nearly every particle) the two cells need no folding.
    if i >= 0 && i + 1 < n {
        return ([i as usize, i as usize + 1], [1.0 - t, t]);
    }
    let fold = |i: i64| -> usize {
        if i < 0 {
            (-i - 1).min(n - 1) as usize
        } else if i >= n {
            (2 * n - 1 - i).max(0) as usize
        } else {
            i as usize
        }
    };
    ([fold(i), fold(i + 1)], [1.0 - t, t])
}

/// Adjoint of [`particle_density`]: adds `Σ_c dens̄_c · ∂dens_c/∂x_p` into `pbar`.
pub fn particle_density_adjoint(
    pos: &[Vec3],
    grid: &Grid,
    ppc: usize,
    dens_bar: &[f64],
    pbar: &mut [Vec3],
) {
    let unit = 1.0 / ppc as f64;
    // Each particle gathers into its own adjoint: in parallel, the same bits.
    pos.par_iter().zip(pbar.par_iter_mut()).with_min_len(1024).for_each(|(x, xb)| {
        let (idx, w, dw) = deposit_weights(grid, *x);
        let mut g = Vec3::ZERO;
        for c in 0..8 {
            let b = [c & 1, (c >> 1) & 1, (c >> 2) & 1];
            let s = dens_bar[grid.cell(idx[0][b[0]], idx[1][b[1]], idx[2][b[2]])];
            if s == 0.0 {
                continue;
            }
            g += s
                * unit
                * Vec3::new(
                    dw[0][b[0]] * w[1][b[1]] * w[2][b[2]],
                    w[0][b[0]] * dw[1][b[1]] * w[2][b[2]],
                    w[0][b[0]] * w[1][b[1]] * dw[2][b[2]],
                );
        }
        *xb += g;
    });
}

/// Liquid volume in m³: the particle density capped at one full cell per cell, times the
/// cell volume. A freshly seeded region gives its exact volume; marker particles that bunch
/// up (the way a marker-particle liquid loses volume) push cells over full and lower it.
/// A narrow band's deep cells (their deposit `base`) count as the full cells they stand for.
pub fn liquid_volume(pos: &[Vec3], grid: &Grid, ppc: usize, base: Option<&[f64]>) -> f64 {
    let dens = particle_density(pos, grid, ppc, base);
    let parts: Vec<f64> = dens
        .par_chunks(crate::geometry::grid::REDUCE_CHUNK)
        .map(|c| c.iter().map(|d| d.min(1.0)).sum())
        .collect();
    parts.iter().sum::<f64>() * grid.dx.powi(3)
}
