//! One V-cycle, `z = V(r)`: red–black Gauss–Seidel half-sweeps down and up, the red residual
//! restricted to the coarser level, its correction prolongated back.
//!
//! Each loop is a fork of rayon's, and on a two-core machine a fork costs about as much as a
//! few thousand rows of work, so the cycle makes as few as it can without changing a bit:
//! both colours are gathered (or restricted) in one loop, which also does the first red
//! half-sweep from zero; the correction is prolongated to the red cells only (the black
//! half-sweep that follows overwrites the black ones); and [`Multigrid::apply_dot`] scatters
//! the answer and takes its dot product with `r` in one pass.

use super::hierarchy::Multigrid;
use super::level::{unpack, Half, Level, Work};
use super::tuning::{CHUNK, COARSEST_SWEEPS, MIN_PAR, SMOOTHING};
use crate::geometry::grid::{NONE, REDUCE_CHUNK};
use rayon::prelude::*;

// The up-sweep starts with a black half-sweep, which is what lets the prolongation skip the
// black cells.
const _: () = assert!(SMOOTHING >= 1);

impl Multigrid {
    /// z = V(r): one V-cycle from a zero guess.
    pub fn apply(&self, r: &[f64], z: &mut [f64]) {
        let mut work = self.work.lock().unwrap_or_else(|e| e.into_inner());
        self.solve_fine(r, &mut work);
        let x = &work[0].x;
        z.par_iter_mut().with_min_len(MIN_PAR).zip(&self.slot_of_row).for_each(|(zr, &s)| {
            *zr = from_slot(x, s);
        });
    }

    /// [`Multigrid::apply`], and `r·z` as [`crate::geometry::grid::dot`] gives it (the same
    /// chunks, so the same bits), taken as `z` is written instead of in a pass of its own.
    pub fn apply_dot(&self, r: &[f64], z: &mut [f64]) -> f64 {
        let mut work = self.work.lock().unwrap_or_else(|e| e.into_inner());
        self.solve_fine(r, &mut work);
        let x = &work[0].x;
        let parts: Vec<f64> = z
            .par_chunks_mut(REDUCE_CHUNK)
            .zip(r.par_chunks(REDUCE_CHUNK))
            .zip(self.slot_of_row.par_chunks(REDUCE_CHUNK))
            .map(|((z, r), slots)| {
                z.iter_mut().zip(slots).for_each(|(zr, &s)| *zr = from_slot(x, s));
                r.iter().zip(z.iter()).map(|(p, q)| p * q).sum::<f64>()
            })
            .collect();
        parts.iter().sum()
    }

    /// The V-cycle for the rows' right-hand side `r`, its answer in `work[0].x`.
    fn solve_fine(&self, r: &[f64], work: &mut [Work]) {
        let red = &self.levels[0].half[0];
        load_and_relax_red(red, &mut work[0], |colour, i| r[self.row[colour][i] as usize]);
        self.cycle(0, work);
    }

