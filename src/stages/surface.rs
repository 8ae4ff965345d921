//! The free surface: marker particles, their advection, and the liquid signed distance φ_L.
//!
//! Particles are seeded on a regular sub-lattice (m³ per cell), advected with RK2 in the
//! grid velocity, pushed out of static solids and kept inside the tank. φ_L at a cell centre
//! is `min_p |x − x_p| − r`: negative in liquid. It is a distance only within a cell or two
//! of the surface (deep inside it is just negative), which is all the ghost-fluid boundary
//! reads. The radius `r` is chosen so that a flat, freshly seeded surface on a cell face is
//! reconstructed exactly halfway between the cell centres that straddle it
//! (see [`particle_radius`]).

use crate::geometry::grid::{Grid, Mac};
use crate::geometry::shape::Solid;
use crate::math::Vec3;
use rayon::prelude::*;

/// Sub-lattice offsets (in cells, relative to the cell's lower corner) for m per axis.
fn sub_offsets(m: usize) -> Vec<f64> {
    (0..m).map(|a| (a as f64 + 0.5) / m as f64).collect()
}

/// Particles per axis for a particle-per-cell count (1, 8, 27, 64).
pub fn per_axis(ppc: usize) -> usize {
    (ppc as f64).cbrt().round() as usize
}

/// The particle radius for `m` particles per axis: the mean of the nearest-particle
/// distances from the two cell centres on either side of a flat seeded surface lying on a
/// cell face. With it, linear interpolation of φ_L between those centres puts the surface
/// exactly on the face (θ = 1/2), so still water is reconstructed flat at its true height.
/// For m = 2 this is (√11 + √3)/8·dx ≈ 0.631·dx.
pub fn particle_radius(dx: f64, m: usize) -> f64 {
    let off = sub_offsets(m);
    // Liquid fills z < 0 with cells [.., −1]; centres above (z = +½) and below (z = −½).
    let nearest = |cz: f64| {
        let mut best = f64::MAX;
        for &ox in &off {
            for &oy in &off {
                for &oz in &off {
                    let p = Vec3::new(ox - 0.5, oy - 0.5, oz - 1.0);
                    best = best.min((p - Vec3::new(0.0, 0.0, cz)).length());
                }
            }
        }
        best
    };
    0.5 * (nearest(0.5) + nearest(-0.5)) * dx
}

/// Seeds m³ particles per cell on a regular sub-lattice, inside any of `regions` and outside
/// the static solids (`node_sdf`).
pub fn seed(grid: &Grid, regions: &[Solid], ppc: usize, node_sdf: &[f64]) -> Vec<Vec3> {
    let off = sub_offsets(per_axis(ppc));
    let nodes = grid.nodes();
    let dx = grid.dx;
    let bounds: Vec<(Vec3, Vec3)> = regions.iter().map(|r| r.bounds()).collect();
    let slabs: Vec<Vec<Vec3>> = (0..grid.n[2])
        .into_par_iter()
        .map(|k| {
            let mut out = Vec::new();
            for j in 0..grid.n[1] {
                for i in 0..grid.n[0] {
                    for &oz in &off {
                        for &oy in &off {
                            for &ox in &off {
                                let x = Vec3::new(
                                    (i as f64 + ox) * dx,
                                    (j as f64 + oy) * dx,
                                    (k as f64 + oz) * dx,
                                );
                                let in_liquid = regions.iter().zip(&bounds).any(|(r, (lo, hi))| {
                                    x.cmpge(*lo).all() && x.cmple(*hi).all() && r.sdf(x) < 0.0
                                });
                                if in_liquid && nodes.sample(node_sdf, x) > 0.0 {
                                    out.push(x);
                                }
                            }
                        }
                    }
                }
            }
            out
        })
        .collect();
    slabs.concat()
}

/// Advects particles through `u` for `dt` with the midpoint rule (RK2), then pushes any
/// that ended inside a static solid back to its surface and keeps all inside the tank.
pub fn advect(pos: &mut [Vec3], u: &Mac, grid: &Grid, dt: f64, node_sdf: &[f64]) {
    let nodes = grid.nodes();
    let size = grid.size();
    let margin = 1e-3 * grid.dx;
    // Sub-steps so no particle moves more than half a cell per sub-step: the surface is not
    // differentiated (it is held fixed in the backward pass), so this costs no gradient.
    let umax = u.max_abs();
    let subs = ((umax * dt / (0.5 * grid.dx)).ceil() as usize).clamp(1, 64);
    let h = dt / subs as f64;
    pos.par_iter_mut().for_each(|x| {
        for _ in 0..subs {
            let mid = *x + 0.5 * h * u.velocity(grid, *x);
            let mut y = *x + h * u.velocity(grid, mid);
            let (d, g) = nodes.sample_grad(node_sdf, y);
            if d < margin && g.length() > 1e-12 {
                y += (margin - d) * g.normalize();
            }
            *x = y.clamp(Vec3::splat(margin), size - Vec3::splat(margin));
        }
    });
}

