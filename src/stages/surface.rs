//! The free surface: marker particles, their advection, and the liquid signed distance φ_L,
//! each with its adjoint (the live-surface gradient of `gradients::backward`).
//!
//! Particles are seeded on a regular sub-lattice (m³ per cell), advected with RK2 in the
//! grid velocity, pushed out of static solids and kept inside the tank. φ_L at a cell centre
//! is `min_p |x − x_p| − r`: negative in liquid. It is a distance only within a cell or two
//! of the surface (deep inside it is just negative), which is all the ghost-fluid boundary
//! reads. The radius `r` is chosen so that a flat, freshly seeded surface on a cell face is
//! reconstructed exactly halfway between the cell centres that straddle it
//! (see [`particle_radius`]).

use crate::geometry::body::RigidBody;
use crate::geometry::fractions::NodeSdf;
use crate::geometry::grid::{floor_index, Grid, Mac};
use crate::geometry::shape::Solid;
use crate::math::buffer::refill;
use crate::math::par::min_pieces;
use crate::math::{comp, Pose, SharedShape, Vec3};
use rayon::prelude::*;

/// Sub-lattice offsets (in cells, relative to the cell's lower corner) for m per axis.
pub fn sub_offsets(m: usize) -> Vec<f64> {
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
/// the static solids (`node_sdf`), in every cell but those `skip` marks (a narrow band's deep
/// cells).
pub fn seed(
    grid: &Grid,
    regions: &[Solid],
    ppc: usize,
    node_sdf: &NodeSdf,
    skip: Option<&[bool]>,
) -> Vec<Vec3> {
    let off = sub_offsets(per_axis(ppc));
    let liquid = Regions::new(regions);
    let slabs: Vec<Vec<Vec3>> = (0..grid.n[2])
        .into_par_iter()
        .map(|k| {
            let mut out = Vec::new();
            for j in 0..grid.n[1] {
                for i in 0..grid.n[0] {
                    if skip.is_some_and(|s| s[grid.cell(i, j, k)]) {
                        continue;
                    }
                    out.extend(
                        sites(grid, [i, j, k], &off)
                            .filter(|x| liquid.contain(*x) && node_sdf.sample(grid, *x) > 0.0),
                    );
                }
            }
            out
        })
        .collect();
    slabs.concat()
}

/// The sub-lattice sites of cell `ijk` at offsets `off` (see [`sub_offsets`]), x fastest.
pub fn sites<'a>(grid: &Grid, ijk: [usize; 3], off: &'a [f64]) -> impl Iterator<Item = Vec3> + 'a {
    let dx = grid.dx;
    let at = move |a: usize, o: f64| (ijk[a] as f64 + o) * dx;
    off.iter().flat_map(move |&oz| {
        off.iter().flat_map(move |&oy| {
            off.iter().map(move |&ox| Vec3::new(at(0, ox), at(1, oy), at(2, oz)))
        })
    })
}

/// Liquid regions with their bounds, to ask whether a point is in any of them.
pub struct Regions<'a> {
    regions: &'a [Solid],
    bounds: Vec<(Vec3, Vec3)>,
}

impl<'a> Regions<'a> {
    /// `regions` and their bounds.
    pub fn new(regions: &'a [Solid]) -> Regions<'a> {
        Regions { regions, bounds: regions.iter().map(Solid::bounds).collect() }
    }

    /// Whether `x` is inside any region (its bounds first, then its signed distance).
    pub fn contain(&self, x: Vec3) -> bool {
        self.regions
            .iter()
            .zip(&self.bounds)
            .any(|(r, (lo, hi))| x.cmpge(*lo).all() && x.cmple(*hi).all() && r.sdf(x) < 0.0)
    }
}

/// Sub-steps of [`advect`] for the field `u`: so many that no particle moves more than half
/// a cell per sub-step (at most 64).
pub fn advect_substeps(u: &Mac, grid: &Grid, dt: f64) -> usize {
    ((u.max_abs() * dt / (0.5 * grid.dx)).ceil() as usize).clamp(1, 64)
}

/// What keeps a particle out of the static solids and inside the tank: the node signed
/// distance, the margin kept from surfaces, the tank size.
#[derive(Clone, Copy)]
pub struct Walls<'a> {
    /// The grid.
    pub grid: &'a Grid,
    /// Signed distance of the static solids at grid nodes, when there is any (without one,
    /// keeping is clamping into the tank).
    solids: Option<&'a [f64]>,
}

impl<'a> Walls<'a> {
    /// The walls of `grid` with the static solids of distance `node_sdf`.
    pub fn new(grid: &'a Grid, node_sdf: &'a NodeSdf) -> Walls<'a> {
        Walls { grid, solids: node_sdf.values() }
    }

    /// A point a thousandth of a cell out of the static solids and inside the tank.
    #[inline]
    pub fn keep(&self, y: Vec3) -> Vec3 {
        let margin = 1e-3 * self.grid.dx;
        let nodes = self.grid.nodes();
        let mut y = y;
        // The distance alone first: far from the solids (most particles) that is all.
        if let Some(sdf) = self.solids.filter(|sdf| nodes.sample(sdf, y) < margin) {
            let (d, g) = nodes.sample_grad(sdf, y);
            if g.length() > 1e-12 {
                y += (margin - d) * g.normalize();
            }
        }
        y.clamp(Vec3::splat(margin), self.grid.size() - Vec3::splat(margin))
    }
}

/// One particle's path: `subs` midpoint (RK2) sub-steps of length `h` through `u`, each
/// ending with [`Walls::keep`].
#[inline]
fn advect_one(x: Vec3, u: &Mac, walls: &Walls<'_>, h: f64, subs: usize) -> Vec3 {
    let grid = walls.grid;
    let mut x = x;
    for _ in 0..subs {
        let mid = x + 0.5 * h * u.velocity(grid, x);
        x = walls.keep(x + h * u.velocity(grid, mid));
    }
    x
}

