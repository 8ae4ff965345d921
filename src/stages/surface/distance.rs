//! The liquid signed distance φ_L from the particles, and its adjoint.

use super::softmin::{soft_full_phi, SoftSdf, SOFT};
use super::*;
use crate::geometry::grid::Grid;
use crate::math::buffer::refill;
use crate::math::Vec3;
use rayon::prelude::*;

/// Per cell, the L∞ distance in cells to the nearest `from` cell, capped at `cap` (cells
/// beyond the tank do not count). Separable: one windowed
/// min–max pass per axis.
pub fn linf_distance(grid: &Grid, from: &[bool], cap: u8) -> Vec<u8> {
    let mut d: Vec<u8> = from.par_iter().map(|&o| if o { 0 } else { cap }).collect();
    for axis in 0..3 {
        d = depth_pass(grid, &d, axis, cap);
    }
    d
}

/// `out(x) = min over |s| ≤ cap of max(|s|, d(x + s·e_axis))`, as whole-row passes: for
/// each shift s, the row (or slab) s away raised to at least s and folded in by a minimum
/// (loops over u8 slices the compiler vectorises, instead of a branchy search per cell).
fn depth_pass(grid: &Grid, d: &[u8], axis: usize, cap: u8) -> Vec<u8> {
    let n = grid.n;
    let slab = n[0] * n[1];
    let fold = |o: &mut [u8], src: &[u8], s: u8| {
        o.iter_mut().zip(src).for_each(|(o, &v)| *o = (*o).min(v.max(s)));
    };
    let mut out = d.to_vec();
    out.par_chunks_mut(slab).enumerate().for_each(|(k, o)| match axis {
        0 => {
            for (j, row) in o.chunks_mut(n[0]).enumerate() {
                let src = &d[k * slab + j * n[0]..][..n[0]];
                for s in 1..=(cap as usize).min(n[0] - 1) {
                    fold(&mut row[s..], &src[..n[0] - s], s as u8);
                    fold(&mut row[..n[0] - s], &src[s..], s as u8);
                }
            }
        }
        1 => {
            for s in 1..=(cap as usize).min(n[1] - 1) {
                let src = &d[k * slab..][..slab];
                let shift = s * n[0];
                fold(&mut o[shift..], &src[..slab - shift], s as u8);
                fold(&mut o[..slab - shift], &src[shift..], s as u8);
            }
        }
        _ => {
            for s in 1..=cap as usize {
                if k >= s {
                    fold(o, &d[(k - s) * slab..][..slab], s as u8);
                }
                if k + s < n[2] {
                    fold(o, &d[(k + s) * slab..][..slab], s as u8);
                }
            }
        }
    });
    out
}

/// A narrow band's deep cells, for φ_L: which cells, and their φ.
#[derive(Clone, Copy, Debug)]
pub struct Deep<'a> {
    /// Per cell, whether it is deep.
    pub cells: &'a [bool],
    /// φ_L of a deep cell.
    pub phi: f64,
}

/// How φ_L is made from the particles.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceModel {
    /// The particle radius r of `min_p |x − x_p| − r` (see [`particle_radius`]).
    pub radius: f64,
    /// A cell that holds a particle is liquid even where the distance says air (see
    /// [`liquid_sdf_nearest`]).
    pub sparse_cells: bool,
    /// With `sparse_cells`: 0 for the rule as it was (a cell is liquid the moment it holds a
    /// particle, a jump of φ as a particle crosses a face), or the depth (cells, up to 0.5)
    /// a particle must be inside its cell to make it liquid, φ falling continuously with the
    /// particle's depth up to there (see `sparse_phi`).
    pub sparse_depth: f64,
    /// The softness τ (metres) of the soft minimum of the particles' distances φ is made of
    /// (see `softmin.rs`), or 0 for the nearest particle's distance.
    pub softness: f64,
    /// Particles per axis of the seeding sub-lattice (the soft minimum counts a narrow band's
    /// deep cells as that many particles each).
    pub per_axis: usize,
}

impl SurfaceModel {
    /// The nearest particle's distance for particles of radius `radius` seeded `m` per axis,
    /// without the sparse-cell rule.
    pub fn nearest(radius: f64, m: usize) -> SurfaceModel {
        SurfaceModel { radius, sparse_cells: false, sparse_depth: 0.0, softness: 0.0, per_axis: m }
    }

