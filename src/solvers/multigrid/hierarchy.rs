//! The multigrid hierarchy of one pressure stencil ([`Multigrid`]): the finest level from the
//! rows, coarser ones until a level is small, each block's parent and children, built into
//! the memory of a hierarchy no longer needed.

use super::lattice::{cell_ijk, LatticeStencil};
use super::level::{unpack, Level, Work};
use super::split::{split, split_rows};
use super::tuning::COARSEST_CELLS;
use crate::geometry::grid::NONE;
use crate::math::buffer::refill;
use crate::solvers::stencil::Stencil;
use rayon::prelude::*;
use std::sync::Mutex;

/// The multigrid hierarchy of one pressure stencil, applied as `z ≈ A⁻¹ r`.
#[derive(Debug, Default)]
pub struct Multigrid {
    pub(super) levels: Vec<Level>,
    /// Packed fine slot of each row ([`NONE`] for a row left out: zero diagonal).
    pub(super) slot_of_row: Vec<u32>,
    /// Row of each fine entry, per colour.
    pub(super) row: [Vec<u32>; 2],
    pub(super) work: Mutex<Vec<Work>>,
}

impl Multigrid {
    /// Builds the levels from the stencil over the unknowns, on a lattice of `n` cells whose
    /// cell `cell_of_row[r]` holds row `r` (in increasing cell order).
    pub fn new(n: [usize; 3], cell_of_row: &[u32], a: &Stencil) -> Multigrid {
        Multigrid::new_in(Multigrid::default(), n, cell_of_row, a)
    }

    /// [`Multigrid::new`] into the memory of a hierarchy no longer needed (a step builds two
    /// systems of about the same size, and the next step two more): its vectors are cleared
    /// and refilled, so a step allocates nothing of the grid's size for its multigrid.
    pub fn new_in(old: Multigrid, n: [usize; 3], cell_of_row: &[u32], a: &Stencil) -> Multigrid {
        let Multigrid { mut levels, mut slot_of_row, mut row, work } = old;
        let mut work = work.into_inner().unwrap_or_else(|e| e.into_inner());
        if levels.is_empty() {
            levels.push(Level::default());
        }
        split_rows(n, cell_of_row, a, &mut levels[0], &mut slot_of_row, &mut row);
        let present = slot_of_row.iter().filter(|&&s| s != NONE).count();
        let mut built = 1;
        if present > COARSEST_CELLS && n.iter().any(|&m| m > 1) {
            let mut fine_n = n;
            let mut lat = LatticeStencil::coarsen_rows(n, cell_of_row, a);
            loop {
                if levels.len() == built {
                    levels.push(Level::default());
                }
                let (finer, coarse) = levels.split_at_mut(built);
                let (finer, coarse) = (&mut finer[built - 1], &mut coarse[0]);
                let coarse_slot = split(&lat, coarse);
                if coarse.half[0].len() + coarse.half[1].len() == 0 {
                    break;
                }
                let cn = lat.n;
                let block = |c: u32| {
                    let [i, j, k] = cell_ijk(fine_n, c as usize);
                    (i / 2) + cn[0] * ((j / 2) + cn[1] * (k / 2))
                };
                for h in finer.half.iter_mut() {
                    h.cell
                        .par_iter()
                        .map(|&c| coarse_slot[block(c)])
                        .collect_into_vec(&mut h.parent);
                }
                // Red children of each block, in lattice order.
                for colour in 0..2 {
                    let len = coarse.half[colour].len();
                    let children = &mut coarse.half[colour].red_children;
                    refill(children, len, [NONE; 4]);
                    let mut filled = vec![0u8; children.len()];
                    for (i, &p) in finer.half[0].parent.iter().enumerate() {
                        if p != NONE && unpack(p).0 == colour {
                            let b = unpack(p).1;
                            children[b][filled[b] as usize] = i as u32;
                            filled[b] += 1;
                        }
                    }
                }
                built += 1;
                if lat.present() <= COARSEST_CELLS || lat.n.iter().all(|&m| m <= 1) {
                    break;
                }
                fine_n = lat.n;
                lat = lat.coarsen();
            }
        }
        levels.truncate(built);
        for h in levels.last_mut().expect("the fine level").half.iter_mut() {
            let n = h.len();
            refill(&mut h.parent, n, NONE);
        }
        work.resize_with(built, Work::default);
        for (w, l) in work.iter_mut().zip(&levels) {
            let (nr, nb) = (l.half[0].len(), l.half[1].len());
            let [x0, x1] = &mut w.x;
            let [b0, b1] = &mut w.b;
            // x of each colour with its padding slot.
            for (v, len) in [(x0, nr + 1), (x1, nb + 1), (b0, nr), (b1, nb), (&mut w.r, nr)] {
                refill(v, len, 0.0);
            }
        }
        Multigrid { levels, slot_of_row, row, work: Mutex::new(work) }
    }

    /// Number of levels, the finest included.
    pub fn levels(&self) -> usize {
        self.levels.len()
    }
}
