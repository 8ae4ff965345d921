//! One V-cycle, `z = V(r)`: red–black Gauss–Seidel half-sweeps down and up, the red residual
//! restricted to the coarser level, its correction prolongated back.

use super::hierarchy::Multigrid;
use super::level::{unpack, Level, Work};
use super::tuning::{CHUNK, COARSEST_SWEEPS, MIN_PAR, SMOOTHING};
use crate::geometry::grid::NONE;
use rayon::prelude::*;

impl Multigrid {
    /// z = V(r): one V-cycle from a zero guess.
    pub fn apply(&self, r: &[f64], z: &mut [f64]) {
        let mut work = self.work.lock().unwrap_or_else(|e| e.into_inner());
        let w = &mut work[0];
        for colour in 0..2 {
            let rows = &self.row[colour];
            w.b[colour].par_iter_mut().with_min_len(MIN_PAR).enumerate().for_each(|(i, bi)| {
                *bi = r[rows[i] as usize];
            });
        }
        self.cycle(0, &mut work);
        let x = &work[0].x;
        z.par_iter_mut().with_min_len(MIN_PAR).zip(&self.slot_of_row).for_each(|(zr, &s)| {
            *zr = if s == NONE {
                0.0
            } else {
                let (colour, i) = unpack(s);
                x[colour][i]
            };
        });
    }

    /// One V-cycle on level `l` for the right-hand side in `work[0].b`, answer in `work[0].x`.
    fn cycle(&self, l: usize, work: &mut [Work]) {
        let level = &self.levels[l];
        let (w, coarser) = work.split_first_mut().expect("work for every level");
        // From a zero guess: the first red half-sweep reads only zeros of the black cells.
        relax_red_from_zero(level, w);
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
        let c = &mut coarser[0];
        let next = &self.levels[l + 1];
        for colour in 0..2 {
            let children = &next.half[colour].red_children;
            let r = &w.r;
            c.b[colour].par_iter_mut().with_min_len(MIN_PAR).enumerate().for_each(|(i, bi)| {
                let mut s = 0.0;
                for &ch in &children[i] {
                    if ch != NONE {
                        s += r[ch as usize];
                    }
                }
                *bi = s;
            });
        }
        self.cycle(l + 1, coarser);
        let xc = &coarser[0].x;
        for colour in 0..2 {
            let parent = &level.half[colour].parent;
            w.x[colour].par_iter_mut().with_min_len(MIN_PAR).zip(parent).for_each(|(x, &p)| {
                if p != NONE {
                    let (pc, pi) = unpack(p);
                    *x += xc[pc][pi];
                }
            });
        }
        for _ in 0..SMOOTHING {
            relax(level, 1, w);
            relax(level, 0, w);
        }
    }
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

/// [`relax`] of the red cells when every black cell is zero (the cycle's first half-sweep):
/// the same bits, `(b + 0)/d` for a neighbour sum of `+0`, without reading the neighbours. The
/// black cells need not even be zero: the next half-sweep overwrites them all, and their
/// padding slot is never written.
fn relax_red_from_zero(level: &Level, w: &mut Work) {
    let h = &level.half[0];
    let b = &w.b[0];
    w.x[0][..h.len()].par_iter_mut().with_min_len(MIN_PAR).enumerate().for_each(|(i, x)| {
        *x = (b[i] + 0.0) / h.diag[i] as f64;
    });
}
