//! Closing air pockets: a hole in the marker particles inside the liquid is liquid, by a
//! function of φ_L that is continuous where the classification it replaces jumps.
//!
//! φ_L from the particles (`min_p |x − x_p| − r`) is positive wherever the particles leave a
//! gap, also inside the liquid. Such a pocket is a cell of zero pressure in the middle of the
//! liquid, a sink the projection drains the liquid into, and as the particles around it move
//! by a hair it appears and vanishes: a jump of the step (on `surge_ball`, one such cell
//! changing kind moved the ball's velocity by 2.6e-4 m/s within the step, and by 7.5e-3 m/s
//! fifteen steps later).
//!
//! The closing lowers φ in the air to what the air "can reach": with κ = `radius`·dx, for an
//! air cell c (φ_c > 0),
//!
//! ```text
//! φ̃_c = max over paths c = p₀, p₁, …, p_m = e through open faces, all but e air, of
//!        min(φ_{p₀}, …, φ_{p_{m−1}}, s(e)),
//! s(e) = φ_e for a liquid cell e, σ(φ_e) for an air one:
//! σ(φ) = −φ up to κ, 3φ − 4κ up to 2κ, φ beyond.
//! ```
//!
//! Liquid cells keep their φ. An air cell that reaches air at least 2κ from the particles
//! through air keeps its φ too (σ = φ there, and the path's minimum is its own φ). An air
//! region whose φ stays below 4κ/3 everywhere (a pocket a particle gap opened) gets φ̃ < 0,
//! and is liquid. φ̃ is continuous: a max–min of continuous functions of φ, over paths that
//! change only where a cell crosses φ = 0, and there its value is 0 as air and as liquid.
//! It is Lipschitz (3 in the max norm, σ's steepest slope) and piecewise one of the φ's: its
//! derivative is a selection, [`Pockets::adjoint`]. Only air cells nearer the particles than
//! 2κ can change (a shell about a cell thick over the surface); they are searched by a
//! max-first Dijkstra.

use crate::geometry::grid::{Grid, NONE};
use crate::geometry::weights::{open_neighbour, FaceWeights};
use crate::math::par::MIN_LEN;
use rayon::prelude::*;
use std::cmp::Ordering;
use std::collections::BinaryHeap;

/// The cells [`close_pockets`] changed: each one's φ̃ is `slope`·φ of its `origin` plus a
/// constant, in the φ it was given.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Pockets {
    /// (cell, origin cell, slope) for each changed cell.
    pub changed: Vec<(u32, u32, f64)>,
}

impl Pockets {
    /// Cells whose φ the closing changed.
    pub fn len(&self) -> usize {
        self.changed.len()
    }

    /// Whether the closing changed nothing.
    pub fn is_empty(&self) -> bool {
        self.changed.is_empty()
    }

    /// Adjoint of [`close_pockets`]: turns ∂L/∂φ̃ (`bar`, in place) into ∂L/∂φ.
    pub fn adjoint(&self, bar: &mut [f64]) {
        let given: Vec<f64> = self.changed.iter().map(|&(c, _, _)| bar[c as usize]).collect();
        for (&(c, _, _), &g) in self.changed.iter().zip(&given) {
            bar[c as usize] -= g;
        }
        for (&(_, origin, slope), &g) in self.changed.iter().zip(&given) {
            bar[origin as usize] += slope * g;
        }
    }
}

/// σ(φ) (see the module's notes) of an air cell, and its slope.
#[inline]
fn sigma(phi: f64, kappa: f64) -> (f64, f64) {
    if phi <= kappa {
        (-phi, -1.0)
    } else if phi < 2.0 * kappa {
        (3.0 * phi - 4.0 * kappa, 3.0)
    } else {
        (phi, 1.0)
    }
}

/// A heap entry: a cell's current value (max first).
#[derive(PartialEq)]
struct Entry(f64, u32);