    /// The soft minimum of softness `tau` (cells) of the distances of particles seeded `m`
    /// per axis on cells of size `dx`, without the sparse-cell rule.
    pub fn soft(dx: f64, m: usize, tau: f64) -> SurfaceModel {
        let radius = soft_particle_radius(dx, m, tau);
        SurfaceModel { softness: tau * dx, ..SurfaceModel::nearest(radius, m) }
    }

    /// φ_L at the centre of a cell deep in freshly seeded liquid, on cells of size `dx`: what
    /// a narrow band's deep cells read.
    pub fn full_phi(&self, dx: f64) -> f64 {
        if self.softness > 0.0 {
            return soft_full_phi(dx, self);
        }
        let o = sub_offsets(self.per_axis);
        let near = o.iter().map(|a| (a - 0.5).abs()).fold(f64::MAX, f64::min);
        near * 3f64.sqrt() * dx - self.radius
    }
}

/// The φ (in cells, negative) the sparse-cell rule sets a cell that holds a particle to.
pub(super) const SPARSE_FLOOR: f64 = 1e-3;
/// Marks a cell's entry in the nearest-particle list as set by the sparse-cell rule.
pub(super) const SPARSE: u32 = 1 << 31;

/// The continuous sparse-cell rule's φ for a cell holding a particle `offset` from its
/// centre (see [`SurfaceModel::sparse_depth`], `depth` > 0 cells): it falls linearly with the
/// particle's depth δ in the cell (dx/2 less the L∞ norm of `offset`) from the most a
/// particle on the cell's boundary leaves φ at (√3/2·dx − r: it is that near the centre),
/// through 0 at δ = `depth`·dx, to −[`SPARSE_FLOOR`]·dx. So a particle entering or leaving
/// the cell through a face moves φ continuously, with Lipschitz constant
/// (√3/2·dx − r)/(depth·dx) (4.7 for two particles a cell across at depth 0.05).
#[inline]
pub(super) fn sparse_phi(offset: Vec3, dx: f64, radius: f64, depth: f64) -> f64 {
    let inside = 0.5 * dx - offset.abs().max_element();
    (sparse_top(dx, radius) * (1.0 - inside / (depth * dx))).max(-SPARSE_FLOOR * dx)
}

/// [`sparse_phi`] of a particle on its cell's boundary: the most its distance leaves φ at.
fn sparse_top(dx: f64, radius: f64) -> f64 {
    0.5 * 3f64.sqrt() * dx - radius
}

/// ∂/∂offset of [`sparse_phi`] (zero on its floor).
fn sparse_phi_gradient(offset: Vec3, dx: f64, radius: f64, depth: f64) -> Vec3 {
    if sparse_phi(offset, dx, radius, depth) <= -SPARSE_FLOOR * dx {
        return Vec3::ZERO;
    }
    // The axis of the L∞ norm (the first of equals, as `max_element` reads it).
    let axis = offset.abs().max_position();
    let mut g = Vec3::ZERO;
    g[axis] = sparse_top(dx, radius) / (depth * dx) * offset[axis].signum();
    g
}

/// The liquid signed distance at cell centres: `min_p |x − x_p| − r`, exact where the
/// nearest particle is within two cells, and `2·dx − r` or more beyond; or with
/// `model.softness`, a soft minimum of the particles' distances (see `softmin.rs`).
///
/// With `reads` (the soft minimum only), φ is what a step reads: its value wherever the step
/// reads one, the deep value of [`SurfaceModel::full_phi`] in the liquid's interior (see
/// [`Reads`]). Without, its value everywhere.
pub fn liquid_sdf(
    pos: &[Vec3],
    bins: &Bins,
    ghosts: &[Vec3],
    grid: &Grid,
    model: &SurfaceModel,
    deep: Option<Deep<'_>>,
    reads: Option<Reads<'_>>,
) -> Vec<f64> {
    liquid_sdf_with(Vec::new(), pos, bins, ghosts, grid, model, deep, reads, false).0
}