/// Advects particles through `u` for `dt` with the midpoint rule (RK2), in
/// [`advect_substeps`] sub-steps, each pushing particles that ended inside a static solid
/// back to its surface and keeping all inside the tank. Returns the sub-steps taken.
pub fn advect(pos: &mut [Vec3], u: &Mac, grid: &Grid, dt: f64, node_sdf: &NodeSdf) -> usize {
    let subs = advect_substeps(u, grid, dt);
    advect_substepped(pos, u, grid, dt, subs, node_sdf);
    subs
}

/// [`advect`] in a given number of sub-steps.
pub fn advect_substepped(
    pos: &mut [Vec3],
    u: &Mac,
    grid: &Grid,
    dt: f64,
    subs: usize,
    node_sdf: &NodeSdf,
) {
    let walls = Walls::new(grid, node_sdf);
    let h = dt / subs as f64;
    pos.par_iter_mut().for_each(|x| *x = advect_one(*x, u, &walls, h, subs));
}

/// `Jᵀ·v̄` of `f` at `x` by central differences with step `h`: for the few maps of a particle
/// stage whose exact Jacobian needs the second derivatives of a distance field (pushing a
/// point out of a solid, clamping it into the tank). Their error is O(h²) of the surface's
/// curvature and O(ε/h) of round-off.
#[inline]
pub fn jacobian_t(f: impl Fn(Vec3) -> Vec3, x: Vec3, h: f64, vbar: Vec3) -> Vec3 {
    let d = [0, 1, 2].map(|k| {
        let e = h * crate::math::unit(k);
        vbar.dot(f(x + e) - f(x - e)) / (2.0 * h)
    });
    Vec3::from_array(d)
}

/// The step of [`jacobian_t`] on `grid`: a millionth of a cell.
pub fn jacobian_step(grid: &Grid) -> f64 {
    1e-6 * grid.dx
}

/// Adjoint of [`advect`] from the start positions `pos0` (the same `u`, `dt` and sub-steps):
/// given ∂L/∂(advected positions) in `pbar`, leaves ∂L/∂(start positions) there and adds
/// ∂L/∂u into `ubar`. Each particle's path is replayed and walked back: the midpoint rule's
/// transpose (the velocity's Jacobian and its transpose-scatter into the field), and the
/// wall push's Jacobian where it acted. The particles run in parallel; the scatter into the
/// field runs in particle order, so the sums do not depend on the thread count.
#[allow(clippy::too_many_arguments)]
pub fn advect_adjoint(
    pos0: &[Vec3],
    pbar: &mut [Vec3],
    u: &Mac,
    grid: &Grid,
    dt: f64,
    subs: usize,
    node_sdf: &NodeSdf,
    ubar: &mut Mac,
) {
    let walls = Walls::new(grid, node_sdf);
    let h = dt / subs as f64;
    let fd = jacobian_step(grid);
    // Per particle, in parallel: its start adjoint and the points and coefficients at which
    // its path read the field (2 a sub-step).
    let stride = 2 * subs;
    scatter_reads_in_chunks(pbar, stride, grid, ubar, |first, xbs, reads| {
        let xs = &pos0[first..first + xbs.len()];
        xs.par_iter()
            .zip(xbs.par_iter_mut())
            .zip(reads.par_chunks_mut(stride.max(1)))
            .with_min_len(1024)
            .for_each_init(
                || Vec::with_capacity(subs),
                |path, ((x0, xb), out)| {
                    if *xb == Vec3::ZERO {
                        out.fill((Vec3::ZERO, Vec3::ZERO));
                        return;
                    }
                    path.clear();
                    let mut x = *x0;
                    for _ in 0..subs {
                        let mid = x + 0.5 * h * u.velocity(grid, x);
                        let y = x + h * u.velocity(grid, mid);
                        let kept = walls.keep(y);
                        path.push((x, mid, y, kept == y));
                        x = kept;
                    }
                    let mut bar = *xb;
                    for (n, &(x, mid, y, free)) in path.iter().rev().enumerate() {
                        // x' = keep(y): the identity unless the push or the clamp acted.
                        let ybar =
                            if free { bar } else { jacobian_t(|p| walls.keep(p), y, fd, bar) };
                        // y = x + h·U(mid), mid = x + h/2·U(x).
                        let (_, jm) = u.velocity_jacobian(grid, mid);
                        let mbar = h * (ybar.x * jm[0] + ybar.y * jm[1] + ybar.z * jm[2]);
                        out[2 * n] = (mid, h * ybar);
                        let (_, jx) = u.velocity_jacobian(grid, x);
                        bar = ybar
                            + mbar
                            + 0.5 * h * (mbar.x * jx[0] + mbar.y * jx[1] + mbar.z * jx[2]);
                        out[2 * n + 1] = (x, 0.5 * h * mbar);
                    }
                    *xb = bar;
                },
            );
    });
}

