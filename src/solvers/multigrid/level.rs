//! One level of the hierarchy: its cells split by colour ([`Half`]), their coefficients in
//! f32, the runs of uniform entries the sweep streams, the neighbour sum it reads, and the
//! level's vectors ([`Work`]).

use super::tuning::MIN_PAR;
use crate::math::buffer::clear_for;
use crate::math::runs;
use rayon::prelude::*;

/// Marks a slot of the black colour in a packed (colour, index) slot.
const BLACK_BIT: u32 = 1 << 31;
/// Marks, in an entry's first neighbour index, an entry whose diagonal and six couplings are
/// its half's [`Half::uniform`] ones: the sweep then reads no coefficient of it.
const UNIFORM: u32 = 1 << 31;

#[inline]
pub(super) fn pack(colour: usize, i: usize) -> u32 {
    (i as u32) | if colour == 1 { BLACK_BIT } else { 0 }
}

#[inline]
pub(super) fn unpack(s: u32) -> (usize, usize) {
    ((s >> 31) as usize, (s & !BLACK_BIT) as usize)
}

/// The cells of one colour on one level, numbered in lattice order.
///
/// The coefficients are stored in f32 (see [`diag32`] and [`coef32`]): the cycle is memory
/// bound, and a V-cycle of the f32-rounded operator, evaluated in f64, is as exactly
/// symmetric as one of the f64 operator, and as good a preconditioner.
#[derive(Debug, Default)]
pub(super) struct Half {
    /// Lattice cell of each entry.
    pub(super) cell: Vec<u32>,
    /// Diagonal (rounded up to f32).
    pub(super) diag: Vec<f32>,
    /// Entries of the other colour at −x, +x, −y, +y, −z, +z; an absent one is the other
    /// colour's padding slot (its length), whose value is always 0, with coupling 0, so the
    /// sweep has no branch.
    pub(super) nbr: Vec<[u32; 6]>,
    /// Their couplings (A_ij = −coef; rounded toward zero to f32).
    pub(super) coef: Vec<[f32; 6]>,
    /// The diagonal and the coupling of the entries flagged [`UNIFORM`] (all six couplings
    /// equal): most of a deep pool's cells, whose coefficients the sweep then does not stream.
    pub(super) uniform: (f32, f32),
    /// Runs of consecutive [`UNIFORM`] entries `start..start + len` whose six neighbours each
    /// step by one entry from one entry to the next (a row of a deep pool): the sweep reads
    /// their neighbours as six contiguous slices from the first entry's indices, not
    /// 24 bytes of indices an entry. In increasing order, disjoint.
    pub(super) runs: Vec<(u32, u32)>,
    /// Packed slot of the block on the next coarser level ([`NONE`] on the coarsest).
    ///
    /// [`NONE`]: crate::geometry::grid::NONE
    pub(super) parent: Vec<u32>,
    /// Red entries of the finer level in this block (coarse levels only; [`NONE`]-padded).
    ///
    /// [`NONE`]: crate::geometry::grid::NONE
    pub(super) red_children: Vec<[u32; 4]>,
}

impl Half {
    pub(super) fn len(&self) -> usize {
        self.diag.len()
    }

    /// Empties the cells and their coefficients for `n` entries (see [`clear_for`]).
    pub(super) fn clear_for(&mut self, n: usize) {
        clear_for(&mut self.cell, n);
        clear_for(&mut self.diag, n);
        clear_for(&mut self.nbr, n);
        clear_for(&mut self.coef, n);
        self.runs.clear();
    }

    /// Picks [`Half::uniform`] (the first entry with six equal positive couplings) and flags
    /// every entry that has exactly its coefficients.
    pub(super) fn mark_uniform(&mut self) {
        let same = |c: &[f32; 6]| c[0] > 0.0 && c.iter().all(|x| x.to_bits() == c[0].to_bits());
        let Some((c, &d)) = self.coef.iter().zip(&self.diag).find(|(c, _)| same(c)) else {
            self.uniform = (0.0, 0.0);
            return;
        };
        let (d, c) = (d, c[0]);
        self.uniform = (d, c);
        self.nbr.par_iter_mut().with_min_len(MIN_PAR).zip(&self.coef).zip(&self.diag).for_each(
            |((n, cf), dg)| {
                if dg.to_bits() == d.to_bits() && cf.iter().all(|x| x.to_bits() == c.to_bits()) {
                    n[0] |= UNIFORM;
                }
            },
        );
        self.find_runs();
    }

