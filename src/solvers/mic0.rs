//! Modified incomplete Cholesky, level 0 (MIC(0)), for the 7-point pressure stencil.
//!
//! The factor has the sparsity of the lower triangle of A in lexicographic cell order, with
//! the dropped fill-in moved back onto the diagonal (the "modified" part, weight τ), which
//! keeps the factor's row sums equal to A's and cuts CG iterations roughly by the square
//! root of the grid size for Poisson problems. τ = 0.97 rather than 1 and the safety
//! threshold σ = 0.25 (a pivot smaller than σ·A_ii falls back to A_ii) follow Bridson's
//! notes: with them MIC(0) is well defined for any weakly diagonally dominant M-matrix, which
//! the weighted stencil always is (weights in [0, 1], ghost-fluid terms only add to the
//! diagonal). Rigid-body terms, a low-rank addition, are left out of the factor.

use crate::geometry::grid::NONE;
use crate::solvers::stencil::Stencil;
use rayon::prelude::*;

/// Bridson's τ: the fraction of dropped fill-in moved to the diagonal.
pub const TAU: f64 = 0.97;
/// Bridson's σ: the smallest pivot kept, relative to the diagonal.
pub const SIGMA: f64 = 0.25;

/// Tiles across y; see the private `Schedule`.
const TILES_J: usize = 4;
/// Planes per tile along z.
const TILE_K: usize = 2;

/// The order of the triangular solves' parallel work (level scheduling by tiles). The rows
/// of one x-line (j, k) are consecutive; the lines are grouped in tiles of TILE × TILE lines
/// in (j, k), and a tile's rows are swept in their sequential order by one thread. A row
/// depends on its −x, −y and −z neighbours only, which lie in the same tile (earlier) or in
/// the tiles at (J−1, K) and (J, K−1). So tiles of one wave J + K are independent, and the
/// waves run in order. Every row is still computed from the same operands in the same order
/// as in a sequential sweep, so the result is bit-identical for any thread count; tiles rather
/// than single lines keep the number of waves (and of rayon joins) small, 2·n/TILE.
#[derive(Clone, Debug, Default)]
struct Schedule {
    /// Rows in all.
    rows: usize,
    /// Row ranges `[start, end)` of the lines, grouped by tile, tiles by wave.
    lines: Vec<(u32, u32)>,
    /// Ranges of `lines`, one per tile, sorted by wave.
    tiles: Vec<(usize, usize)>,
    /// The tiles of wave `w` are `tiles[wave[w]..wave[w + 1]]`.
    wave: Vec<usize>,
}

impl Schedule {
    fn new(n: [usize; 3], cell_of_row: &[u32]) -> Schedule {
        let tile_j = n[1].div_ceil(TILES_J).max(1);
        let tiles_j = n[1].div_ceil(tile_j).max(1);
        // (wave, tile, start, end) of each line, in row order.
        let mut lines: Vec<(usize, usize, u32, u32)> = Vec::new();
        let mut last_line = usize::MAX;
        for (r, &c) in cell_of_row.iter().enumerate() {
            let line = c as usize / n[0];
            if line != last_line {
                let (j, k) = (line % n[1], line / n[1]);
                let (tj, tk) = (j / tile_j, k / TILE_K);
                lines.push((tj + tk, tj + tiles_j * tk, r as u32, r as u32 + 1));
                last_line = line;
            } else {
                lines.last_mut().expect("a line").3 = r as u32 + 1;
            }
        }
        // Stable: rows keep their order inside a tile.
        lines.sort_by_key(|l| (l.0, l.1));
        let (mut tiles, mut wave) = (Vec::new(), vec![0]);
        for (i, l) in lines.iter().enumerate() {
            if i == 0 || l.1 != lines[i - 1].1 {
                if i > 0 && l.0 != lines[i - 1].0 {
                    wave.push(tiles.len());
                }
                tiles.push((i, i + 1));
            } else {
                tiles.last_mut().expect("a tile").1 = i + 1;
            }
        }
        if !tiles.is_empty() {
            wave.push(tiles.len());
        }
        let rows = cell_of_row.len();
        Schedule { rows, lines: lines.iter().map(|l| (l.2, l.3)).collect(), tiles, wave }
    }

    /// Calls `f` on the row range of every line, wave after wave, the tiles of a wave in
    /// parallel and the lines of a tile in order. On one thread, `f` of every row at once:
    /// the sequential sweep the waves reorder, so the same bits, without a rayon split per
    /// wave and with the rows read in their order in memory.
    fn forward(&self, f: impl Fn(usize, usize) + Sync) {
        if rayon::current_num_threads() == 1 {
            return f(0, self.rows);
        }
        for w in self.wave.windows(2) {
            self.tiles[w[0]..w[1]].par_iter().with_min_len(1).for_each(|&(a, b)| {
                for &(s, e) in &self.lines[a..b] {
                    f(s as usize, e as usize);
                }
            });
        }
    }