    /// One V-cycle on level `l` for the right-hand side in `work[0].b`, answer in `work[0].x`,
    /// whose red cells already hold the first half-sweep from zero.
    fn cycle(&self, l: usize, work: &mut [Work]) {
        let level = &self.levels[l];
        let (w, coarser) = work.split_first_mut().expect("work for every level");
        if l + 1 == self.levels.len() {
            // Palindromic: R (B R)^COARSEST_SWEEPS.
            for _ in 0..COARSEST_SWEEPS {
                relax(level, 1, w);
                relax(level, 0, w);
            }
            return;
        }
        relax(level, 1, w);
        for _ in 1..SMOOTHING {
            relax(level, 0, w);
            relax(level, 1, w);
        }
        // Residual of the red cells; the black ones were just solved for exactly.
        let red = &level.half[0];
        {
            let [xr, xb] = &w.x;
            let b = &w.b[0];
            w.r.par_chunks_mut(CHUNK).enumerate().for_each(|(c, r)| {
                red.each(c * CHUNK, r, xb, |i, s, d| b[i] - d * xr[i] + s);
            });
        }
        let next = &self.levels[l + 1];
        {
            let r = &w.r;
            load_and_relax_red(&next.half[0], &mut coarser[0], |colour, i| {
                let mut s = 0.0;
                for &ch in &next.half[colour].red_children[i] {
                    if ch != NONE {
                        s += r[ch as usize];
                    }
                }
                s
            });
        }
        self.cycle(l + 1, coarser);
        // The correction of the red cells: the black half-sweep below overwrites the black.
        let xc = &coarser[0].x;
        let parent = &level.half[0].parent;
        w.x[0].par_iter_mut().with_min_len(MIN_PAR).zip(parent).for_each(|(x, &p)| {
            if p != NONE {
                let (pc, pi) = unpack(p);
                *x += xc[pc][pi];
            }
        });
        for _ in 0..SMOOTHING {
            relax(level, 1, w);
            relax(level, 0, w);
        }
    }
}

impl crate::solvers::cg::Precondition for &Multigrid {
    fn precondition(&self, r: &[f64], z: &mut [f64]) {
        self.apply(r, z)
    }

    fn precondition_dot(&self, r: &[f64], z: &mut [f64]) -> f64 {
        self.apply_dot(r, z)
    }
}

/// The value of a packed slot in a level's `x` (0 for a row with no slot).
#[inline]
fn from_slot(x: &[Vec<f64>; 2], s: u32) -> f64 {
    if s == NONE {
        0.0
    } else {
        let (colour, i) = unpack(s);
        x[colour][i]
    }
}

/// Fills both colours of `w.b` with `b(colour, i)` in one parallel loop, and does the
/// cycle's first half-sweep, of the red cells (`red`) when every black one is zero, as each
/// piece of the red right-hand side is filled: the same bits as [`relax`], `(b + 0)/d` for a
/// neighbour sum of `+0`, without reading the neighbours. The black cells need not even be
/// zero: the next half-sweep overwrites them all, and their padding slot is never written.
fn load_and_relax_red(red: &Half, w: &mut Work, b: impl Fn(usize, usize) -> f64 + Sync) {
    let [b0, b1] = &mut w.b;
    let x0 = &mut w.x[0][..red.len()];
    type Piece<'a> = (usize, usize, &'a mut [f64], Option<&'a mut [f64]>);
    let reds = b0
        .par_chunks_mut(MIN_PAR)
        .zip(x0.par_chunks_mut(MIN_PAR))
        .enumerate()
        .map(|(c, (b, x))| -> Piece<'_> { (0, c, b, Some(x)) });
    let blacks =
        b1.par_chunks_mut(MIN_PAR).enumerate().map(|(c, b)| -> Piece<'_> { (1, c, b, None) });
    reds.chain(blacks).for_each(|(colour, c, bs, x)| {
        let first = c * MIN_PAR;
        bs.iter_mut().enumerate().for_each(|(t, v)| *v = b(colour, first + t));
        if let Some(x) = x {
            let diag = &red.diag[first..first + x.len()];
            x.iter_mut().zip(&*bs).zip(diag).for_each(|((x, &bi), &d)| *x = (bi + 0.0) / d as f64);
        }
    });
}

/// Gauss–Seidel half-sweep over one colour: each of its cells solved for with the other
/// colour held.
fn relax(level: &Level, colour: usize, w: &mut Work) {
    let h = &level.half[colour];
    let [x0, x1] = &mut w.x;
    let (x, other) = if colour == 0 { (x0, &*x1) } else { (x1, &*x0) };
    let b = &w.b[colour];
    x[..h.len()].par_chunks_mut(CHUNK).enumerate().for_each(|(c, x)| {
        h.each(c * CHUNK, x, other, |i, s, d| (b[i] + s) / d);
    });
}
