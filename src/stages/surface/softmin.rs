//! φ_L as a soft minimum of the particles' distances instead of the nearest one's, and its
//! adjoint.
//!
//! The nearest particle's distance `min_p |x − x_p| − r` has a kink wherever another
//! particle becomes a cell's nearest, and a surface's cells pass through such ties all the
//! time as the particles move: after 50 steps of `surge_ball` the loss has a kink every
//! micrometre along the ball's height. The soft minimum, with softness τ,
//!
//! ```text
//! φ = −τ ln( Σ_p c_p e^{−(|x − x_p| − r)/τ} + e^{−φ_far/τ} ),  c_p = (1 − |x − x_p|²/R²)³,
//! ```
//!
//! is infinitely differentiable in the particles' positions: within a few τ of a tie it turns
//! smoothly from one particle's distance to the other's. The cut-off c_p (and its first two
//! derivatives) vanishes at the reach R = 2·dx, so a particle entering or leaving a cell's
//! reach moves φ smoothly, and the last term, the far value φ_far = R − r the nearest
//! particle's distance is capped at, takes over continuously as a cell's particles all leave
//! it. A lone particle well inside the reach gives its distance less r (and less
//! τ·ln c_p, a hair). It stays a distance to the particles, not a mean of them (Zhu &
//! Bridson's averaged kernel, tried first, reads a sheet thinner than a cell, or particles
//! bunched into a corner, as air, and the dam break lost 7% of its volume over 100 steps):
//! a particle within r of a cell's centre makes it liquid, as before. A cell among many
//! particles reads a little deeper than the nearest one (τ·ln of how many are about as
//! near); the radius r is set so that a flat, freshly seeded surface on a cell face is
//! reconstructed exactly on it (see [`soft_particle_radius`]).

use super::lanes::{Points, Terms};
use super::*;
use crate::geometry::grid::{Grid, NONE};
use crate::math::Vec3;
use rayon::prelude::*;

/// Marks a cell whose φ the soft minimum set (in the list of the particles each cell's φ
/// moves with; its adjoint finds them again).
pub(super) const SOFT: u32 = NONE - 1;

/// The reach R of a cell's soft minimum, in cells: the nearest particle's search reach.
pub const SOFT_REACH: f64 = 2.0;

/// The cell offsets (L∞ at most 2) whose nearest point is within `reach` cells of a cell
/// centre: the cells whose particles a centre's soft minimum can see.
fn block(reach: f64) -> Vec<[i64; 3]> {
    let mut out = Vec::new();
    for k in -2i64..=2 {
        for j in -2i64..=2 {
            for i in -2i64..=2 {
                let gap = |o: i64| ((o.abs() as f64) - 0.5).max(0.0).powi(2);
                if gap(i) + gap(j) + gap(k) < reach * reach {
                    out.push([i, j, k]);
                }
            }
        }
    }
    out
}

/// The cell at lattice index `at` (up to two cells beyond the tank): itself inside the
/// tank, or beyond a wall the cell inside it mirrors, and along which axes it is mirrored.
/// The soft minimum sees the liquid continued through the walls as their mirror image, as
/// the deposit does: a flat surface stays flat up to the wall, so still water stays still.
#[inline]
fn mirror(grid: &Grid, at: [i64; 3]) -> Option<(usize, [i8; 3])> {
    let mut c = [0usize; 3];
    let mut flip = [0i8; 3];
    for d in 0..3 {
        let n = grid.n[d] as i64;
        let i = if at[d] < 0 {
            flip[d] = -1;
            -1 - at[d]
        } else if at[d] >= n {
            flip[d] = 1;
            2 * n - 1 - at[d]
        } else {
            at[d]
        };
        if !(0..n).contains(&i) {
            return None;
        }
        c[d] = i as usize;
    }
    Some((grid.cell(c[0], c[1], c[2]), flip))
}

/// `p` mirrored across the walls `flip` names: per axis −1 the lower wall, 1 the upper, 0
/// neither.
#[inline]
fn reflect(p: Vec3, flip: [i8; 3], size: Vec3) -> Vec3 {
    let mut q = p;
    for d in 0..3 {
        match flip[d] {
            -1 => q[d] = -p[d],
            1 => q[d] = 2.0 * size[d] - p[d],
            _ => {}
        }
    }
    q
}