    /// As [`Schedule::forward`], everything in reverse order.
    fn backward(&self, f: impl Fn(usize, usize) + Sync) {
        if rayon::current_num_threads() == 1 {
            return f(0, self.rows);
        }
        for w in self.wave.windows(2).rev() {
            self.tiles[w[0]..w[1]].par_iter().with_min_len(1).for_each(|&(a, b)| {
                for &(s, e) in self.lines[a..b].iter().rev() {
                    f(s as usize, e as usize);
                }
            });
        }
    }
}

/// A vector the triangular solves write from several threads at once.
///
/// Soundness rests on the schedule: every row is written by exactly one task (the one whose
/// tile holds it), and a row is read only by that task after writing it, or by tasks of a
/// later wave, which start after the wave that wrote it has joined (a rayon join orders the
/// memory). Relaxed atomics would need no `unsafe`, but the compiler may not reorder loads
/// across them, and the solve is slower for it (docs/performance.md, "Why the hot paths are
/// written as they are").
struct Shared<'a> {
    ptr: *mut f64,
    len: usize,
    _marker: std::marker::PhantomData<&'a mut [f64]>,
}

// SAFETY: see the type's doc; the schedule keeps the threads' accesses apart.
unsafe impl Send for Shared<'_> {}
// SAFETY: as above.
unsafe impl Sync for Shared<'_> {}

impl<'a> Shared<'a> {
    fn new(v: &'a mut [f64]) -> Self {
        Shared { ptr: v.as_mut_ptr(), len: v.len(), _marker: std::marker::PhantomData }
    }

    #[inline]
    fn get(&self, i: usize) -> f64 {
        assert!(i < self.len);
        // SAFETY: in bounds; no other thread writes row i while it may be read (type doc).
        unsafe { *self.ptr.add(i) }
    }

    #[inline]
    fn set(&self, i: usize, x: f64) {
        assert!(i < self.len);
        // SAFETY: in bounds; only this task touches row i during its wave (type doc).
        unsafe { *self.ptr.add(i) = x }
    }
}

/// The MIC(0) factor, stored as the inverse square roots of its pivots, and per row the
/// coefficients of its −x, −y, −z neighbours in the forward solve.
///
/// The factorisation and the triangular solves run wave by wave (see the private
/// `Schedule`): each row is written by exactly one thread and read only after the wave that
/// wrote it has joined, so the answer does not depend on the number of threads.
#[derive(Clone, Debug, Default)]
pub struct Mic0 {
    inv: Vec<f64>,
    /// Per row, `A_{m,+axis} · inv[m]` for its −axis neighbour m (0 without one): the
    /// forward solve's product `A_{m,+axis} · inv[m] · q[m]`, whose first two factors it
    /// read from two other rows (two more cache lines a neighbour), made once per factor.
    /// The same bits, as the product is evaluated left to right.
    lower: Vec<[f64; 3]>,
    schedule: Schedule,
    /// Whether every row's −x neighbour is the row before it and its +x neighbour the row
    /// after (rows in lexicographic order, as [`Mic0::new`] asks): then a sweep on one
    /// thread carries that neighbour's value from the row it just solved
    /// ([`Mic0::apply_in_order`]).
    x_adjacent: bool,
}

impl Mic0 {
    /// Factors the stencil of the rows in cells `cell_of_row` of a lattice of `n` cells. Rows
    /// must be in lexicographic order (x fastest), so the −x, −y, −z neighbours of a row come
    /// before it.
    pub fn new(a: &Stencil, n: [usize; 3], cell_of_row: &[u32]) -> Mic0 {
        let schedule = Schedule::new(n, cell_of_row);
        let n = a.diag.len();
        let mut inv = vec![0.0; n];
        let inv_s = Shared::new(&mut inv);
        let (diag, nbr, plus) = (&a.diag[..], &a.nbr[..], &a.plus[..]);
        schedule.forward(|start, end| {
            for r in start..end {
                let mut e = diag[r];
                for axis in 0..3 {
                    let m = nbr[r][2 * axis];
                    if m == NONE {
                        continue;
                    }
                    let m = m as usize;
                    let im = inv_s.get(m);
                    let c = plus[m][axis] * im;
                    let others: f64 = (0..3).filter(|&b| b != axis).map(|b| plus[m][b]).sum();
                    e -= c * c + TAU * plus[m][axis] * others * im * im;
                }
                if e < SIGMA * diag[r] {
                    e = diag[r];
                }
                inv_s.set(r, if e > 0.0 { 1.0 / e.sqrt() } else { 0.0 });
            }
        });
        let lower = nbr
            .par_iter()
            .with_min_len(crate::math::par::MIN_LEN)
            .map(|nb| {
                std::array::from_fn(|axis| match nb[2 * axis] {
                    NONE => 0.0,
                    m => plus[m as usize][axis] * inv[m as usize],
                })
            })
            .collect();
        let x_adjacent = nbr.iter().enumerate().all(|(i, nb)| {
            (nb[0] == NONE || nb[0] as usize + 1 == i) && (nb[1] == NONE || nb[1] as usize == i + 1)
        });
        Mic0 { inv, lower, schedule, x_adjacent }
    }