/// Moves particles that ended inside a rigid body to its surface, `margin` outside.
pub fn push_out_of_bodies(
    pos: &mut [Vec3],
    bodies: &[crate::geometry::body::RigidBody],
    margin: f64,
) {
    for b in bodies {
        let (lo, hi) = b.bounds();
        let pose = b.pose();
        pos.par_iter_mut().for_each(|x| {
            if x.cmplt(lo).any() || x.cmpgt(hi).any() {
                return;
            }
            let proj = b.shape.project_point(&pose, *x, false);
            if proj.is_inside {
                let n = proj.point - *x;
                let len = n.length();
                *x = if len > 0.0 { proj.point + n * (margin / len) } else { proj.point };
            } else if (proj.point - *x).length() < margin {
                let n = *x - proj.point;
                *x = proj.point + n.normalize_or_zero() * margin;
            }
        });
    }
}

/// Particles sorted by cell (a counting sort, so the order is deterministic).
#[derive(Clone, Debug, Default)]
pub struct Bins {
    /// `start[c]..start[c + 1]` indexes `items` for cell c.
    pub start: Vec<u32>,
    /// Particle indices.
    pub items: Vec<u32>,
}

impl Bins {
    /// Bins `pos` into the cells of `grid`.
    pub fn new(pos: &[Vec3], grid: &Grid) -> Bins {
        let cells = grid.num_cells();
        let cell_of: Vec<u32> = pos.iter().map(|x| cell_of(grid, *x) as u32).collect();
        let mut start = vec![0u32; cells + 1];
        for &c in &cell_of {
            start[c as usize + 1] += 1;
        }
        for c in 0..cells {
            start[c + 1] += start[c];
        }
        let mut fill = start.clone();
        let mut items = vec![0u32; pos.len()];
        for (p, &c) in cell_of.iter().enumerate() {
            items[fill[c as usize] as usize] = p as u32;
            fill[c as usize] += 1;
        }
        Bins { start, items }
    }

    /// Particles in cell `c`.
    #[inline]
    pub fn cell(&self, c: usize) -> &[u32] {
        &self.items[self.start[c] as usize..self.start[c + 1] as usize]
    }
}

/// The cell containing `x` (clamped into the grid).
#[inline]
pub fn cell_of(grid: &Grid, x: Vec3) -> usize {
    let a = x.to_array();
    let ijk = [0, 1, 2].map(|d| ((a[d] / grid.dx).floor().max(0.0) as usize).min(grid.n[d] - 1));
    grid.cell(ijk[0], ijk[1], ijk[2])
}

/// Calls `f` for every cell within `reach` cells of (i, j, k) (a cube of side 2·reach + 1).
#[inline]
fn for_neighbour_cells(grid: &Grid, ijk: [usize; 3], reach: usize, mut f: impl FnMut(usize)) {
    let lo = ijk.map(|x| x.saturating_sub(reach));
    let hi = [0, 1, 2].map(|d| (ijk[d] + reach).min(grid.n[d] - 1));
    for k in lo[2]..=hi[2] {
        for j in lo[1]..=hi[1] {
            for i in lo[0]..=hi[0] {
                f(grid.cell(i, j, k));
            }
        }
    }
}

/// The liquid signed distance at cell centres: `min_p |x − x_p| − r`, exact where the
/// nearest particle is within two cells, and `2·dx − r` or more beyond.
pub fn liquid_sdf(pos: &[Vec3], bins: &Bins, grid: &Grid, radius: f64) -> Vec<f64> {
    let cells = grid.cells();
    let mut phi = vec![0.0; cells.len()];
    let dx = grid.dx;
    cells.fill_par(&mut phi, |i, j, k| {
        let x = cells.position(i, j, k);
        let nearest = |reach: usize| {
            let mut best = f64::MAX;
            for_neighbour_cells(grid, [i, j, k], reach, |c| {
                for &p in bins.cell(c) {
                    best = best.min((pos[p as usize] - x).length_squared());
                }
            });
            best.sqrt()
        };
        // A particle outside the 3³ block is at least dx away, so a nearer one found inside
        // it is the true nearest; otherwise look one ring further (exact up to 2·dx).
        let mut d = nearest(1);
        if d > dx {
            d = nearest(2).min(2.0 * dx);
        }
        let phi = d - radius;
        // A cell that holds a particle is liquid even where the particles are too sparse
        // for the distance to say so (thin sheets, splashes): the projection then keeps it
        // divergence-free instead of leaving its particles to extrapolated air velocities,
        // which bunch them up and lose volume.
        if phi >= 0.0 && !bins.cell(grid.cell(i, j, k)).is_empty() {
            -1e-3 * dx
        } else {
            phi
        }
    });
    phi
}

