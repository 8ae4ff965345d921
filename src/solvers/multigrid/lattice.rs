//! A 7-point stencil on a whole lattice ([`LatticeStencil`]) and its Galerkin coarse operator
//! `COARSE_SCALE·Pᵀ A P` over 2×2×2 blocks: from a coarser lattice, or straight from the
//! pressure rows for the first coarse level.

use super::tuning::{COARSE_SCALE, MIN_PAR};
use crate::solvers::stencil::Stencil;
use rayon::prelude::*;

/// The lattice index of cell `c` on a lattice of `n` cells.
#[inline]
pub(super) fn cell_ijk(n: [usize; 3], c: usize) -> [usize; 3] {
    let i = c % n[0];
    let r = c / n[0];
    [i, r % n[1], r / n[1]]
}

/// A 7-point stencil on a whole lattice; a cell with a zero diagonal is absent.
pub(super) struct LatticeStencil {
    pub(super) n: [usize; 3],
    pub(super) diag: Vec<f64>,
    /// Coupling to the +x, +y, +z neighbour (A_ij = −plus).
    pub(super) plus: Vec<[f64; 3]>,
}

impl LatticeStencil {
    fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.n[0] * (j + self.n[1] * k)
    }

    pub(super) fn ijk(&self, c: usize) -> [usize; 3] {
        cell_ijk(self.n, c)
    }

    pub(super) fn present(&self) -> usize {
        self.diag.iter().filter(|&&d| d > 0.0).count()
    }

    /// `COARSE_SCALE·Pᵀ A P` over 2×2×2 blocks.
    pub(super) fn coarsen(&self) -> LatticeStencil {
        let n = self.n.map(|m| m.div_ceil(2));
        let len = n[0] * n[1] * n[2];
        let mut coarse = LatticeStencil { n, diag: vec![0.0; len], plus: vec![[0.0; 3]; len] };
        let rows: Vec<(f64, [f64; 3])> = (0..len)
            .into_par_iter()
            .with_min_len(MIN_PAR)
            .map(|cc| {
                let big = coarse.ijk(cc);
                let mut block = Block::default();
                for k in 2 * big[2]..(2 * big[2] + 2).min(self.n[2]) {
                    for j in 2 * big[1]..(2 * big[1] + 2).min(self.n[1]) {
                        for i in 2 * big[0]..(2 * big[0] + 2).min(self.n[0]) {
                            let c = self.index(i, j, k);
                            block.add([i, j, k], self.diag[c], self.plus[c]);
                        }
                    }
                }
                block.coefficients()
            })
            .collect();
        for (c, (d, p)) in rows.into_iter().enumerate() {
            coarse.diag[c] = d;
            coarse.plus[c] = p;
        }
        coarse.cut_absent();
        coarse
    }

    /// The first coarse lattice straight from the stencil over the unknowns (row `r` at
    /// lattice cell `cell_of_row[r]`, in increasing cell order): the same sums as
    /// [`LatticeStencil::coarsen`] of the fine lattice, in the same order, without building
    /// the fine lattice (32 bytes a cell of the whole grid).
    pub(super) fn coarsen_rows(n: [usize; 3], cell_of_row: &[u32], a: &Stencil) -> LatticeStencil {
        let cn = n.map(|m| m.div_ceil(2));
        let len = cn[0] * cn[1] * cn[2];
        let mut coarse = LatticeStencil { n: cn, diag: vec![0.0; len], plus: vec![[0.0; 3]; len] };
        let slab = cn[0] * cn[1];
        let fine_slab = n[0] * n[1];
        // The rows of coarse slab kc are those of fine slabs 2kc and 2kc + 1, a contiguous run
        // (the rows are in cell order), visited in cell order: each block's children in the
        // order of the lattice loop.
        let first_row = |k: usize| cell_of_row.partition_point(|&c| (c as usize) < k * fine_slab);
        coarse
            .diag
            .par_chunks_mut(slab)
            .zip(coarse.plus.par_chunks_mut(slab))
            .enumerate()
            .for_each(|(kc, (diag, plus))| {
                let rows = first_row(2 * kc)..first_row((2 * kc + 2).min(n[2]));
                let mut blocks = vec![Block::default(); slab];
                for r in rows {
                    let ijk = cell_ijk(n, cell_of_row[r] as usize);
                    let b = ijk[0] / 2 + cn[0] * (ijk[1] / 2);
                    blocks[b].add(ijk, a.diag[r].max(0.0), a.plus[r]);
                }
                for ((d, p), block) in diag.iter_mut().zip(plus.iter_mut()).zip(&blocks) {
                    (*d, *p) = block.coefficients();
                }
            });
        coarse.cut_absent();
        coarse
    }

    /// No coupling into an absent block.
    fn cut_absent(&mut self) {
        let (nn, diag) = (self.n, &self.diag);
        self.plus.par_iter_mut().enumerate().with_min_len(MIN_PAR).for_each(|(c, p)| {
            let i = c % nn[0];
            let j = (c / nn[0]) % nn[1];
            let k = c / (nn[0] * nn[1]);
            let ijk = [i, j, k];
            let stride = [1, nn[0], nn[0] * nn[1]];
            for a in 0..3 {
                if diag[c] <= 0.0 || ijk[a] + 1 >= nn[a] || diag[c + stride[a]] <= 0.0 {
                    p[a] = 0.0;
                }
            }
        });
    }
}

/// The sums of one 2×2×2 block's children in `P^T A P`.
#[derive(Clone, Copy, Default)]
struct Block {
    diag: f64,
    gross: f64,
    plus: [f64; 3],
}

impl Block {
    /// Adds the child at lattice index `ijk` with diagonal `d` and + couplings `plus` (absent
    /// when `d` is not positive).
    #[inline]
    fn add(&mut self, ijk: [usize; 3], d: f64, plus: [f64; 3]) {
        if d <= 0.0 {
            return;
        }
        self.diag += d;
        self.gross += d;
        for a in 0..3 {
            // A child at an even index couples to its +a sibling inside the block; one at an
            // odd index to the next block.
            if ijk[a] % 2 == 0 {
                self.diag -= 2.0 * plus[a];
            } else {
                self.plus[a] += plus[a];
            }
        }
    }

    /// The coarse diagonal and + couplings.
    fn coefficients(&self) -> (f64, [f64; 3]) {
        // A block whose rows cancel (a sealed pocket of a few cells) is left out rather than
        // divided by its round-off: dropping a row and column keeps the operator positive
        // semi-definite.
        if self.diag <= 1e-12 * self.gross {
            return (0.0, [0.0; 3]);
        }
        (COARSE_SCALE * self.diag, self.plus.map(|p| COARSE_SCALE * p))
    }
}