    /// z = (L Lᵀ)⁻¹ r.
    pub fn apply(&self, a: &Stencil, r: &[f64], z: &mut [f64]) {
        if self.x_adjacent && rayon::current_num_threads() == 1 {
            return self.apply_in_order(a, r, z);
        }
        // Slices in locals: the compiler cannot keep a Vec's pointer in a register across
        // stores it cannot prove to be elsewhere.
        let (inv, lower, nbr, plus) = (&self.inv[..], &self.lower[..], &a.nbr[..], &a.plus[..]);
        let q = Shared::new(z);
        // Forward: L q = r.
        self.schedule.forward(|start, end| {
            for i in start..end {
                let mut t = r[i];
                for axis in 0..3 {
                    let m = nbr[i][2 * axis];
                    if m != NONE {
                        t += lower[i][axis] * q.get(m as usize);
                    }
                }
                q.set(i, t * inv[i]);
            }
        });
        // Backward: Lᵀ z = q, in place.
        self.schedule.backward(|start, end| {
            for i in (start..end).rev() {
                let mut t = q.get(i);
                for axis in 0..3 {
                    let p = nbr[i][2 * axis + 1];
                    if p != NONE {
                        t += plus[i][axis] * inv[i] * q.get(p as usize);
                    }
                }
                q.set(i, t * inv[i]);
            }
        });
    }

    /// [`Mic0::apply`] on one thread, row after row: every row from the same operands in the
    /// same order as the waves take them, so the same bits. The value of a row's ±x
    /// neighbour, the row just solved, is carried in a register: read back from memory, the
    /// store and the load added their latency to every row's, which waits on it.
    fn apply_in_order(&self, a: &Stencil, r: &[f64], z: &mut [f64]) {
        let n = self.inv.len();
        let (inv, lower, nbr, plus) = (&self.inv[..n], &self.lower[..n], &a.nbr[..n], &a.plus[..n]);
        let (r, z) = (&r[..n], &mut z[..n]);
        // Forward: L q = r.
        let mut last = 0.0;
        for i in 0..n {
            let (nb, l) = (&nbr[i], &lower[i]);
            let mut t = r[i];
            if nb[0] != NONE {
                t += l[0] * last;
            }
            if nb[2] != NONE {
                t += l[1] * z[nb[2] as usize];
            }
            if nb[4] != NONE {
                t += l[2] * z[nb[4] as usize];
            }
            last = t * inv[i];
            z[i] = last;
        }
        // Backward: Lᵀ z = q, in place.
        for i in (0..n).rev() {
            let (nb, pl) = (&nbr[i], &plus[i]);
            let mut t = z[i];
            if nb[1] != NONE {
                t += pl[0] * inv[i] * last;
            }
            if nb[3] != NONE {
                t += pl[1] * inv[i] * z[nb[3] as usize];
            }
            if nb[5] != NONE {
                t += pl[2] * inv[i] * z[nb[5] as usize];
            }
            last = t * inv[i];
            z[i] = last;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Mic0;
    use crate::solvers::testing::tank;

    /// The factor and its application give the same bits on one thread (rows in order, the
    /// ±x neighbour carried from the row before) as on two (wave by wave), on a pool with a
    /// sloped surface and a solid blob, whose rows lack some neighbours of every kind.
    #[test]
    fn one_thread_in_order_is_the_waves_bit_for_bit() {
        let sys = tank([40, 24, 30], 0.45);
        let a = sys.operator();
        let r: Vec<f64> = (0..a.diag.len() as u64)
            .map(|i| ((i.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40) as f64) / 1e7 - 0.8)
            .collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let m = Mic0::new(a, sys.grid.n, &sys.cell_of_row);
                assert!(m.x_adjacent);
                let mut z = vec![0.0; r.len()];
                m.apply(a, &r, &mut z);
                (m.inv, z)
            })
        };
        let ((inv1, z1), (inv2, z2)) = (run(1), run(2));
        let same = |x: &[f64], y: &[f64]| x.iter().zip(y).all(|(p, q)| p.to_bits() == q.to_bits());
        assert!(same(&inv1, &inv2) && same(&z1, &z2));
        assert!(z1.iter().any(|&x| x != 0.0));
    }
}