/// Where a step reads the value of φ_L and not only its sign, for [`liquid_sdf`] to make
/// the soft minimum's sum (about 270 terms a cell) only there.
///
/// Reading the step's consumers of φ_L: the pressure's ghost-fluid θ, the blend's share,
/// the closing of air pockets and the entrained liquid read a liquid cell's value only
/// beside air (and as that neighbour's φ rises through zero, θ → 1 whatever the liquid
/// cell's value); the band's update, the unknowns and the measures read signs; the density
/// projection's depth weights read a value only above −[`DEPTH_RAMP`] cells (below it
/// they are 1, and φ's highest value over a block is either above it, and then not the
/// interior cell's, or below it in both); and φ's extension into the solids reads the
/// cells it sets and their face neighbours, at any depth ([`Reads::near_solids`]). So a
/// liquid cell whose own particles prove it deeper than a tenth of a cell, whose face
/// neighbours are all proven liquid, and which is not near a solid may hold any value
/// below that depth: it holds the deep value, as a narrow band's deep cells do, and the
/// step's result is the same bits as with the sum made everywhere
/// (`the_interior_skip_leaves_the_step_unchanged`). A cell changes between the two only
/// where nothing reads its value, so the map stays as smooth as the sum everywhere.
///
/// [`DEPTH_RAMP`]: crate::stages::density::DEPTH_RAMP
#[derive(Clone, Copy, Debug)]
pub struct Reads<'a> {
    /// Per cell, whether φ's extension into the solids reads its value: the cells it sets
    /// (a centre in a solid or partly in a body) and their neighbours (see
    /// [`crate::stages::solid_phi::extension_reads`]).
    pub near_solids: &'a [bool],
}

/// [`liquid_sdf`] written into the memory of `phi` (whatever it holds).
#[allow(clippy::too_many_arguments)]
pub fn liquid_sdf_into(
    phi: &mut Vec<f64>,
    pos: &[Vec3],
    bins: &Bins,
    ghosts: &[Vec3],
    grid: &Grid,
    model: &SurfaceModel,
    deep: Option<Deep<'_>>,
    reads: Option<Reads<'_>>,
) {
    let memory = std::mem::take(phi);
    *phi = liquid_sdf_with(memory, pos, bins, ghosts, grid, model, deep, reads, false).0;
}

/// [`liquid_sdf`] and, per cell, the particle whose distance φ is (`NONE` where φ does not
/// move with a particle: capped far from the liquid, or on the sparse-cell rule's floor;
/// tagged with `SPARSE` where the continuous rule set it). With `model.sparse_cells`, a cell
/// that holds a particle is liquid even where the particles are
/// too sparse for the distance to say so (thin sheets, splashes): the projection then keeps
/// it divergence-free instead of leaving its particles to extrapolated air velocities, which
/// bunch them up and lose volume. As it was, the rule makes φ jump when a particle crosses
/// a cell face; with `model.sparse_depth` > 0, φ moves continuously (see `sparse_phi`).
/// The `deep` cells of a narrow band are liquid with its φ (see `band.rs`).
pub fn liquid_sdf_nearest(
    pos: &[Vec3],
    bins: &Bins,
    ghosts: &[Vec3],
    grid: &Grid,
    model: &SurfaceModel,
    deep: Option<Deep<'_>>,
    reads: Option<Reads<'_>>,
) -> (Vec<f64>, Vec<u32>) {
    liquid_sdf_with(Vec::new(), pos, bins, ghosts, grid, model, deep, reads, true)
}