/// Calls `f` with the lattice index of the cell `own` (inside a tank of `n` cells) and of
/// each of its mirror images within two cells beyond a wall, with the axes it is mirrored
/// along: the cells whose particles [`SoftSdf::sum`] reads as mirrored.
#[inline]
fn for_images(own: [i64; 3], n: [i64; 3], mut f: impl FnMut([i64; 3], [i8; 3])) {
    let options = |d: usize| {
        let mut out = [(own[d], 0i8); 3];
        let mut len = 1;
        if own[d] < 2 {
            out[len] = (-1 - own[d], -1);
            len += 1;
        }
        if own[d] >= n[d] - 2 {
            out[len] = (2 * n[d] - 1 - own[d], 1);
            len += 1;
        }
        (out, len)
    };
    let (ox, oy, oz) = (options(0), options(1), options(2));
    for &(k, fz) in &oz.0[..oz.1] {
        for &(j, fy) in &oy.0[..oy.1] {
            for &(i, fx) in &ox.0[..ox.1] {
                f([i, j, k], [fx, fy, fz]);
            }
        }
    }
}

/// The kernel of a particle at squared distance `d2`: c_p e^{−|x − x_p|/τ} (the r of the
/// exponent taken out, see [`Kernel::phi`]), zero beyond the reach.
#[derive(Clone, Copy, Debug)]
struct Kernel {
    /// The terms' cut-off (1/R²) and softness (1/τ).
    terms: Terms,
    /// τ.
    tau: f64,
    /// The far value's term, e^{−R/τ}.
    far: f64,
}

impl Kernel {
    /// For reach `reach` and softness `tau` (both in the same unit).
    fn new(reach: f64, tau: f64) -> Kernel {
        let terms = Terms::new(1.0 / (reach * reach), 1.0 / tau);
        Kernel { terms, tau, far: (-reach / tau).exp() }
    }

    #[inline(always)]
    fn term(&self, d2: f64) -> f64 {
        self.terms.term(d2)
    }

    /// φ of the sum `sum` of the terms (the far value's included) for radius `radius`:
    /// −τ ln(Σ c_p e^{−(d_p − r)/τ} + e^{−(R − r)/τ}) = −τ ln(sum) − r.
    #[inline]
    fn phi(&self, sum: f64, radius: f64) -> f64 {
        -self.tau * sum.ln() - radius
    }
}

/// The particle radius r for the soft minimum of softness `tau` (cells) and `m` particles
/// per axis: as [`particle_radius`] for the nearest particle, the r that puts a flat, freshly
/// seeded surface on a cell face exactly halfway between the cell centres that straddle it.
pub fn soft_particle_radius(dx: f64, m: usize, tau: f64) -> f64 {
    let off = sub_offsets(m);
    let kernel = Kernel::new(SOFT_REACH, tau);
    // Liquid fills z < 0 (cells of size 1 centred on x, y ∈ ℤ, z ∈ [c, c + 1] for c < 0):
    // seen from (0, 0, ±½) its cells lie (i, j, c) and (i, j, c + 1) away. With r = 0, φ is
    // the soft distance.
    let distance = |above: bool| {
        let mut sum = kernel.far;
        for i in -3..=3 {
            for j in -3..=3 {
                for c in -3..=-1 {
                    let o = [i, j, if above { c } else { c + 1 }];
                    sum += lattice_terms(&kernel, &off, o, 1.0);
                }
            }
        }
        kernel.phi(sum, 0.0)
    };
    0.5 * (distance(true) + distance(false)) * dx
}

/// The soft minimum's φ at the centre of a cell deep in freshly seeded liquid, for the
/// surface model `model` (softness > 0) on cells of size `dx`.
pub(super) fn soft_full_phi(dx: f64, model: &SurfaceModel) -> f64 {
    let off = sub_offsets(model.per_axis);
    let kernel = Kernel::new(SOFT_REACH * dx, model.softness);
    let cells: f64 = block(SOFT_REACH).iter().map(|o| lattice_terms(&kernel, &off, *o, dx)).sum();
    kernel.phi(kernel.far + cells, model.radius)
}