/// The particles' reads of a velocity field in an adjoint pass, scattered into its adjoint
/// `field` a chunk of `PARTICLE_CHUNK` (65,536) particles at a time: `fill(first, pbar, reads)`
/// sets, in parallel, the `stride` reads (a point, and the coefficient of the velocity
/// there; zero for none) of the particles `first..first + pbar.len()`, whose adjoints
/// `pbar` it may update; then the chunk's reads are scattered in particle order (the same
/// sums on any thread count). One buffer of a chunk's reads, not one per particle.
pub fn scatter_reads_in_chunks(
    pbar: &mut [Vec3],
    stride: usize,
    grid: &Grid,
    field: &mut Mac,
    mut fill: impl FnMut(usize, &mut [Vec3], &mut [(Vec3, Vec3)]),
) {
    let chunk = PARTICLE_CHUNK.min(pbar.len().max(1));
    let mut reads = vec![(Vec3::ZERO, Vec3::ZERO); chunk * stride];
    for (c, xbs) in pbar.chunks_mut(chunk).enumerate() {
        let reads = &mut reads[..xbs.len() * stride];
        fill(c * chunk, xbs, reads);
        for &(x, coef) in reads.iter() {
            // A zero adds nothing (scatter_velocity skips zero components).
            if coef != Vec3::ZERO {
                field.scatter_velocity(grid, x, coef);
            }
        }
    }
}

/// Particles whose adjoint is taken at once before their scatter (a few MB of reads).
const PARTICLE_CHUNK: usize = 1 << 16;

/// One point pushed out of a body's shape at `pose` (bounds `lo`..`hi`): a point inside goes
/// to the closest surface point and `margin` beyond it, a point outside but nearer than
/// `margin` out to `margin`; any other point stays.
#[inline]
fn push_one(shape: &SharedShape, pose: &Pose, bounds: (Vec3, Vec3), x: Vec3, margin: f64) -> Vec3 {
    let (lo, hi) = bounds;
    if x.cmplt(lo).any() || x.cmpgt(hi).any() {
        return x;
    }
    let proj = shape.project_point(pose, x, false);
    if proj.is_inside {
        let n = proj.point - x;
        let len = n.length();
        if len > 0.0 {
            proj.point + n * (margin / len)
        } else {
            proj.point
        }
    } else if (proj.point - x).length() < margin {
        proj.point + (x - proj.point).normalize_or_zero() * margin
    } else {
        x
    }
}

/// A body's pose and bounds.
type PlacedShape = (Pose, (Vec3, Vec3));

/// Moves particles that ended inside a rigid body to its surface, `margin` outside (the
/// bodies in order).
pub fn push_out_of_bodies(pos: &mut [Vec3], bodies: &[RigidBody], margin: f64) {
    for b in bodies {
        let (bounds, pose) = (b.bounds(), b.pose());
        pos.par_iter_mut().for_each(|x| *x = push_one(&b.shape, &pose, bounds, *x, margin));
    }
}

