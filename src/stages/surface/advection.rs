//! The particles' advection (RK2 sub-steps in the grid velocity, kept in the tank and out of
//! static solids) and its adjoint.

use crate::geometry::fractions::NodeSdf;
use crate::geometry::grid::{Grid, Mac, MacSampler};
use crate::math::Vec3;
use rayon::prelude::*;

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

    /// The margin kept from the walls and the static solids: a thousandth of a cell.
    #[inline(always)]
    fn margin(&self) -> f64 {
        1e-3 * self.grid.dx
    }

    /// `p` moved along the gradient of the static solids' distance `sdf` to the margin,
    /// from wherever it is; None where the distance has no direction.
    #[inline(always)]
    fn out_to_margin(&self, sdf: &[f64], p: Vec3) -> Option<Vec3> {
        let (d, g) = self.grid.nodes().sample_grad(sdf, p);
        if g.length() > 1e-12 {
            Some(p + (self.margin() - d) * g.normalize())
        } else {
            None
        }
    }

    /// A point a thousandth of a cell out of the static solids and inside the tank. Always
    /// inlined: left a call, each of a particle's sub-steps and its displacement paid for
    /// one, and for passing the point through memory.
    #[inline(always)]
    pub fn keep(&self, y: Vec3) -> Vec3 {
        let margin = self.margin();
        let mut y = y;
        // The distance alone first: far from the solids (most particles) that is all. (An
        // `if let` and a test, not `Option::filter`, which stayed a call a point.)
        if let Some(sdf) = self.solids {
            if self.grid.nodes().sample(sdf, y) < margin {
                if let Some(z) = self.out_to_margin(sdf, y) {
                    y = z;
                }
            }
        }
        y.clamp(Vec3::splat(margin), self.grid.size() - Vec3::splat(margin))
    }

    /// The transpose of [`Walls::keep`]'s Jacobian at `y` applied to `bar`, of the rules
    /// that acted there: the clamp holds a coordinate still, and the solids' push is
    /// differentiated by central differences of step `h` as a push, also where a point
    /// within `h` of the margin's edge would not be pushed (a central difference across
    /// that edge reads the mean of the two sides' slopes; docs/gradients.md, "The
    /// push-out's two sides").
    pub fn keep_adjoint(&self, y: Vec3, bar: Vec3, h: f64) -> Vec3 {
        let margin = self.margin();
        let pushed = self
            .solids
            .filter(|sdf| self.grid.nodes().sample(sdf, y) < margin)
            .and_then(|sdf| Some((sdf, self.out_to_margin(sdf, y)?)));
        let z = pushed.map_or(y, |(_, z)| z);
        let hi = self.grid.size() - Vec3::splat(margin);
        let mut b = bar;
        for a in 0..3 {
            if z[a] < margin || z[a] > hi[a] {
                b[a] = 0.0;
            }
        }
        match pushed {
            Some((sdf, _)) => jacobian_t(|p| self.out_to_margin(sdf, p).unwrap_or(p), y, h, b),
            None => b,
        }
    }
}

/// One particle's path: `subs` midpoint (RK2) sub-steps of length `h` through `u`, each
/// ending with [`Walls::keep`].
#[inline]
fn advect_one(x: Vec3, u: &MacSampler<'_>, walls: &Walls<'_>, h: f64, subs: usize) -> Vec3 {
    let mut x = x;
    for _ in 0..subs {
        let mid = x + 0.5 * h * u.velocity(x);
        x = walls.keep(x + h * u.velocity(mid));
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
    let u = MacSampler::new(u, grid);
    pos.par_iter_mut().for_each(|x| *x = advect_one(*x, &u, &walls, h, subs));
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
    let sampler = MacSampler::new(u, grid);
    // A particle's path through its sub-steps: each start, midpoint, end before the walls,
    // and whether the walls left it there.
    let replay = |path: &mut Vec<(Vec3, Vec3, Vec3, bool)>, x0: Vec3| {
        path.clear();
        let mut x = x0;
        for _ in 0..subs {
            let mid = x + 0.5 * h * sampler.velocity(x);
            let y = x + h * sampler.velocity(mid);
            let kept = walls.keep(y);
            path.push((x, mid, y, kept == y));
            x = kept;
        }
    };
    if rayon::current_num_threads() == 1 {
        // One thread: each read scattered where its stencil is made (the same reads in the
        // same order as below, so the same bits), not kept and made again.
        let mut path = Vec::with_capacity(subs);
        for (x0, xb) in pos0.iter().zip(pbar.iter_mut()) {
            if *xb == Vec3::ZERO {
                continue;
            }
            replay(&mut path, *x0);
            *xb = walk_back(&path, *xb, h, &walls, fd, |p, coef| {
                u.gradient_and_scatter(grid, p, coef, ubar)
            });
        }
        return;
    }
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
                    replay(path, *x0);
                    let mut n = 0;
                    *xb = walk_back(path, *xb, h, &walls, fd, |p, coef| {
                        out[n] = (p, coef);
                        n += 1;
                        u.velocity_gradient(grid, p)
                    });
                },
            );
    });
}

/// One particle's sub-steps `path` (start, midpoint, end before the walls, whether they
/// left it there) walked back from ∂L/∂(its end) `bar` to ∂L/∂(its start): x' = keep(y),
/// the identity unless the push or the clamp acted; y = x + h·U(mid), mid = x + h/2·U(x).
/// Each read of the field, the point and the coefficient of the velocity there (the
/// midpoint's, then the start's, last sub-step first), goes to `read`, which gives the
/// field's gradient at that point.
#[inline(always)]
fn walk_back(
    path: &[(Vec3, Vec3, Vec3, bool)],
    bar: Vec3,
    h: f64,
    walls: &Walls<'_>,
    fd: f64,
    mut read: impl FnMut(Vec3, Vec3) -> [Vec3; 3],
) -> Vec3 {
    let mut bar = bar;
    for &(x, mid, y, free) in path.iter().rev() {
        let ybar = if free { bar } else { walls.keep_adjoint(y, bar, fd) };
        let jm = read(mid, h * ybar);
        let mbar = h * (ybar.x * jm[0] + ybar.y * jm[1] + ybar.z * jm[2]);
        let jx = read(x, 0.5 * h * mbar);
        bar = ybar + mbar + 0.5 * h * (mbar.x * jx[0] + mbar.y * jx[1] + mbar.z * jx[2]);
    }
    bar
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