/// The terms of a cell `o` cells from a centre holding the seeding sub-lattice `off`: what a
/// deep cell there adds to the centre's sum.
fn lattice_terms(kernel: &Kernel, off: &[f64], o: [i64; 3], dx: f64) -> f64 {
    let mut sum = 0.0;
    for &oz in off {
        for &oy in off {
            for &ox in off {
                let p = Vec3::new(ox, oy, oz) - Vec3::splat(0.5);
                let d = (p + Vec3::new(o[0] as f64, o[1] as f64, o[2] as f64)) * dx;
                sum += kernel.term(d.length_squared());
            }
        }
    }
    sum
}

/// The soft minimum of φ_L at the cell centres of `grid`, with the softness (metres) of the
/// surface model.
pub(super) struct SoftSdf<'a> {
    bins: &'a Bins,
    /// The bins of the bodies' ghosts (see `ghosts.rs`), counted as particles (None without
    /// ghosts: no bins to build or read a cell).
    ghost_bins: Option<Bins>,
    grid: &'a Grid,
    block: Vec<[i64; 3]>,
    kernel: Kernel,
    radius: f64,
    deep: Option<&'a [bool]>,
    /// Per entry of `block`, what a deep cell there adds to a centre's sum: its m³
    /// sub-lattice particles' terms (the same for every centre).
    deep_terms: Vec<f64>,
    /// The block as rows along x (see [`Row`]), for a centre whose block is inside the tank.
    rows: Vec<Row>,
    /// The largest L∞ offset of the block: a centre at least this far from every wall
    /// sees no mirror image.
    span: usize,
    /// The particles' positions in bin order (a row of cells' particles lie together), and
    /// the ghosts'.
    sorted: Points,
    sorted_ghosts: Points,
}

/// A run of the block's cells along x, at linear offsets `first..=last` from the centre's
/// cell, whose deep terms start at `deep` in `SoftSdf::deep_terms`.
#[derive(Clone, Copy, Debug)]
struct Row {
    first: isize,
    last: isize,
    deep: usize,
}

/// The most cells a block holds: 5³, its offsets being at most 2 along each axis (see
/// [`block`]).
const BLOCK_CELLS: usize = 125;

/// Runs of consecutive cells, `first..=last` each, that a centre's sum reads (at most one a
/// block cell), and their particles' runs in bin order.
struct Runs {
    cells: [(u32, u32); BLOCK_CELLS],
    len: usize,
    points: [(u32, u32); BLOCK_CELLS],
}

impl Default for Runs {
    fn default() -> Runs {
        Runs { cells: [(0, 0); BLOCK_CELLS], len: 0, points: [(0, 0); BLOCK_CELLS] }
    }
}

impl Runs {
    /// Adds cells `first..=last`, joined to the last run where it ends at `first`.
    #[inline]
    fn push(&mut self, first: usize, last: usize) {
        match self.cells[..self.len].last_mut() {
            Some(run) if run.1 as usize + 1 == first => run.1 = last as u32,
            _ => {
                self.cells[self.len] = (first as u32, last as u32);
                self.len += 1;
            }
        }
    }

    /// The runs' particles in bin order, for bins starting at `start`.
    #[inline]
    fn of(&mut self, start: &[u32]) -> &[(u32, u32)] {
        for (p, &(a, b)) in self.points.iter_mut().zip(&self.cells[..self.len]) {
            *p = (start[a as usize], start[b as usize + 1]);
        }
        &self.points[..self.len]
    }
}

/// The rows of `block` (listed x fastest, as [`block`] makes it) on a grid of `n` cells.
fn rows(block: &[[i64; 3]], n: [usize; 3]) -> Vec<Row> {
    let lin = |o: &[i64; 3]| (o[0] + n[0] as i64 * (o[1] + n[1] as i64 * o[2])) as isize;
    let mut out: Vec<Row> = Vec::new();
    for (e, o) in block.iter().enumerate() {
        match out.last_mut() {
            Some(r) if e > 0 && block[e - 1][1..] == o[1..] && block[e - 1][0] + 1 == o[0] => {
                r.last = lin(o);
            }
            _ => out.push(Row { first: lin(o), last: lin(o), deep: e }),
        }
    }
    out
}