/// Adjoint of [`push_out_of_bodies`] from the positions before it, `pos0`: given ∂L/∂(pushed
/// positions) in `pbar`, leaves ∂L/∂(positions before) there and returns each body's
/// ∂L/∂[δx; δθ] (translation, and rotation about its centre of mass in the world frame).
/// Only pushed particles carry a Jacobian; it is taken by central differences in the point
/// ([`jacobian_t`]) and in the six pose directions, so it holds for any shape.
pub fn push_out_of_bodies_adjoint(
    pos0: &[Vec3],
    pbar: &mut [Vec3],
    bodies: &[RigidBody],
    margin: f64,
    step: f64,
) -> Vec<[f64; 6]> {
    // Replay, keeping (body, particle, position before) of every push.
    let mut pos = pos0.to_vec();
    let mut pushes = Vec::new();
    for (bi, b) in bodies.iter().enumerate() {
        let (bounds, pose) = (b.bounds(), b.pose());
        let moved: Vec<(usize, Vec3, Vec3)> = pos
            .par_iter()
            .enumerate()
            .filter_map(|(i, x)| {
                let y = push_one(&b.shape, &pose, bounds, *x, margin);
                (y != *x).then_some((i, *x, y))
            })
            .collect();
        for (i, x, y) in moved {
            pushes.push((bi, i, x));
            pos[i] = y;
        }
    }
    let mut out = vec![[0.0; 6]; bodies.len()];
    // The poses ±step along each of the six directions, per body that pushed.
    let moved = |b: &RigidBody, k: usize, s: f64| -> PlacedShape {
        let mut c = b.clone();
        let e = s * crate::math::unit(k % 3);
        if k < 3 {
            c.x += e;
        } else {
            c.q = (crate::math::Rotation::from_scaled_axis(e) * c.q).normalize();
        }
        (c.pose(), c.bounds())
    };
    let mut poses: Vec<Option<Vec<[PlacedShape; 2]>>> = vec![None; bodies.len()];
    for &(bi, i, x) in pushes.iter().rev() {
        let b = &bodies[bi];
        let bar = pbar[i];
        if bar == Vec3::ZERO {
            continue;
        }
        let (bounds, pose) = (b.bounds(), b.pose());
        let dirs = poses[bi].get_or_insert_with(|| {
            (0..6).map(|k| [moved(b, k, step), moved(b, k, -step)]).collect()
        });
        for (k, [(pp, bp), (pm, bm)]) in dirs.iter().enumerate() {
            let d = push_one(&b.shape, pp, *bp, x, margin) - push_one(&b.shape, pm, *bm, x, margin);
            out[bi][k] += bar.dot(d) / (2.0 * step);
        }
        pbar[i] = jacobian_t(|p| push_one(&b.shape, &pose, bounds, p, margin), x, step, bar);
    }
    out
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
struct SlabBuckets {
    /// `start[b]..start[b + 1]` indexes `items` for bucket b.
    start: Vec<u32>,
    items: Vec<u32>,
}

impl SlabBuckets {
    /// Buckets `0..n` of the particles, particle p in bucket `bucket(keys[p])`. A counting
    /// sort of each fixed chunk of particles in parallel, then each bucket gathers its part
    /// of every chunk in chunk order: particle order within a bucket, on any thread count.
    fn new(keys: &[u32], bucket: impl Fn(u32) -> usize + Sync, n: usize) -> SlabBuckets {
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
    fn of(&self, b: usize) -> &[u32] {
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
    // Written out: as an array map this was left as a call (`try_map`) in some builds, 2.4%
    // of a step's instructions.
    let at = |a: f64, d: usize| floor_index(a / grid.dx).min(grid.n[d] - 1);
    grid.cell(at(x.x, 0), at(x.y, 1), at(x.z, 2))
}

/// Calls `f`, in lattice order, for every cell within `reach` cells of (i, j, k) that can
/// hold a point within `reach·dx` of its centre: the cube of side 2·reach + 1, less, from
/// reach 2 on, the cells `reach` away along two or three axes (their nearest point is
/// √2·(reach − ½)·dx > reach·dx away: 44 of the 125 cells at reach 2).
#[inline(always)]
fn for_neighbour_cells(grid: &Grid, ijk: [usize; 3], reach: usize, mut f: impl FnMut(usize)) {
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
}

/// The liquid signed distance at cell centres: `min_p |x − x_p| − r`, exact where the
/// nearest particle is within two cells, and `2·dx − r` or more beyond.
pub fn liquid_sdf(
    pos: &[Vec3],
    bins: &Bins,
    grid: &Grid,
    model: &SurfaceModel,
    deep: Option<Deep<'_>>,
) -> Vec<f64> {
    liquid_sdf_with(Vec::new(), pos, bins, grid, model, deep, false).0
}

/// [`liquid_sdf`] written into the memory of `phi` (whatever it holds).
pub fn liquid_sdf_into(
    phi: &mut Vec<f64>,
    pos: &[Vec3],
    bins: &Bins,
    grid: &Grid,
    model: &SurfaceModel,
    deep: Option<Deep<'_>>,
) {
    *phi = liquid_sdf_with(std::mem::take(phi), pos, bins, grid, model, deep, false).0;
}

/// [`liquid_sdf`] and, per cell, the particle whose distance φ is (`NONE` where φ does not
/// move with a particle: capped far from the liquid, or set by the sparse-cell rule). With
/// `model.sparse_cells`, a cell that holds a particle is liquid even where the particles are
/// too sparse for the distance to say so (thin sheets, splashes): the projection then keeps
/// it divergence-free instead of leaving its particles to extrapolated air velocities, which
/// bunch them up and lose volume. The rule makes φ jump when a particle crosses a cell face.
/// The `deep` cells of a narrow band are liquid with its φ (see `band.rs`).
pub fn liquid_sdf_nearest(
    pos: &[Vec3],
    bins: &Bins,
    grid: &Grid,
    model: &SurfaceModel,
    deep: Option<Deep<'_>>,
) -> (Vec<f64>, Vec<u32>) {
    liquid_sdf_with(Vec::new(), pos, bins, grid, model, deep, true)
}

/// [`liquid_sdf_nearest`] in the memory of `phi`, the nearest particles only when `nearest`
/// (empty otherwise: 4 bytes a cell that the forward pass never reads).
fn liquid_sdf_with(
    mut phi: Vec<f64>,
    pos: &[Vec3],
    bins: &Bins,
    grid: &Grid,
    model: &SurfaceModel,
    deep: Option<Deep<'_>>,
    nearest: bool,
) -> (Vec<f64>, Vec<u32>) {
    let radius = model.radius;
    use crate::geometry::grid::NONE;
    let cells = grid.cells();
    let dx = grid.dx;
    let slab = grid.n[0] * grid.n[1];
    // How far (L∞, in cells) the nearest cell holding a particle is: nothing to search in
    // the air beyond two cells of the liquid (most of a tall tank's cells).
    let occupied: Vec<bool> =
        (0..cells.len()).into_par_iter().map(|c| !bins.cell(c).is_empty()).collect();
    let reach = linf_distance(grid, &occupied, 3);
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
        if reach[grid.cell(i, j, k)] > 2 {
            return (2.0 * dx - radius, NONE);
        }
        let x = cells.position(i, j, k);
        let nearest = |reach: usize| {
            let mut best = (f64::MAX, NONE);
            for_neighbour_cells(grid, [i, j, k], reach, |c| {
                for &p in bins.cell(c) {
                    let d = (pos[p as usize] - x).length_squared();
                    if d < best.0 {
                        best = (d, p);
                    }
                }
            });
            (best.0.sqrt(), best.1)
        };
        // A particle outside the cell is at least dx/2 from its centre, so one nearer inside
        // it is the nearest (deep in the liquid, most cells: 8 distances instead of 216). A
        // particle outside the 3³ block is at least dx away, so a nearer one found inside it
        // is the true nearest; otherwise look one ring further (exact up to 2·dx).
        let mut d = nearest(0);
        if d.0 >= 0.5 * dx {
            d = nearest(1);
        }
        if d.0 > dx {
            d = nearest(2);
            if d.0 > 2.0 * dx {
                d = (2.0 * dx, NONE);
            }
        }
        let value = d.0 - radius;
        if model.sparse_cells && value >= 0.0 && !bins.cell(grid.cell(i, j, k)).is_empty() {
            (-1e-3 * dx, NONE)
        } else {
            (value, d.1)
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

/// Adjoint of [`liquid_sdf_nearest`] in the particles: ∂φ_c/∂x_p = (x_p − x_c)/|x_p − x_c|
/// for the particle p whose distance φ_c is. Adds into `pbar`.
pub fn liquid_sdf_adjoint(
    pos: &[Vec3],
    nearest: &[u32],
    grid: &Grid,
    phi_bar: &[f64],
    pbar: &mut [Vec3],
) {
    let cells = grid.cells();
    for (c, (&p, &g)) in nearest.iter().zip(phi_bar).enumerate() {
        if g == 0.0 || p == crate::geometry::grid::NONE {
            continue;
        }
        let [i, j, k] = cells.ijk(c);
        let d = pos[p as usize] - cells.position(i, j, k);
        let len = d.length();
        if len > 0.0 {
            pbar[p as usize] += g * d / len;
        }
    }
}

/// Marker particle number density at cell centres, in full cells (1 = as dense as freshly
/// seeded): each particle is deposited on its 8 nearest cell centres with trilinear weights,
/// and a weight that would fall on a cell beyond a tank wall lands on its mirror image inside
/// (reflection), so every particle deposits exactly one unit. The scatter runs in particle
/// order on one thread, so the sums do not depend on the thread count. They add to `base`
/// (a narrow band's deep cells' deposit) when given.
pub fn particle_density(pos: &[Vec3], grid: &Grid, ppc: usize, base: Option<&[f64]>) -> Vec<f64> {
    let mut out =
        base.map_or_else(|| vec![0.0; grid.num_cells()], |b| b.par_iter().copied().collect());
    let unit = 1.0 / ppc as f64;
    let deposit = |x: Vec3, out: &mut [f64], first: usize| {
        let (idx, w, _) = deposit_weights(grid, x);
        for c in 0..8 {
            let (bi, bj, bk) = (c & 1, (c >> 1) & 1, (c >> 2) & 1);
            out[grid.cell(idx[0][bi], idx[1][bj], idx[2][bk]) - first] +=
                w[0][bi] * w[1][bj] * w[2][bk] * unit;
        }
    };
    let (nz, slab) = (grid.n[2], grid.n[0] * grid.n[1]);
    if nz < 2 {
        pos.iter().for_each(|x| deposit(*x, &mut out, 0));
        return out;
    }
    // A particle in bucket b deposits on z-slabs b and b + 1 only, so the buckets of one
    // parity write disjoint pairs of slabs: even buckets in parallel, then odd ones, each in
    // particle order. A particle outside the tank (whose folded slabs are not adjacent) is
    // deposited last, on one thread.
    let bucket = |x: &Vec3| {
        let [k0, k1] = deposit_axis(grid, comp(*x, 2), 2).0;
        let b = k0.min(k1).min(nz - 2);
        if k0.max(k1) <= b + 1 {
            b
        } else {
            nz - 1
        }
    };
    let keys: Vec<u32> = pos.par_iter().map(|x| bucket(x) as u32).collect();
    let buckets = SlabBuckets::new(&keys, |b| b as usize, nz);
    for parity in 0..2 {
        let pairs =
            out[parity * slab..].par_chunks_mut(2 * slab).with_min_len(min_pieces(2 * slab));
        pairs.enumerate().for_each(|(m, pair)| {
            let b = 2 * m + parity;
            if b + 1 < nz {
                buckets.of(b).iter().for_each(|&p| deposit(pos[p as usize], pair, b * slab));
            }
        });
    }
    buckets.of(nz - 1).iter().for_each(|&p| deposit(pos[p as usize], &mut out, 0));
    out
}

/// Per axis: the two cells, their weights and the weights' derivatives.
type Deposit = ([[usize; 2]; 3], [[f64; 2]; 3], [[f64; 2]; 3]);

/// The cells a particle at `x` deposits on, per axis (folded back at the walls), their 1D
/// weights and the weights' derivatives. Always inlined: a caller that reads only the
/// indices or the weights computes nothing else (the deposit of `large_tank`'s particles
/// called it twice a particle, as a function returning 144 bytes: 4.7% of a step's profile).
#[inline(always)]
fn deposit_weights(grid: &Grid, x: Vec3) -> Deposit {
    // Written out: an array map here stays a call (2.5% of a step's profile).
    let a = x.to_array();
    let (i0, w0) = deposit_axis(grid, a[0], 0);
    let (i1, w1) = deposit_axis(grid, a[1], 1);
    let (i2, w2) = deposit_axis(grid, a[2], 2);
    let dw = [[-1.0 / grid.dx, 1.0 / grid.dx]; 3];
    ([i0, i1, i2], [w0, w1, w2], dw)
}

/// Along axis `d`, the two cells a particle at coordinate `a` deposits on (folded back at
/// the walls) and their weights.
#[inline(always)]
fn deposit_axis(grid: &Grid, a: f64, d: usize) -> ([usize; 2], [f64; 2]) {
    let g = a / grid.dx - 0.5;
    let i0 = crate::math::floor(g);
    let t = g - i0;
    let n = grid.n[d] as i64;
    let i = i0 as i64;
    // Away from the walls (nearly every particle) the two cells need no folding.
    if i >= 0 && i + 1 < n {
        return ([i as usize, i as usize + 1], [1.0 - t, t]);
    }
    let fold = |i: i64| -> usize {
        if i < 0 {
            (-i - 1).min(n - 1) as usize
        } else if i >= n {
            (2 * n - 1 - i).max(0) as usize
        } else {
            i as usize
        }
    };
    ([fold(i), fold(i + 1)], [1.0 - t, t])
}

/// Adjoint of [`particle_density`]: adds `Σ_c dens̄_c · ∂dens_c/∂x_p` into `pbar`.
pub fn particle_density_adjoint(
    pos: &[Vec3],
    grid: &Grid,
    ppc: usize,
    dens_bar: &[f64],
    pbar: &mut [Vec3],
) {
    let unit = 1.0 / ppc as f64;
    // Each particle gathers into its own adjoint: in parallel, the same bits.
    pos.par_iter().zip(pbar.par_iter_mut()).with_min_len(1024).for_each(|(x, xb)| {
        let (idx, w, dw) = deposit_weights(grid, *x);
        let mut g = Vec3::ZERO;
        for c in 0..8 {
            let b = [c & 1, (c >> 1) & 1, (c >> 2) & 1];
            let s = dens_bar[grid.cell(idx[0][b[0]], idx[1][b[1]], idx[2][b[2]])];
            if s == 0.0 {
                continue;
            }
            g += s
                * unit
                * Vec3::new(
                    dw[0][b[0]] * w[1][b[1]] * w[2][b[2]],
                    w[0][b[0]] * dw[1][b[1]] * w[2][b[2]],
                    w[0][b[0]] * w[1][b[1]] * dw[2][b[2]],
                );
        }
        *xb += g;
    });
}

/// Liquid volume in m³: the particle density capped at one full cell per cell, times the
/// cell volume. A freshly seeded region gives its exact volume; marker particles that bunch
/// up (the way a marker-particle liquid loses volume) push cells over full and lower it.
/// A narrow band's deep cells (their deposit `base`) count as the full cells they stand for.
pub fn liquid_volume(pos: &[Vec3], grid: &Grid, ppc: usize, base: Option<&[f64]>) -> f64 {
    let dens = particle_density(pos, grid, ppc, base);
    let parts: Vec<f64> = dens
        .par_chunks(crate::geometry::grid::REDUCE_CHUNK)
        .map(|c| c.iter().map(|d| d.min(1.0)).sum())
        .collect();
    parts.iter().sum::<f64>() * grid.dx.powi(3)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Scattered particles, some on the tank's faces and edges.
    fn scattered(grid: &Grid, n: usize) -> Vec<Vec3> {
        let size = grid.size();
        (0..n)
            .map(|i| {
                let r = |k: usize| ((i * 7919 + k * 104_729) % 10_007) as f64 / 10_006.0;
                let edge = |t: f64| if i % 97 == 0 { t.round() } else { t };
                Vec3::new(edge(r(1)) * size.x, r(2) * size.y, edge(r(3)) * size.z)
            })
            .collect()
    }

    #[test]
    fn liquid_sdf_is_the_nearest_particles_distance_up_to_two_cells() {
        // Sparse: most cells find their nearest particle one or two cells away, or none.
        let grid = Grid { n: [11, 9, 10], dx: 0.1 };
        let pos = scattered(&grid, 60);
        let model = SurfaceModel { radius: 0.03, sparse_cells: false };
        let bins = Bins::new(&pos, &grid);
        let (phi, who) = liquid_sdf_nearest(&pos, &bins, &grid, &model, None);
        let cells = grid.cells();
        let mut rings = [0; 3];
        for c in 0..grid.num_cells() {
            let [i, j, k] = cells.ijk(c);
            let x = cells.position(i, j, k);
            let (d, p) = (0..pos.len())
                .map(|p| ((pos[p] - x).length(), p as u32))
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .expect("particles");
            if d <= 2.0 * grid.dx {
                rings[usize::from(d >= 0.5 * grid.dx) + usize::from(d > grid.dx)] += 1;
                assert_eq!((phi[c], who[c]), (d - model.radius, p), "cell {c}");
            } else {
                assert_eq!(
                    (phi[c], who[c]),
                    (2.0 * grid.dx - model.radius, crate::geometry::grid::NONE),
                    "cell {c}"
                );
            }
        }
        // Found in the own cell, within one cell and within two: every search ring is used.
        assert!(rings.iter().all(|&r| r >= 10), "{rings:?}");
    }

    #[test]
    fn bins_list_each_cells_particles_in_order_with_any_thread_count() {
        let grid = Grid { n: [7, 5, 9], dx: 0.1 };
        // More than two of the counting sort's chunks of 65,536.
        let pos = scattered(&grid, 150_000);
        let run = |t: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap();
            pool.install(|| Bins::new(&pos, &grid))
        };
        let (a, b) = (run(1), run(2));
        assert_eq!((&a.start, &a.items), (&b.start, &b.items));
        for c in 0..grid.num_cells() {
            let want: Vec<u32> =
                (0..pos.len() as u32).filter(|&p| cell_of(&grid, pos[p as usize]) == c).collect();
            assert_eq!(a.cell(c), &want[..], "cell {c}");
        }
    }

    #[test]
    fn deposit_is_the_serial_scatter_with_any_thread_count() {
        let grid = Grid { n: [6, 5, 8], dx: 0.1 };
        // More than two of the slab sort's chunks of 65,536.
        let mut pos = scattered(&grid, 140_000);
        // Two outside the tank, whose folded slabs are not adjacent.
        pos.insert(17, Vec3::new(0.21, 0.33, -0.25));
        pos.push(Vec3::new(0.43, 0.12, 1.06));
        let run = |t: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap();
            pool.install(|| particle_density(&pos, &grid, 8, None))
        };
        let (a, b) = (run(1), run(2));
        assert!(a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()));
        let mut serial = vec![0.0; grid.num_cells()];
        let mut terms = vec![0usize; grid.num_cells()];
        for x in &pos {
            let (idx, w, _) = deposit_weights(&grid, *x);
            for c in 0..8 {
                let (bi, bj, bk) = (c & 1, (c >> 1) & 1, (c >> 2) & 1);
                let cell = grid.cell(idx[0][bi], idx[1][bj], idx[2][bk]);
                serial[cell] += w[0][bi] * w[1][bj] * w[2][bk] / 8.0;
                terms[cell] += 1;
            }
        }
        // The slab pairs add in another order than one serial pass: the two sums of n
        // non-negative terms differ by at most n·ε times the sum.
        for ((x, y), n) in a.iter().zip(&serial).zip(&terms) {
            let bound = *n as f64 * f64::EPSILON * y;
            assert!((x - y).abs() <= bound, "{x} against {y} ({n} terms)");
        }
        let total: f64 = a.iter().sum();
        assert!((total - pos.len() as f64 / 8.0).abs() < 1e-9, "each particle deposits one unit");
    }

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
        let sdf = NodeSdf::new(&grid, &[]);
        let pos = seed(&grid, &[region], 8, &sdf, None);
        assert_eq!(pos.len(), 8 * 8 * 4 * 8);
        let bins = Bins::new(&pos, &grid);
        let vol = liquid_volume(&pos, &grid, 8, None);
        assert!((vol - 0.5).abs() < 1e-12, "volume {vol}");
        let model = SurfaceModel { radius: particle_radius(grid.dx, 2), sparse_cells: true };
        let phi = liquid_sdf(&pos, &bins, &grid, &model, None);
        // Centres at y = 7/16 (below) and 9/16 (above) straddle the surface y = 0.5 evenly.
        let below = phi[grid.cell(3, 3, 3)];
        let above = phi[grid.cell(3, 4, 3)];
        assert!(below < 0.0 && above > 0.0);
        assert!((below / (below - above) - 0.5).abs() < 1e-12);
    }
}

#[cfg(test)]
mod adjoint_tests {
    //! Each particle-stage adjoint against central differences of its forward map, for a
    //! fixed linear functional of the output: ⟨∇L, d⟩ = (L(x + εd) − L(x − εd)) / 2ε.
    use super::*;
    use crate::math::{Rotation, SharedShape};

    fn grid() -> Grid {
        Grid { n: [8, 7, 6], dx: 0.1 }
    }

    /// Particles spread over the tank, away from lattice planes.
    fn particles(n: usize) -> Vec<Vec3> {
        (0..n)
            .map(|i| {
                let f = |k: usize| ((i * k * 7919 + k * 104729) % 1000) as f64 / 1000.0;
                Vec3::new(0.05 + 0.7 * f(3), 0.05 + 0.6 * f(5), 0.05 + 0.5 * f(7))
                    + Vec3::splat(1e-4)
            })
            .collect()
    }

    fn field(grid: &Grid, seed: usize) -> Mac {
        let mut u = Mac::zeros(grid);
        for a in 0..3 {
            for (f, x) in u.c[a].iter_mut().enumerate() {
                *x = (((f * 7919 + a * 131 + seed * 31) % 101) as f64 / 50.0 - 1.0) * 0.6 + 0.0123;
            }
        }
        u
    }

    fn dir(n: usize, seed: usize) -> Vec<Vec3> {
        (0..n)
            .map(|i| {
                let f = |k: usize| ((i * 31 + k * 17 + seed * 7) % 23) as f64 / 11.5 - 1.0;
                Vec3::new(f(1), f(2), f(3))
            })
            .collect()
    }

    fn dot(a: &[Vec3], b: &[Vec3]) -> f64 {
        a.iter().zip(b).map(|(x, y)| x.dot(*y)).sum()
    }

    /// The liquid distance and its nearest particle per cell against a search over every
    /// particle, for a dense block (where a cell's own particle is the nearest) beside sparse
    /// ones (where the search must look one or two rings out, or give up at 2·dx).
    #[test]
    fn nearest_particle_is_the_nearest_of_all() {
        let grid = grid();
        let mut pos = particles(150);
        // A dense block: 8 jittered particles in each of 3×3×2 cells.
        for c in 0..18 {
            let ijk = [1 + c % 3, 1 + (c / 3) % 3, 1 + c / 9];
            for q in 0..8 {
                let r = |k: usize| ((c * 131 + q * 17 + k * 7) % 97) as f64 / 97.0 * 0.02 - 0.01;
                let sub = [q & 1, (q >> 1) & 1, (q >> 2) & 1];
                pos.push(Vec3::from_array(
                    [0, 1, 2]
                        .map(|a| (ijk[a] as f64 + 0.25 + 0.5 * sub[a] as f64) * grid.dx + r(a)),
                ));
            }
        }
        let model = SurfaceModel { radius: particle_radius(grid.dx, 2), sparse_cells: false };
        let bins = Bins::new(&pos, &grid);
        let (phi, who) = liquid_sdf_nearest(&pos, &bins, &grid, &model, None);
        let cells = grid.cells();
        let mut own = 0;
        for c in 0..grid.num_cells() {
            let [i, j, k] = cells.ijk(c);
            let x = cells.position(i, j, k);
            let (d, p) = pos
                .iter()
                .enumerate()
                .map(|(p, y)| ((*y - x).length(), p as u32))
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .unwrap();
            if d <= 2.0 * grid.dx {
                assert_eq!((phi[c], who[c]), (d - model.radius, p), "cell {c}");
                own += usize::from(d < 0.5 * grid.dx);
            } else {
                assert_eq!(phi[c], 2.0 * grid.dx - model.radius, "cell {c}");
            }
        }
        assert!(own >= 18, "the dense block's cells find their own particle: {own}");
    }

    /// Advection through a field with a solid obstacle and the tank walls in reach: the
    /// adjoint in the positions and in the field against central differences.
    #[test]
    fn advection_adjoint_matches_central_differences() {
        let grid = grid();
        let obstacle =
            Solid::new(SharedShape::ball(0.12), Pose::from_translation(Vec3::new(0.4, 0.3, 0.3)));
        let node_sdf = NodeSdf::new(&grid, &[obstacle]);
        let (p0, u, du) = (particles(200), field(&grid, 1), field(&grid, 2));
        let (c, dp) = (dir(200, 3), dir(200, 4));
        let (dt, subs) = (0.05, 3);
        let run = |p: &[Vec3], u: &Mac| {
            let mut q = p.to_vec();
            advect_substepped(&mut q, u, &grid, dt, subs, &node_sdf);
            dot(&q, &c)
        };
        let mut pbar = c.clone();
        let mut ubar = Mac::zeros(&grid);
        advect_adjoint(&p0, &mut pbar, &u, &grid, dt, subs, &node_sdf, &mut ubar);
        let eps = 1e-7;
        let shift = |s: f64| p0.iter().zip(&dp).map(|(x, d)| *x + s * *d).collect::<Vec<_>>();
        let fd = (run(&shift(eps), &u) - run(&shift(-eps), &u)) / (2.0 * eps);
        let ad = dot(&pbar, &dp);
        assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "positions: adjoint {ad:e}, fd {fd:e}");
        let moved = |s: f64| {
            let mut v = u.clone();
            for a in 0..3 {
                for (x, d) in v.c[a].iter_mut().zip(&du.c[a]) {
                    *x += s * d;
                }
            }
            v
        };
        let fd = (run(&p0, &moved(eps)) - run(&p0, &moved(-eps))) / (2.0 * eps);
        let ad = ubar.dot(&du);
        assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "field: adjoint {ad:e}, fd {fd:e}");
    }

    /// The push out of a tilted box and a ball: positions and the bodies' pose.
    #[test]
    fn push_out_adjoint_matches_central_differences() {
        let grid = grid();
        let pose = |x: [f64; 3], q: Rotation| Pose::from_parts(Vec3::from_array(x), q);
        let bodies = vec![
            RigidBody::new(
                "box".into(),
                SharedShape::cuboid(0.15, 0.1, 0.12),
                pose(
                    [0.31, 0.33, 0.29],
                    Rotation::from_axis_angle(Vec3::new(0.3, 1.0, 0.2).normalize(), 0.4),
                ),
                500.0,
            ),
            RigidBody::new(
                "ball".into(),
                SharedShape::ball(0.1),
                pose([0.55, 0.4, 0.3], Rotation::IDENTITY),
                500.0,
            ),
        ];
        let (p0, c, dp) = (particles(400), dir(400, 5), dir(400, 6));
        let margin = 1e-3 * grid.dx;
        let run = |p: &[Vec3], bodies: &[RigidBody]| {
            let mut q = p.to_vec();
            push_out_of_bodies(&mut q, bodies, margin);
            dot(&q, &c)
        };
        let mut pbar = c.clone();
        let pose_bar =
            push_out_of_bodies_adjoint(&p0, &mut pbar, &bodies, margin, jacobian_step(&grid));
        let mut pushed = p0.clone();
        push_out_of_bodies(&mut pushed, &bodies, margin);
        assert!(pushed.iter().zip(&p0).filter(|(a, b)| a != b).count() > 20, "too few pushed");
        let eps = 1e-7;
        let shift = |s: f64| p0.iter().zip(&dp).map(|(x, d)| *x + s * *d).collect::<Vec<_>>();
        let fd = (run(&shift(eps), &bodies) - run(&shift(-eps), &bodies)) / (2.0 * eps);
        let ad = dot(&pbar, &dp);
        assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "positions: adjoint {ad:e}, fd {fd:e}");
        for (b, k) in [(0, 0), (0, 4), (1, 1), (1, 5)] {
            let moved = |s: f64| {
                let mut bs = bodies.clone();
                let e = s * crate::math::unit(k % 3);
                if k < 3 {
                    bs[b].x += e;
                } else {
                    bs[b].q = (Rotation::from_scaled_axis(e) * bs[b].q).normalize();
                }
                bs
            };
            let fd = (run(&p0, &moved(eps)) - run(&p0, &moved(-eps))) / (2.0 * eps);
            let ad = pose_bar[b][k];
            assert!(
                (ad - fd).abs() <= 1e-5 * fd.abs().max(1e-3),
                "body {b} dir {k}: {ad:e} vs {fd:e}"
            );
        }
    }

    /// φ_L and the particle density in the particles.
    #[test]
    fn sdf_and_density_adjoints_match_central_differences() {
        let grid = grid();
        let (p0, dp) = (particles(300), dir(300, 8));
        let cells = grid.num_cells();
        let phi_bar: Vec<f64> = (0..cells).map(|c| ((c * 37) % 11) as f64 / 5.0 - 1.0).collect();
        let model = SurfaceModel { radius: particle_radius(grid.dx, 2), sparse_cells: true };
        let sdf = |p: &[Vec3]| {
            let phi = liquid_sdf(p, &Bins::new(p, &grid), &grid, &model, None);
            phi.iter().zip(&phi_bar).map(|(a, b)| a * b).sum::<f64>()
        };
        let dens = |p: &[Vec3]| {
            particle_density(p, &grid, 8, None)
                .iter()
                .zip(&phi_bar)
                .map(|(a, b)| a * b)
                .sum::<f64>()
        };
        let (_, nearest) = liquid_sdf_nearest(&p0, &Bins::new(&p0, &grid), &grid, &model, None);
        let mut g_sdf = vec![Vec3::ZERO; p0.len()];
        liquid_sdf_adjoint(&p0, &nearest, &grid, &phi_bar, &mut g_sdf);
        let mut g_dens = vec![Vec3::ZERO; p0.len()];
        particle_density_adjoint(&p0, &grid, 8, &phi_bar, &mut g_dens);
        let eps = 1e-7;
        let shift = |s: f64| p0.iter().zip(&dp).map(|(x, d)| *x + s * *d).collect::<Vec<_>>();
        for (name, f, g) in
            [("sdf", &sdf as &dyn Fn(&[Vec3]) -> f64, &g_sdf), ("density", &dens, &g_dens)]
        {
            let fd = (f(&shift(eps)) - f(&shift(-eps))) / (2.0 * eps);
            let ad = dot(g, &dp);
            assert!(fd.abs() > 1e-3, "{name}: a vanishing derivative checks nothing");
            assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "{name}: adjoint {ad:e}, fd {fd:e}");
        }
    }
}
