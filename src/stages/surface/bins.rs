//! Particles binned by cell, the cells around a cell, and L∞ distances in cells.

use crate::geometry::grid::{floor_index, Grid};
use crate::math::par::min_pieces;
use crate::math::Vec3;
use rayon::prelude::*;

/// Particles sorted by cell (a counting sort, so the order is deterministic).
#[derive(Clone, Debug, Default)]
pub struct Bins {
    /// `start[c]..start[c + 1]` indexes `items` for cell c.
    pub start: Vec<u32>,
    /// Particle indices.
    pub items: Vec<u32>,
}

impl Bins {
    /// Bins `pos` into the cells of `grid`, each cell's particles in increasing order. In
    /// parallel over z-slabs after a counting sort of the particles by slab.
    pub fn new(pos: &[Vec3], grid: &Grid) -> Bins {
        let cells = grid.num_cells();
        let slab = grid.n[0] * grid.n[1];
        let cell_of: Vec<u32> = pos.par_iter().map(|x| cell_of(grid, *x) as u32).collect();
        let by_slab = SlabBuckets::new(&cell_of, |c| c as usize / slab, grid.n[2]);
        let mut start = vec![0u32; cells + 1];
        let slabs = start[..cells].par_chunks_mut(slab).with_min_len(min_pieces(slab));
        slabs.enumerate().for_each(|(k, counts)| {
            for &p in by_slab.of(k) {
                counts[cell_of[p as usize] as usize - k * slab] += 1;
            }
            let mut sum = by_slab.start[k];
            for c in counts.iter_mut() {
                (*c, sum) = (sum, sum + *c);
            }
        });
        start[cells] = pos.len() as u32;
        let mut items = vec![0u32; pos.len()];
        let parts = by_slab.split_mut(&mut items).into_par_iter().with_min_len(min_pieces(slab));
        parts.enumerate().for_each(|(k, part)| {
            let first = by_slab.start[k];
            let mut fill: Vec<u32> = start[k * slab..(k + 1) * slab].to_vec();
            for &p in by_slab.of(k) {
                let f = &mut fill[cell_of[p as usize] as usize - k * slab];
                part[(*f - first) as usize] = p;
                *f += 1;
            }
        });
        Bins { start, items }
    }

    /// Particles in cell `c`.
    #[inline]
    pub fn cell(&self, c: usize) -> &[u32] {
        &self.items[self.start[c] as usize..self.start[c + 1] as usize]
    }
}

/// Particle indices sorted into buckets (a counting sort, in particle order within each).
pub(super) struct SlabBuckets {
    /// `start[b]..start[b + 1]` indexes `items` for bucket b.
    start: Vec<u32>,
    items: Vec<u32>,
}

impl SlabBuckets {
    /// Buckets `0..n` of the particles, particle p in bucket `bucket(keys[p])`. A counting
    /// sort of each fixed chunk of particles in parallel, then each bucket gathers its part
    /// of every chunk in chunk order: particle order within a bucket, on any thread count.
    pub(super) fn new(keys: &[u32], bucket: impl Fn(u32) -> usize + Sync, n: usize) -> SlabBuckets {
        const CHUNK: usize = 1 << 16;
        // Per chunk: its particles sorted by bucket, and where each bucket starts.
        let sorted: Vec<(Vec<u32>, Vec<u32>)> = keys
            .par_chunks(CHUNK)
            .enumerate()
            .map(|(ch, part)| {
                let mut start = vec![0u32; n + 1];
                for &k in part {
                    start[bucket(k) + 1] += 1;
                }
                for b in 0..n {
                    start[b + 1] += start[b];
                }
                let mut fill = start.clone();
                let mut items = vec![0u32; part.len()];
                for (i, &k) in part.iter().enumerate() {
                    let f = &mut fill[bucket(k)];
                    items[*f as usize] = (ch * CHUNK + i) as u32;
                    *f += 1;
                }
                (items, start)
            })
            .collect();
        let mut start = vec![0u32; n + 1];
        for b in 0..n {
            start[b + 1] = start[b] + sorted.iter().map(|(_, s)| s[b + 1] - s[b]).sum::<u32>();
        }
        let mut items = vec![0u32; keys.len()];
        let mut parts = Vec::with_capacity(n);
        let mut rest = items.as_mut_slice();
        for w in start.windows(2) {
            let (part, tail) = rest.split_at_mut((w[1] - w[0]) as usize);
            parts.push(part);
            rest = tail;
        }
        parts.into_par_iter().enumerate().for_each(|(b, part)| {
            let mut at = 0;
            for (chunk, s) in &sorted {
                let run = &chunk[s[b] as usize..s[b + 1] as usize];
                part[at..at + run.len()].copy_from_slice(run);
                at += run.len();
            }
        });
        SlabBuckets { start, items }
    }