impl<'a> SoftSdf<'a> {
    pub(super) fn new(
        pos: &'a [Vec3],
        bins: &'a Bins,
        ghosts: &'a [Vec3],
        grid: &'a Grid,
        model: &SurfaceModel,
        deep: Option<&'a [bool]>,
    ) -> SoftSdf<'a> {
        let dx = grid.dx;
        let kernel = Kernel::new(SOFT_REACH * dx, model.softness);
        let block = block(SOFT_REACH);
        let off = sub_offsets(model.per_axis);
        let deep_terms = block.iter().map(|o| lattice_terms(&kernel, &off, *o, dx)).collect();
        let ghost_bins = (!ghosts.is_empty()).then(|| Bins::new(ghosts, grid));
        let rows = rows(&block, grid.n);
        let span = block.iter().flatten().map(|o| o.unsigned_abs() as usize).max().unwrap_or(0);
        let sorted = Points::gather(&bins.items, pos);
        let sorted_ghosts =
            ghost_bins.as_ref().map_or_else(Points::default, |b| Points::gather(&b.items, ghosts));
        SoftSdf {
            bins,
            ghost_bins,
            grid,
            block,
            kernel,
            radius: model.radius,
            deep,
            deep_terms,
            rows,
            span,
            sorted,
            sorted_ghosts,
        }
    }

    /// Whether cell `c` holds a ghost.
    pub(super) fn has_ghost(&self, c: usize) -> bool {
        self.ghost_bins.as_ref().is_some_and(|b| !b.cell(c).is_empty())
    }

    /// φ beyond every particle's reach (the nearest particle's distance's cap).
    pub(super) fn far(&self) -> f64 {
        SOFT_REACH * self.grid.dx - self.radius
    }

    /// The sum of the terms at the centre of cell `ijk`: the far value's, each particle's
    /// binned in its block, and m³ on the seeding sub-lattice in each deep cell there (a
    /// narrow band's deep cells are full by construction and carry no particles). The block's
    /// cells beyond a wall are the mirror images of those inside (see [`mirror`]). And whether
    /// a particle is within reach. A centre whose block lies inside the tank (most) reads
    /// the block a row of cells at a time ([`SoftSdf::inner_sum`]).
    fn sum(&self, ijk: [usize; 3]) -> (f64, bool) {
        if self.is_inner(ijk) {
            self.inner_sum(ijk)
        } else {
            self.walled_sum(ijk)
        }
    }

    /// Whether the block of the centre of cell `ijk` lies inside the tank.
    pub(super) fn is_inner(&self, ijk: [usize; 3]) -> bool {
        (0..3).all(|d| ijk[d] >= self.span && ijk[d] + self.span < self.grid.n[d])
    }

    /// [`SoftSdf::sum`] a block cell at a time, the cells beyond a wall read as mirror
    /// images.
    pub(super) fn walled_sum(&self, ijk: [usize; 3]) -> (f64, bool) {
        let grid = self.grid;
        let x = grid.cells().position(ijk[0], ijk[1], ijk[2]);
        let size = grid.size();
        let mut sum = 0.0;
        for (o, deep_term) in self.block.iter().zip(&self.deep_terms) {
            let at = [0, 1, 2].map(|d| ijk[d] as i64 + o[d]);
            let Some((c, flip)) = mirror(grid, at) else { continue };
            if self.deep.is_some_and(|d| d[c]) {
                // The sub-lattice is its own mirror image.
                sum += deep_term;
            } else {
                // A mirrored particle is as far from x as the particle is from x mirrored.
                let seen_from = reflect(x, flip, size);
                let terms = &self.kernel.terms;
                let start = &self.bins.start;
                let range = start[c] as usize..start[c + 1] as usize;
                sum += terms.sum(&self.sorted, range, seen_from);
                if let Some(ghosts) = &self.ghost_bins {
                    let range = ghosts.start[c] as usize..ghosts.start[c + 1] as usize;
                    sum += terms.sum(&self.sorted_ghosts, range, seen_from);
                }
            }
        }
        (sum + self.kernel.far, sum > 0.0)
    }

    /// [`SoftSdf::sum`] for a centre whose block lies inside the tank: a row of the block's
    /// cells at a time, their particles (and ghosts) together in bin order.
    pub(super) fn inner_sum(&self, ijk: [usize; 3]) -> (f64, bool) {
        let grid = self.grid;
        let x = grid.cells().position(ijk[0], ijk[1], ijk[2]);
        let own = grid.cell(ijk[0], ijk[1], ijk[2]) as isize;
        // The runs of sorted particles (and ghosts) the block's cells hold: a row's at once,
        // or its cells that are not deep, a run of them at a time.
        let mut runs = Runs::default();
        let mut deep_sum = 0.0;
        for row in &self.rows {
            let (first, last) = ((own + row.first) as usize, (own + row.last) as usize);
            match self.deep {
                Some(deep) if deep[first..=last].iter().any(|&d| d) => {
                    for (e, c) in (first..=last).enumerate() {
                        if deep[c] {
                            deep_sum += self.deep_terms[row.deep + e];
                        } else {
                            runs.push(c, c);
                        }
                    }
                }
                _ => runs.push(first, last),
            }
        }
        let terms = &self.kernel.terms;
        let mut sum = terms.sum_runs(&self.sorted, runs.of(&self.bins.start), x);
        if let Some(ghosts) = &self.ghost_bins {
            sum += terms.sum_runs(&self.sorted_ghosts, runs.of(&ghosts.start), x);
        }
        let sum = sum + deep_sum;
        (sum + self.kernel.far, sum > 0.0)
    }

    /// The cells whose sum [`liquid_sdf`](super::liquid_sdf) need not make, given `near`, the
    /// cells whose value φ's extension into the solids reads: liquid cells at least a tenth of
    /// a cell deep whose face neighbours are all liquid, away from the solids. Every reader
    /// of φ_L in the step reads such a cell's sign only, or a value that no longer depends on
    /// it (see `liquid_sdf_with`). A cell's own particles prove it: every term of its sum is
    /// positive, so the sum of its own cell's terms bounds φ from above (the far value, the
    /// other cells, the ghosts only lower it). Empty where the deep value itself (what a
    /// skipped cell stores) would not be as deep.
    pub(super) fn interior(&self, near: &[bool], deep_phi: f64) -> Vec<bool> {
        let grid = self.grid;
        let dx = grid.dx;
        let depth = -crate::stages::density::DEPTH_RAMP * dx;
        if deep_phi >= depth {
            return Vec::new();
        }
        let cells = grid.cells();
        let start = &self.bins.start;
        // Per cell: 0 unproven, 1 proven liquid, 2 proven at least `depth` deep.
        let level: Vec<u8> = (0..cells.len())
            .into_par_iter()
            .with_min_len(crate::math::par::MIN_LEN)
            .map(|c| {
                if self.deep.is_some_and(|d| d[c]) {
                    return 2;
                }
                let range = start[c] as usize..start[c + 1] as usize;
                if range.is_empty() {
                    return 0;
                }
                let [i, j, k] = cells.ijk(c);
                let own = self.kernel.terms.sum(&self.sorted, range, cells.position(i, j, k));
                match self.kernel.phi(own, self.radius) {
                    b if b < depth => 2,
                    b if b < 0.0 => 1,
                    _ => 0,
                }
            })
            .collect();
        (0..cells.len())
            .into_par_iter()
            .with_min_len(crate::math::par::MIN_LEN)
            .map(|c| {
                if level[c] < 2 || near[c] || self.deep.is_some_and(|d| d[c]) {
                    return false;
                }
                let ijk = cells.ijk(c);
                (0..6).all(|f| cells.neighbour(c, ijk, f / 2, f % 2).is_none_or(|n| level[n] > 0))
            })
            .collect()
    }

    /// φ at cell `ijk`, and whether it moves with a particle.
    pub(super) fn phi(&self, ijk: [usize; 3]) -> (f64, u32) {
        let (sum, moves) = self.sum(ijk);
        (self.kernel.phi(sum, self.radius), if moves { SOFT } else { NONE })
    }

    /// Adjoint: adds ∂φ_c/∂x_p · φ̄_c over the cells `marks` tags [`SOFT`] into `pbar` (the
    /// particles) and `gbar` (the ghosts), their sums read from `phi` (φ as [`SoftSdf::phi`]
    /// made it there) or else summed again. ∂φ/∂x_p is particle p's share of the sum times
    /// the gradient of its distance less τ·ln c_p.
    pub(super) fn adjoint(
        &self,
        marks: &[u32],
        phi: Option<&[f64]>,
        phi_bar: &[f64],
        pbar: &mut [Vec3],
        gbar: &mut [Vec3],
    ) {
        let cells = self.grid.cells();
        let tau = self.kernel.tau;
        // Per cell φ̄ over its sum: a particle's share of φ̄ is its term times this. The sum
        // is e^{−(φ + r)/τ} (see [`Kernel::phi`]).
        let per_term: Vec<f64> = (0..marks.len())
            .into_par_iter()
            .map(|c| {
                let g = phi_bar[c];
                if marks[c] != SOFT || g == 0.0 {
                    return 0.0;
                }
                match phi {
                    Some(phi) => g * ((phi[c] + self.radius) / tau).exp(),
                    None => g / self.sum(cells.ijk(c)).0,
                }
            })
            .collect();
        if let Some(ghosts) = &self.ghost_bins {
            self.points_adjoint(&per_term, ghosts, &self.sorted_ghosts, gbar);
        }
        self.points_adjoint(&per_term, self.bins, &self.sorted, pbar);
    }

    /// Σ_c per_term_c · ∂(term of a point in cell c's sum)/∂x_p for every point p binned in
    /// `bins` (`sorted` in bin order), added into `bar`: a bin at a time, in parallel, each
    /// bin's points together four at a time, seen from every cell whose block holds their
    /// cell or its mirror image beyond a wall. A mirrored point is as far from a centre as
    /// the point is from the centre mirrored, and moves the other way along the mirrored
    /// axes, so the point's own coordinates are differentiated seen from the centre mirrored.
    fn points_adjoint(&self, per_term: &[f64], bins: &Bins, sorted: &Points, bar: &mut [Vec3]) {
        let grid = self.grid;
        let cells = grid.cells();
        let size = grid.size();
        let n = grid.n.map(|n| n as i64);
        let len = bins.items.len();
        let (mut bx, mut by, mut bz) = (vec![0.0; len], vec![0.0; len], vec![0.0; len]);
        // Each bin's share of the three arrays; a deep cell's sums count its sub-lattice, not
        // what it holds, so its points have no share.
        let mut shares = Vec::new();
        let (mut rx, mut ry, mut rz) = (&mut bx[..], &mut by[..], &mut bz[..]);
        for c in 0..cells.len() {
            let count = (bins.start[c + 1] - bins.start[c]) as usize;
            if count == 0 {
                continue;
            }
            let (x, tx) = std::mem::take(&mut rx).split_at_mut(count);
            let (y, ty) = std::mem::take(&mut ry).split_at_mut(count);
            let (z, tz) = std::mem::take(&mut rz).split_at_mut(count);
            (rx, ry, rz) = (tx, ty, tz);
            if !self.deep.is_some_and(|d| d[c]) {
                shares.push((c, [x, y, z]));
            }
        }
        let terms = &self.kernel.terms;
        shares.into_par_iter().with_min_len(64).for_each(|(b, [x, y, z])| {
            let range = bins.start[b] as usize..bins.start[b + 1] as usize;
            let own = cells.ijk(b).map(|i| i as i64);
            for_images(own, n, |at, flip| {
                for o in &self.block {
                    let c = [0, 1, 2].map(|d| at[d] - o[d]);
                    if !(0..3).all(|d| (0..n[d]).contains(&c[d])) {
                        continue;
                    }
                    let c = grid.cell(c[0] as usize, c[1] as usize, c[2] as usize);
                    let g = per_term[c];
                    if g == 0.0 {
                        continue;
                    }
                    let [i, j, k] = cells.ijk(c);
                    let seen_from = reflect(cells.position(i, j, k), flip, size);
                    terms.add_gradients(
                        sorted,
                        range.clone(),
                        seen_from,
                        g,
                        [&mut *x, &mut *y, &mut *z],
                    );
                }
            });
        });
        for (i, &p) in bins.items.iter().enumerate() {
            bar[p as usize] += Vec3::new(bx[i], by[i], bz[i]);
        }
    }
}