impl Eq for Entry {}

impl PartialOrd for Entry {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for Entry {
    fn cmp(&self, other: &Self) -> Ordering {
        self.0.total_cmp(&other.0).then(other.1.cmp(&self.1))
    }
}

/// Closes the air pockets of `phi` (cell centres) in place, `radius` (κ, in cells) the
/// depth below which an air region is a pocket (see the module's notes). Cells connect
/// through faces of positive weight in `weights`. Returns the cells it changed, for the
/// adjoint.
pub fn close_pockets(phi: &mut [f64], grid: &Grid, weights: &FaceWeights, radius: f64) -> Pockets {
    let kappa = radius * grid.dx;
    let cells = grid.cells();
    let axes = weights.axes();
    let open = |c: usize, ijk: [usize; 3], a: usize, side: usize| {
        open_neighbour(grid, &axes, c, ijk, a, side).map(|(n, _)| n)
    };
    let in_shell = |p: f64| p > 0.0 && p < 2.0 * kappa;
    // The shell, in increasing cell order (a cell's place in it by a binary search: the shell
    // is about a cell thick over the surface, so arrays over it, not over the grid).
    let shell: Vec<u32> = phi
        .par_iter()
        .enumerate()
        .with_min_len(MIN_LEN)
        .filter(|(_, &p)| in_shell(p))
        .map(|(c, _)| c as u32)
        .collect();
    if shell.is_empty() {
        return Pockets::default();
    }
    let place = |c: usize| shell.binary_search(&(c as u32)).expect("a shell cell");
    // Per shell cell: its value so far, the origin of that value and the slope in it.
    let mut value = vec![f64::NAN; shell.len()];
    let mut origin = vec![NONE; shell.len()];
    let mut slope = vec![1.0; shell.len()];
    let mut heap = BinaryHeap::with_capacity(shell.len());
    for (i, &c) in shell.iter().enumerate() {
        let c = c as usize;
        let ijk = cells.ijk(c);
        // Its own σ, or a neighbour that ends a path: liquid (its φ), or air beyond the shell
        // (then the path's minimum is the cell's own φ, the most it can have).
        let (mut v, mut from, mut k) = {
            let (v, k) = sigma(phi[c], kappa);
            (v, c, k)
        };
        for a in 0..3 {
            for s in 0..2 {
                let Some(n) = open(c, ijk, a, s) else { continue };
                let end = if phi[n] <= 0.0 {
                    (phi[n], n)
                } else if phi[n] >= 2.0 * kappa {
                    (phi[c], c)
                } else {
                    continue;
                };
                if end.0 > v {
                    (v, from, k) = (end.0, end.1, 1.0);
                }
            }
        }
        (value[i], origin[i], slope[i]) = (v, from as u32, k);
        heap.push(Entry(v, i as u32));
    }
    while let Some(Entry(v, i)) = heap.pop() {
        let i = i as usize;
        if v < value[i] {
            continue;
        }
        let c = shell[i] as usize;
        let ijk = cells.ijk(c);
        for a in 0..3 {
            for s in 0..2 {
                let Some(n) = open(c, ijk, a, s) else { continue };
                if !in_shell(phi[n]) {
                    continue;
                }
                let candidate = phi[n].min(v);
                let m = place(n);
                if candidate > value[m] {
                    value[m] = candidate;
                    if phi[n] <= v {
                        (origin[m], slope[m]) = (n as u32, 1.0);
                    } else {
                        (origin[m], slope[m]) = (origin[i], slope[i]);
                    }
                    heap.push(Entry(candidate, m as u32));
                }
            }
        }
    }
    let mut changed = Vec::new();
    for (i, &c) in shell.iter().enumerate() {
        let c = c as usize;
        if value[i] != phi[c] {
            changed.push((c as u32, origin[i], slope[i]));
            phi[c] = value[i];
        }
    }
    Pockets { changed }
}