/// [`liquid_sdf_nearest`] in the memory of `phi`, the nearest particles only when `nearest`
/// (empty otherwise: 4 bytes a cell that the forward pass never reads).
#[allow(clippy::too_many_arguments)]
fn liquid_sdf_with(
    mut phi: Vec<f64>,
    pos: &[Vec3],
    bins: &Bins,
    ghosts: &[Vec3],
    grid: &Grid,
    model: &SurfaceModel,
    deep: Option<Deep<'_>>,
    reads: Option<Reads<'_>>,
    nearest: bool,
) -> (Vec<f64>, Vec<u32>) {
    let radius = model.radius;
    use crate::geometry::grid::NONE;
    let cells = grid.cells();
    let dx = grid.dx;
    let slab = grid.n[0] * grid.n[1];
    let soft = (model.softness > 0.0)
        .then(|| SoftSdf::new(pos, bins, ghosts, grid, model, deep.map(|d| d.cells)));
    // How far (L∞, in cells) the nearest cell holding a particle is: nothing to search in
    // the air beyond two cells of the liquid (most of a tall tank's cells). The soft minimum
    // counts the deep cells' particles, and the bodies' ghosts, too.
    let counted = |c: usize| {
        soft.as_ref().is_some_and(|s| deep.is_some_and(|d| d.cells[c]) || s.has_ghost(c))
    };
    let occupied: Vec<bool> =
        (0..cells.len()).into_par_iter().map(|c| !bins.cell(c).is_empty() || counted(c)).collect();
    let reach = linf_distance(grid, &occupied, 3);
    let far = soft.as_ref().map_or(2.0 * dx - radius, SoftSdf::far);
    // The liquid's interior, where the step reads φ's sign only (see `Reads`).
    let deep_phi = model.full_phi(dx);
    let interior = match (&soft, reads) {
        (Some(soft), Some(reads)) => soft.interior(reads.near_solids, deep_phi),
        _ => Vec::new(),
    };
    // Filled in place, a slab a task (not built a slab at a time and copied together).
    if phi.len() != cells.len() {
        refill(&mut phi, cells.len(), 0.0);
    }
    let mut who = if nearest { vec![NONE; cells.len()] } else { Vec::new() };
    // φ of cell (i, j, k) and the particle it is the distance to.
    let cell_phi = |i: usize, j: usize, k: usize| -> (f64, u32) {
        if let Some(d) = deep.filter(|d| d.cells[grid.cell(i, j, k)]) {
            return (d.phi, NONE);
        }
        let own = grid.cell(i, j, k);
        if reach[own] > 2 {
            return (far, NONE);
        }
        if interior.get(own) == Some(&true) {
            return (deep_phi, NONE);
        }
        let x = cells.position(i, j, k);
        let (value, particle) = match &soft {
            Some(soft) => soft.phi([i, j, k]),
            None => nearest_particle(pos, bins, grid, radius, [i, j, k], reach[own]),
        };
        // The sparse-cell rule can only lower φ where it is above the rule's floor.
        let own_particles = bins.cell(own);
        if !model.sparse_cells || value <= -SPARSE_FLOOR * dx || own_particles.is_empty() {
            (value, particle)
        } else if model.sparse_depth == 0.0 {
            if value >= 0.0 {
                (-SPARSE_FLOOR * dx, NONE)
            } else {
                (value, particle)
            }
        } else {
            let mut sparse = (value, particle);
            for &p in own_particles {
                let s = sparse_phi(pos[p as usize] - x, dx, radius, model.sparse_depth);
                if s < sparse.0 {
                    sparse = (s, p | SPARSE);
                }
            }
            sparse
        }
    };
    let slab_phi = |k: usize, phi_k: &mut [f64], mut who_k: Option<&mut [u32]>| {
        for j in 0..grid.n[1] {
            for i in 0..grid.n[0] {
                let o = i + grid.n[0] * j;
                let (value, particle) = cell_phi(i, j, k);
                phi_k[o] = value;
                if let Some(w) = who_k.as_deref_mut() {
                    w[o] = particle;
                }
            }
        }
    };
    if nearest {
        phi.par_chunks_mut(slab)
            .zip(who.par_chunks_mut(slab))
            .enumerate()
            .for_each(|(k, (phi_k, who_k))| slab_phi(k, phi_k, Some(who_k)));
    } else {
        phi.par_chunks_mut(slab).enumerate().for_each(|(k, phi_k)| slab_phi(k, phi_k, None));
    }
    (phi, who)
}