/// Marks cells whose centre is inside a static solid as liquid when a face neighbour is
/// liquid, so a partly solid cell next to liquid is not mistaken for air (which would put a
/// spurious p = 0 against the wall and let liquid leak along it).
pub fn extend_into_solids(phi: &mut [f64], grid: &Grid, centre_in_solid: &[bool]) {
    let src = phi.to_vec();
    let cells = grid.cells();
    for c in 0..phi.len() {
        if !centre_in_solid[c] || src[c] < 0.0 {
            continue;
        }
        let [i, j, k] = cells.ijk(c);
        let mut wet = false;
        for a in 0..3 {
            let p = [i, j, k];
            if p[a] > 0 {
                let mut q = p;
                q[a] -= 1;
                wet |= src[grid.cell(q[0], q[1], q[2])] < 0.0;
            }
            if p[a] + 1 < grid.n[a] {
                let mut q = p;
                q[a] += 1;
                wet |= src[grid.cell(q[0], q[1], q[2])] < 0.0;
            }
        }
        if wet {
            phi[c] = -0.5 * grid.dx;
        }
    }
}

/// Marker particle number density at cell centres, in full cells (1 = as dense as freshly
/// seeded): each particle is deposited on its 8 nearest cell centres with trilinear weights,
/// and a weight that would fall on a cell beyond a tank wall lands on its mirror image inside
/// (reflection), so every particle deposits exactly one unit. The scatter runs in particle
/// order on one thread, so the sums do not depend on the thread count.
pub fn particle_density(pos: &[Vec3], grid: &Grid, ppc: usize) -> Vec<f64> {
    let cells = grid.cells();
    let mut out = vec![0.0; cells.len()];
    let unit = 1.0 / ppc as f64;
    for x in pos {
        let a = x.to_array();
        let mut idx = [[0usize; 2]; 3];
        let mut w = [[0.0f64; 2]; 3];
        for d in 0..3 {
            let g = a[d] / grid.dx - 0.5;
            let i0 = g.floor();
            let t = g - i0;
            let n = grid.n[d] as i64;
            let fold = |i: i64| -> usize {
                if i < 0 {
                    (-i - 1).min(n - 1) as usize
                } else if i >= n {
                    (2 * n - 1 - i).max(0) as usize
                } else {
                    i as usize
                }
            };
            idx[d] = [fold(i0 as i64), fold(i0 as i64 + 1)];
            w[d] = [1.0 - t, t];
        }
        for c in 0..8 {
            let (bi, bj, bk) = (c & 1, (c >> 1) & 1, (c >> 2) & 1);
            let cell = grid.cell(idx[0][bi], idx[1][bj], idx[2][bk]);
            out[cell] += w[0][bi] * w[1][bj] * w[2][bk] * unit;
        }
    }
    out
}

/// Liquid volume in m³: the particle density capped at one full cell per cell, times the
/// cell volume. A freshly seeded region gives its exact volume; marker particles that bunch
/// up (the way a marker-particle liquid loses volume) push cells over full and lower it.
pub fn liquid_volume(pos: &[Vec3], grid: &Grid, ppc: usize) -> f64 {
    let dens = particle_density(pos, grid, ppc);
    let parts: Vec<f64> = dens
        .chunks(crate::geometry::grid::REDUCE_CHUNK)
        .map(|c| c.iter().map(|d| d.min(1.0)).sum())
        .collect();
    parts.iter().sum::<f64>() * grid.dx.powi(3)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radius_for_eight_per_cell() {
        let r = particle_radius(1.0, 2);
        assert!((r - (11f64.sqrt() + 3f64.sqrt()) / 8.0).abs() < 1e-14);
    }

    #[test]
    fn seeded_box_has_exact_volume_and_flat_surface() {
        use crate::geometry::shape::Solid;
        let grid = Grid { n: [8, 8, 8], dx: 0.125 };
        let region = Solid::aabb(Vec3::ZERO, Vec3::new(1.0, 0.5, 1.0));
        let sdf = vec![1e3; grid.nodes().len()];
        let pos = seed(&grid, &[region], 8, &sdf);
        assert_eq!(pos.len(), 8 * 8 * 4 * 8);
        let bins = Bins::new(&pos, &grid);
        let vol = liquid_volume(&pos, &grid, 8);
        assert!((vol - 0.5).abs() < 1e-12, "volume {vol}");
        let phi = liquid_sdf(&pos, &bins, &grid, particle_radius(grid.dx, 2));
        // Centres at y = 7/16 (below) and 9/16 (above) straddle the surface y = 0.5 evenly.
        let below = phi[grid.cell(3, 3, 3)];
        let above = phi[grid.cell(3, 4, 3)];
        assert!(below < 0.0 && above > 0.0);
        assert!((below / (below - above) - 0.5).abs() < 1e-12);
    }
}