    /// The particles of bucket `b`.
    pub(super) fn of(&self, b: usize) -> &[u32] {
        &self.items[self.start[b] as usize..self.start[b + 1] as usize]
    }

    /// `v` (one entry per particle) split into each bucket's run.
    fn split_mut<'a, T>(&self, mut v: &'a mut [T]) -> Vec<&'a mut [T]> {
        let mut parts = Vec::with_capacity(self.start.len() - 1);
        for w in self.start.windows(2) {
            let (part, rest) = v.split_at_mut((w[1] - w[0]) as usize);
            parts.push(part);
            v = rest;
        }
        parts
    }
}

/// The cell containing `x` (clamped into the grid).
#[inline]
pub fn cell_of(grid: &Grid, x: Vec3) -> usize {
    // Truncation is the floor here: a negative coordinate saturates to cell 0 either way.
    // Written out: as an array map this was left as a call (`try_map`) in some builds.
    let at = |a: f64, d: usize| floor_index(a / grid.dx).min(grid.n[d] - 1);
    grid.cell(at(x.x, 0), at(x.y, 1), at(x.z, 2))
}

/// Calls `f`, in lattice order, for the cells of [`for_neighbour_cells`] exactly `ring` cells
/// (L∞) from (i, j, k): its cells less those within `ring − 1`.
#[inline(always)]
pub(super) fn for_ring_cells(grid: &Grid, ijk: [usize; 3], ring: usize, mut f: impl FnMut(usize)) {
    let lo = ijk.map(|x| x.saturating_sub(ring));
    let hi = [0, 1, 2].map(|d| (ijk[d] + ring).min(grid.n[d] - 1));
    let prune = ring >= 2;
    let [i, n0] = [ijk[0], grid.n[0]];
    // Along x, in a row `ring` away along y or z: all of the cube's cells, or (pruned) those
    // less than `ring` away.
    let across = if prune {
        (i.saturating_sub(ring - 1), (i + ring - 1).min(hi[0]))
    } else {
        (lo[0], hi[0])
    };
    for k in lo[2]..=hi[2] {
        for j in lo[1]..=hi[1] {
            let at =
                usize::from(k.abs_diff(ijk[2]) == ring) + usize::from(j.abs_diff(ijk[1]) == ring);
            match at {
                // Only the two cells `ring` away along x.
                0 => {
                    if i >= ring {
                        f(grid.cell(i - ring, j, k));
                    }
                    if i + ring < n0 {
                        f(grid.cell(i + ring, j, k));
                    }
                }
                2 if prune => continue,
                _ => {
                    for x in across.0..=across.1 {
                        f(grid.cell(x, j, k));
                    }
                }
            }
        }
    }
}

/// Calls `f`, in lattice order, for every cell within `reach` cells of (i, j, k) that can
/// hold a point within `reach·dx` of its centre: the cube of side 2·reach + 1, less, from
/// reach 2 on, the cells `reach` away along two or three axes (their nearest point is
/// √2·(reach − ½)·dx > reach·dx away: 44 of the 125 cells at reach 2).
#[cfg(test)]
pub(super) fn for_neighbour_cells(
    grid: &Grid,
    ijk: [usize; 3],
    reach: usize,
    mut f: impl FnMut(usize),
) {
    let lo = ijk.map(|x| x.saturating_sub(reach));
    let hi = [0, 1, 2].map(|d| (ijk[d] + reach).min(grid.n[d] - 1));
    let prune = reach >= 2;
    let at_reach = |x: usize, d: usize| usize::from(prune && x.abs_diff(ijk[d]) == reach);
    // Along x, in a row already `reach` away along y or z: the cells less than `reach` away.
    let inner = (
        ijk[0].saturating_sub(reach.saturating_sub(1)),
        (ijk[0] + reach).saturating_sub(1).min(hi[0]),
    );
    for k in lo[2]..=hi[2] {
        for j in lo[1]..=hi[1] {
            let (i0, i1) = match at_reach(k, 2) + at_reach(j, 1) {
                0 => (lo[0], hi[0]),
                1 => inner,
                _ => continue,
            };
            for i in i0..=i1 {
                f(grid.cell(i, j, k));
            }
        }
    }
}