/// The particle nearest the centre of cell `ijk` (whose `reach` is the L∞ distance in cells
/// to the nearest cell holding a particle, at most 2) and its distance less the radius: exact
/// up to 2·dx, `2·dx − radius` (and `NONE`) beyond.
fn nearest_particle(
    pos: &[Vec3],
    bins: &Bins,
    grid: &Grid,
    radius: f64,
    [i, j, k]: [usize; 3],
    r: u8,
) -> (f64, u32) {
    use crate::geometry::grid::NONE;
    let dx = grid.dx;
    let x = grid.cells().position(i, j, k);
    let own = grid.cell(i, j, k);
    // The squared distance under which the second ring cannot hold a particle as near: the
    // (1.5·dx)² of its nearest faces, less a relative 1e-9 for the rounding of a particle's
    // bin (its cell from x/dx) and of its computed distance.
    let ring2 = (1.5 * dx).powi(2) * (1.0 - 1e-9);
    // The nearest particle so far: its squared distance, its cell and its index. Of
    // particles as near, the one in the cell first in lattice order, and the first in
    // that cell's bin, as a scan of the whole block in lattice order would find.
    let mut best = (f64::MAX, usize::MAX, NONE);
    let scan = |c: usize, best: &mut (f64, usize, u32)| {
        for &p in bins.cell(c) {
            let d = (pos[p as usize] - x).length_squared();
            if d < best.0 || (d == best.0 && c < best.1) {
                *best = (d, c, p);
            }
        }
    };
    // A particle outside the cell is at least dx/2 from its centre, so one nearer inside
    // it is the nearest (deep in the liquid, most cells: 8 distances instead of 216). A
    // particle outside the 3³ block is at least 1.5·dx away (the nearest face of a cell
    // two away), so one found inside it nearer than that is the true nearest (and no
    // particle beyond ties with it); otherwise look one ring further (exact up to 2·dx).
    // Each ring is searched once, and none that `reach` says is empty.
    if r == 0 {
        scan(own, &mut best);
    }
    if best.0.sqrt() >= 0.5 * dx && r <= 1 {
        for_ring_cells(grid, [i, j, k], 1, |c| scan(c, &mut best));
    }
    if best.0 > ring2 {
        for_ring_cells(grid, [i, j, k], 2, |c| scan(c, &mut best));
    }
    let mut d = (best.0.sqrt(), best.2);
    if d.0 > 2.0 * dx {
        d = (2.0 * dx, NONE);
    }
    (d.0 - radius, d.1)
}

/// Adjoint of [`liquid_sdf_nearest`] (of surface model `model`, a narrow band's `deep`
/// cells) in the particles: ∂φ_c/∂x_p = (x_p − x_c)/|x_p − x_c| for the particle p whose
/// distance φ_c is, the soft minimum's derivative where it set φ_c (see `softmin.rs`), or the
/// derivative of `sparse_phi` where the sparse-cell rule set φ_c. Adds into `pbar`, and the
/// soft minimum's derivative in the bodies' `ghosts` (see `ghosts.rs`) into `gbar`. Given
/// `phi`, φ_L as [`liquid_sdf_nearest`] made it (at least at the cells the soft minimum set
/// whose φ̄ is not zero), the soft minimum's sums are read from it (sum = e^{−(φ + r)/τ}, to
/// rounding) instead of being summed again.
#[allow(clippy::too_many_arguments)]
pub fn liquid_sdf_adjoint(
    pos: &[Vec3],
    ghosts: &[Vec3],
    nearest: &[u32],
    phi: Option<&[f64]>,
    grid: &Grid,
    model: &SurfaceModel,
    deep: Option<&[bool]>,
    phi_bar: &[f64],
    pbar: &mut [Vec3],
    gbar: &mut [Vec3],
) {
    let cells = grid.cells();
    if model.softness > 0.0 {
        let bins = Bins::new(pos, grid);
        let sdf = SoftSdf::new(pos, &bins, ghosts, grid, model, deep);
        sdf.adjoint(nearest, phi, phi_bar, pbar, gbar);
    }
    for (c, (&p, &g)) in nearest.iter().zip(phi_bar).enumerate() {
        if g == 0.0 || p == crate::geometry::grid::NONE || p == SOFT {
            continue;
        }
        let [i, j, k] = cells.ijk(c);
        if p & SPARSE != 0 {
            let p = (p & !SPARSE) as usize;
            let offset = pos[p] - cells.position(i, j, k);
            pbar[p] += g * sparse_phi_gradient(offset, grid.dx, model.radius, model.sparse_depth);
            continue;
        }
        let d = pos[p as usize] - cells.position(i, j, k);
        let len = d.length();
        if len > 0.0 {
            pbar[p as usize] += g * d / len;
        }
    }
}