    /// Fills [`Half::runs`]: the maximal runs of at least [`runs::SHORTEST`] uniform entries, each
    /// of whose neighbour indices is the one before's plus one.
    fn find_runs(&mut self) {
        let nbr = &self.nbr;
        let uniform = |i: usize| nbr[i][0] & UNIFORM != 0;
        let index = |i: usize, k: usize| nbr[i][k] & !UNIFORM;
        self.runs = runs::find(nbr.len(), |i| {
            uniform(i) && uniform(i - 1) && (0..6).all(|k| index(i, k) == index(i - 1, k) + 1)
        });
    }

    /// `out[t] = f(i, s, d)` for the entries `i = first + t` of a chunk, with `(s, d)` what
    /// [`neighbours`] gives for `i` (the same bits): one entry at a time outside the runs,
    /// and six contiguous neighbour slices inside them (a loop the compiler vectorises).
    #[inline(always)]
    pub(super) fn each(
        &self,
        first: usize,
        out: &mut [f64],
        other: &[f64],
        f: impl Fn(usize, f64, f64) -> f64,
    ) {
        runs::walk(&self.runs, first, first + out.len(), |run, a, b| {
            let Some(rs) = run else {
                for j in a..b {
                    let (s, d) = neighbours(self, j, other);
                    out[j - first] = f(j, s, d);
                }
                return;
            };
            let n = b - a;
            let at = |k: usize| {
                let o = ((self.nbr[rs][k] & !UNIFORM) as usize) + (a - rs);
                &other[o..o + n]
            };
            let (o0, o1, o2, o3, o4, o5) = (at(0), at(1), at(2), at(3), at(4), at(5));
            let (d, c) = (self.uniform.0 as f64, self.uniform.1 as f64);
            let dst = &mut out[a - first..b - first];
            for t in 0..n {
                let s = (c * o0[t] + c * o1[t]) + (c * o2[t] + c * o3[t]) + (c * o4[t] + c * o5[t]);
                dst[t] = f(a + t, s, d);
            }
        });
    }
}

/// `Σ coef·x_other` over the neighbours of entry `i` (absent ones read the padding slot, 0,
/// with coupling 0), summed in pairs, and the entry's diagonal. A [`UNIFORM`] entry takes its
/// coefficients from the half (the same values, so the same bits) and reads none of its own.
#[inline(always)]
fn neighbours(h: &Half, i: usize, other: &[f64]) -> (f64, f64) {
    let n = &h.nbr[i];
    if n[0] & UNIFORM != 0 {
        let (d, c) = (h.uniform.0 as f64, h.uniform.1 as f64);
        let t = |k: usize| c * other[(n[k] & !UNIFORM) as usize];
        ((t(0) + t(1)) + (t(2) + t(3)) + (t(4) + t(5)), d)
    } else {
        let c = &h.coef[i];
        let t = |k: usize| c[k] as f64 * other[n[k] as usize];
        ((t(0) + t(1)) + (t(2) + t(3)) + (t(4) + t(5)), h.diag[i] as f64)
    }
}

/// A positive diagonal in f32, rounded up. With the couplings rounded toward zero
/// ([`coef32`]) a weakly diagonally dominant row stays so: the stored operator is again a
/// symmetric positive semi-definite M-matrix, which Gauss–Seidel needs.
#[inline]
pub(super) fn diag32(d: f64) -> f32 {
    let r = d as f32;
    if (r as f64) < d {
        r.next_up()
    } else {
        r
    }
}

/// A non-negative coupling in f32, rounded toward zero (see [`diag32`]).
#[inline]
pub(super) fn coef32(c: f64) -> f32 {
    let r = c as f32;
    if (r as f64) > c {
        r.next_down()
    } else {
        r
    }
}

/// One level: red (index 0) and black (index 1) cells.
#[derive(Debug, Default)]
pub(super) struct Level {
    pub(super) half: [Half; 2],
}

/// Vectors of one level.
#[derive(Debug, Default)]
pub(super) struct Work {
    pub(super) x: [Vec<f64>; 2],
    pub(super) b: [Vec<f64>; 2],
    /// Residual of the red cells (black ones are zero after a black half-sweep).
    pub(super) r: Vec<f64>,
}
