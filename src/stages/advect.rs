//! Semi-Lagrangian advection of the velocity field (stage `advect_velocity`).
//!
//! Each face sample at `x_g` is traced back with one forward-Euler step through the current
//! field, `x_b = x_g − Δt·U(x_g)`, and takes the trilinear value of its own component there:
//! `u_new(x_g) = I(u, x_b)`. The paper picks forward Euler for the backtrace because its
//! derivative is simple: the map is `W(u)·u`, and its adjoint is `(W + ∂W/∂u·u)ᵀ` (eq. 4).

use crate::geometry::grid::{Grid, Mac};
use crate::math::par::{min_pieces, MIN_LEN};
use crate::math::Vec3;
use rayon::prelude::*;

/// Faces whose advected value the step reads, per axis (see [`needed_faces`]); `None` in the
/// functions below means every face.
pub type FaceMask = [Vec<bool>; 3];

/// The faces whose advected value the rest of the step reads: those of liquid cells (φ_L < 0
/// after extension into solids: the projection's faces) and those a body covers (the velocity correction mixes the fluid
/// velocity there with the body's). Every other face is overwritten by extrapolation or set
/// to zero before the step ends, so advecting it would be wasted work: with the mask, air
/// far from the liquid costs nothing here. An empty `phi` marks the bodies' faces alone.
pub fn needed_faces(
    grid: &Grid,
    phi: &[f64],
    body_faces: &[crate::geometry::fractions::BodyFaces],
) -> FaceMask {
    let n = grid.n;
    let mut mask = [0, 1, 2].map(|a| vec![false; grid.faces(a).len()]);
    for (a, m) in mask.iter_mut().enumerate() {
        // A face is needed when the cell on either side of it is liquid (no φ: none is).
        let lat = grid.faces(a);
        let below = [1, n[0], n[0] * n[1]][a];
        let slabs = if phi.is_empty() { 0 } else { lat.n[2] };
        let pieces = m[..slabs * lat.slab()].par_chunks_mut(lat.slab());
        pieces.with_min_len(min_pieces(lat.slab())).enumerate().for_each(|(k, slab)| {
            for j in 0..lat.n[1] {
                for i in 0..lat.n[0] {
                    let at = [i, j, k][a];
                    let c = grid.cell(i.min(n[0] - 1), j.min(n[1] - 1), k.min(n[2] - 1));
                    let plus = at < n[a] && phi[c] < 0.0;
                    let minus = at > 0 && phi[if at < n[a] { c - below } else { c }] < 0.0;
                    slab[i + lat.n[0] * j] = plus || minus;
                }
            }
        });
        for bf in body_faces {
            for &(f, _) in &bf.faces[a] {
                m[f] = true;
            }
        }
    }
    mask
}

/// The four faces of component `b` whose mean is the velocity component `b` at the centre of
/// face `ijk` of component `axis` (`b ≠ axis`): exactly the trilinear interpolation there,
/// with the lattice clamped at the walls as [`crate::geometry::grid::Lattice::sample`] clamps it.
#[inline(always)]
fn cross_faces(grid: &Grid, axis: usize, ijk: [usize; 3], b: usize) -> [usize; 4] {
    // Along `axis` the face sits half a cell from the component-b faces on either side.
    let n = grid.n[axis];
    let (a0, a1) = match ijk[axis] {
        0 => (0, 0),
        i if i >= n => (n - 1, n - 1),
        i => (i - 1, i),
    };
    // On the lattice of the component-b faces (one more sample along b).
    let [n0, n1, _] = grid.face_dims(b);
    let stride = [1, n0, n0 * n1];
    let mut q = ijk;
    q[axis] = a0;
    let first = q[0] + n0 * (q[1] + n1 * q[2]);
    let (next_b, next_a) = (stride[b], (a1 - a0) * stride[axis]);
    [first, first + next_b, first + next_a, first + next_a + next_b]
}

/// The velocity at the centre of face `ijk` (flat index `f`) of component `axis`: its own
/// value and, for the other two components, the mean of the four nearest faces. The same
/// value as `u.velocity(grid, position)` at a fraction of the cost.
#[inline(always)]
pub fn face_velocity(u: &Mac, grid: &Grid, axis: usize, ijk: [usize; 3], f: usize) -> Vec3 {
    let mut v = [0.0; 3];
    v[axis] = u.c[axis][f];
    for b in (0..3).filter(|&b| b != axis) {
        let q = cross_faces(grid, axis, ijk, b);
        v[b] = 0.25 * ((u.c[b][q[0]] + u.c[b][q[1]]) + (u.c[b][q[2]] + u.c[b][q[3]]));
    }
    crate::math::v3(v)
}

/// Advects `u` through itself for `dt`. With a mask, faces outside it are left at zero.
pub fn advect(u: &Mac, grid: &Grid, dt: f64, mask: Option<&FaceMask>) -> Mac {
    let mut out = Mac::zeros(grid);
    advect_into(u, grid, dt, mask, &mut out);
    out
}

/// [`advect`] written over `out` (a field of the grid's size): every face is set.
pub fn advect_into(u: &Mac, grid: &Grid, dt: f64, mask: Option<&FaceMask>, out: &mut Mac) {
    let [x, y, z] = &mut out.c;
    advect_axis::<0>(u, grid, dt, mask, x);
    advect_axis::<1>(u, grid, dt, mask, y);
    advect_axis::<2>(u, grid, dt, mask, z);
}

/// [`advect_into`]'s component `AXIS`, the axis a constant (each face's index arithmetic
/// then folds; measured in docs/performance.md, "Why the hot paths are written as they are").
fn advect_axis<const AXIS: usize>(
    u: &Mac,
    grid: &Grid,
    dt: f64,
    mask: Option<&FaceMask>,
    dst: &mut [f64],
) {
    let lat = grid.faces(AXIS);
    let src = &u.c[AXIS];
    let m = mask.map(|m| &m[AXIS]);
    lat.fill_par(dst, |i, j, k| {
        let f = lat.index(i, j, k);
        if m.is_some_and(|m| !m[f]) {
            return 0.0;
        }
        let xb = lat.position(i, j, k) - dt * face_velocity(u, grid, AXIS, [i, j, k], f);
        lat.sample(src, xb)
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn needed_faces_are_the_faces_of_liquid_cells() {
        let grid = Grid { n: [6, 5, 7], dx: 0.1 };
        let cells = grid.cells();
        let phi: Vec<f64> = (0..cells.len()).map(|c| ((c * 7919) % 13) as f64 - 6.5).collect();
        let mask = needed_faces(&grid, &phi, &[]);
        for a in 0..3 {
            let lat = grid.faces(a);
            let mut want = vec![false; lat.len()];
            for c in (0..cells.len()).filter(|&c| phi[c] < 0.0) {
                let [i, j, k] = cells.ijk(c);
                let mut hi = [i, j, k];
                hi[a] += 1;
                want[lat.index(i, j, k)] = true;
                want[lat.index(hi[0], hi[1], hi[2])] = true;
            }
            assert_eq!(mask[a], want, "axis {a}");
        }
        assert!(needed_faces(&grid, &[], &[]).iter().all(|m| m.iter().all(|x| !x)));
    }

    #[test]
    fn uniform_flow_is_preserved() {
        // A uniform velocity field is a steady solution of u·∇u = 0.
        let grid = Grid { n: [6, 5, 4], dx: 0.2 };
        let mut u = Mac::zeros(&grid);
        for (a, val) in [0.3, -0.2, 0.1].iter().enumerate() {
            u.c[a].iter_mut().for_each(|x| *x = *val);
        }
        let out = advect(&u, &grid, 0.1, None);
        for a in 0..3 {
            for (x, y) in out.c[a].iter().zip(&u.c[a]) {
                assert!((x - y).abs() < 1e-14);
            }
        }
    }
}

/// Tangent of [`advect`] at `u` in direction `du`:
/// `δu_new(x_g) = I(δu, x_b) − Δt·∇I(u, x_b)·δU(x_g)`, with `x_b = x_g − Δt·U(x_g)`.
pub fn advect_tangent(u: &Mac, du: &Mac, grid: &Grid, dt: f64, mask: Option<&FaceMask>) -> Mac {
    let mut out = Mac::zeros(grid);
    for (axis, dst) in out.c.iter_mut().enumerate() {
        let lat = grid.faces(axis);
        let m = mask.map(|m| &m[axis]);
        lat.fill_par(dst, |i, j, k| {
            let f = lat.index(i, j, k);
            if m.is_some_and(|m| !m[f]) {
                return 0.0;
            }
            let xb = lat.position(i, j, k) - dt * face_velocity(u, grid, axis, [i, j, k], f);
            let (_, grad) = lat.sample_grad(&u.c[axis], xb);
            let dvel = face_velocity(du, grid, axis, [i, j, k], f);
            lat.sample(&du.c[axis], xb) - dt * grad.dot(dvel)
        });
    }
    out
}

/// Adjoint of [`advect`] at `u`: `(W + ∂W/∂u·u)ᵀ·adj` (paper, eq. 4), the exact transpose of
/// [`advect_tangent`] with the same mask. A scatter, in parallel and deterministic: a face
/// scatters only within `reach` z-slabs of its own (its backtrace moves at most Δt·max|w|,
/// its stencils add a slab each way), so the faces are taken in blocks of 2·`reach` slabs,
/// the even blocks in parallel and then the odd ones (blocks of one parity write disjoint
/// slabs), each block's faces in face order. The order in which a sample's sums are taken
/// depends on the field only, never on the thread count.
pub fn advect_adjoint(u: &Mac, adj: &Mac, grid: &Grid, dt: f64, mask: Option<&FaceMask>) -> Mac {
    let mut out = Mac::zeros(grid);
    advect_adjoint_into(u, adj, grid, dt, mask, &mut out);
    out
}

/// [`advect_adjoint`] written over `out` (a field of the grid's size, whatever it holds).
pub fn advect_adjoint_into(
    u: &Mac,
    adj: &Mac,
    grid: &Grid,
    dt: f64,
    mask: Option<&FaceMask>,
    out: &mut Mac,
) {
    let blocks = Blocks::new(u, grid, dt);
    blocks.scatter(grid, out, |j, sc| {
        let walk = AdjointWalk { u, adj, grid, dt, mask };
        let z = |a: usize| blocks.slabs(j, a);
        walk.slabs::<0>(z(0), sc);
        walk.slabs::<1>(z(1), sc);
        walk.slabs::<2>(z(2), sc);
    });
}

/// [`advect_adjoint_into`] from the faces' traces through `u` found beforehand: the same
/// bits, the faces taken in the same order, each face's sums in the same order.
pub fn advect_adjoint_traced(traces: &AdvectionTraces, adj: &Mac, grid: &Grid, out: &mut Mac) {
    let dt = traces.dt;
    traces.blocks.scatter(grid, out, |j, sc| {
        let [x, y, z] = &traces.faces[j];
        x.iter().for_each(|t| scatter::<0>(t, adj.c[0][t.face as usize], dt, sc));
        y.iter().for_each(|t| scatter::<1>(t, adj.c[1][t.face as usize], dt, sc));
        z.iter().for_each(|t| scatter::<2>(t, adj.c[2][t.face as usize], dt, sc));
    });
}

/// How the adjoint's scatter splits the faces (see [`advect_adjoint`]): in blocks of
/// `2·reach` z-slabs, a face's writes reaching at most `reach` slabs from its own.
#[derive(Clone, Copy, Debug)]
struct Blocks {
    reach: usize,
    block: usize,
    /// Slabs of each lattice along z (the z faces have one more).
    slabs: [usize; 3],
    count: usize,
}

impl Blocks {
    fn new(u: &Mac, grid: &Grid, dt: f64) -> Blocks {
        let w_max = crate::geometry::grid::max_abs(&u.c[2]);
        let reach = (dt * w_max / grid.dx).ceil() as usize + 2;
        let block = 2 * reach;
        let slabs = [0, 1, 2].map(|a| grid.faces(a).n[2]);
        let count = slabs.iter().max().expect("three axes").div_ceil(block);
        Blocks { reach, block, slabs, count }
    }

    /// The z-slabs of block `j` on the lattice of component `a`.
    fn slabs(&self, j: usize, a: usize) -> std::ops::Range<usize> {
        (j * self.block).min(self.slabs[a])..((j + 1) * self.block).min(self.slabs[a])
    }

    /// Zeroes `out`, then runs `block(j, share)` for every block j, the even ones in
    /// parallel and then the odd ones, `share` the slabs within `reach` of block j's own.
    fn scatter(&self, grid: &Grid, out: &mut Mac, block: impl Fn(usize, &mut Scatter<'_>) + Sync) {
        for c in &mut out.c {
            c.par_iter_mut().with_min_len(MIN_LEN).for_each(|x| *x = 0.0);
        }
        let Blocks { reach, block: size, slabs, count } = *self;
        for parity in 0..2 {
            // Each block of this parity owns the slabs within `reach` of its own.
            let mut parts: Vec<(usize, Scatter<'_>)> = Vec::new();
            let mut rest: [&mut [f64]; 3] = {
                let [x, y, z] = &mut out.c;
                [x.as_mut_slice(), y.as_mut_slice(), z.as_mut_slice()]
            };
            let mut at = [0usize; 3];
            for j in (parity..count).step_by(2) {
                let lo = (j * size).saturating_sub(reach);
                let mut pieces: [&mut [f64]; 3] = Default::default();
                let mut first = [0usize; 3];
                for a in 0..3 {
                    let slab = grid.faces(a).slab();
                    let l = lo.min(slabs[a]) * slab;
                    let h = ((j + 1) * size + reach).min(slabs[a]) * slab;
                    // Blocks of one parity are 2·reach slabs apart: their shares follow in
                    // order.
                    let (_, tail) = std::mem::take(&mut rest[a]).split_at_mut(l - at[a]);
                    let (mine, tail) = tail.split_at_mut(h - l);
                    (pieces[a], rest[a], first[a], at[a]) = (mine, tail, l, h);
                }
                parts.push((j, Scatter { pieces, first }));
            }
            // A block of a small grid is less work than waking a worker.
            let per = min_pieces(size * grid.faces(0).slab());
            parts.into_par_iter().with_min_len(per).for_each(|(j, mut sc)| block(j, &mut sc));
        }
    }
}

/// What the adjoint's scatter at a field `u` reads of `u` alone ([`advect_adjoint_traced`]):
/// per block of the scatter and per component, each face's trace (the eight samples of its
/// backtrace's stencil and their weights, the gradient there, the faces its velocity was
/// the mean of) in the order the scatter takes them (the faces of the mask). It does not depend on the adjoint, so the
/// backward pass finds it ahead of the step's adjoints (`gradients/backward.rs`).
#[derive(Clone, Debug)]
pub struct AdvectionTraces {
    blocks: Blocks,
    dt: f64,
    faces: Vec<[Vec<Trace>; 3]>,
}

impl AdvectionTraces {
    /// The traces of [`advect_adjoint_into`] at `u` with these arguments.
    pub fn new(u: &Mac, grid: &Grid, dt: f64, mask: Option<&FaceMask>) -> AdvectionTraces {
        let blocks = Blocks::new(u, grid, dt);
        let faces = (0..blocks.count)
            .into_par_iter()
            .map(|j| {
                let z = |a: usize| blocks.slabs(j, a);
                [
                    traces::<0>(u, grid, dt, mask, z(0)),
                    traces::<1>(u, grid, dt, mask, z(1)),
                    traces::<2>(u, grid, dt, mask, z(2)),
                ]
            })
            .collect();
        AdvectionTraces { blocks, dt, faces }
    }
}

/// The traces of the faces of component `AXIS` of the mask in the z-slabs `z`, in face order.
fn traces<const AXIS: usize>(
    u: &Mac,
    grid: &Grid,
    dt: f64,
    mask: Option<&FaceMask>,
    z: std::ops::Range<usize>,
) -> Vec<Trace> {
    let [n0, n1, _] = grid.faces(AXIS).n;
    let mut out = Vec::new();
    let mut g = z.start * n0 * n1;
    for k in z {
        for row in 0..n1 {
            for i in 0..n0 {
                if mask.is_none_or(|m| m[AXIS][g]) {
                    out.push(trace::<AXIS>(u, grid, dt, [i, row, k], g));
                }
                g += 1;
            }
        }
    }
    out
}

/// What the adjoint's scatter reads of the forward field at one face: the face, the
/// eight samples of its backtrace's stencil and their weights, the gradient of its own
/// component there, and the four faces of each other component (in increasing order) its
/// velocity was the mean of.
#[derive(Clone, Copy, Debug)]
struct Trace {
    face: u32,
    idx: [u32; 8],
    w: [f64; 8],
    grad: Vec3,
    q: [[u32; 4]; 2],
}

/// The [`Trace`] of face `ijk` (flat index `g`) of component `AXIS`.
#[inline(always)]
fn trace<const AXIS: usize>(u: &Mac, grid: &Grid, dt: f64, ijk: [usize; 3], g: usize) -> Trace {
    let lat = grid.faces(AXIS);
    let mut q = [[0u32; 4]; 2];
    let mut v = [0.0; 3];
    v[AXIS] = u.c[AXIS][g];
    for (k, b) in (0..3).filter(|&b| b != AXIS).enumerate() {
        let qb = cross_faces(grid, AXIS, ijk, b);
        let c = &u.c[b];
        v[b] = 0.25 * ((c[qb[0]] + c[qb[1]]) + (c[qb[2]] + c[qb[3]]));
        q[k] = qb.map(|f| f as u32);
    }
    let xb = lat.position(ijk[0], ijk[1], ijk[2]) - dt * crate::math::v3(v);
    let sb = lat.stencil(xb);
    let mut grad = Vec3::ZERO;
    for c in 0..8 {
        grad += sb.dw[c] * u.c[AXIS][sb.idx[c]];
    }
    Trace { face: g as u32, idx: sb.idx.map(|i| i as u32), w: sb.w, grad, q }
}

/// One face's transpose from its trace and its adjoint `a`: the sample's weights and,
/// through its backtrace, the velocity it was traced with ([`face_velocity`]'s transpose).
/// Nothing for a zero adjoint.
#[inline(always)]
fn scatter<const AXIS: usize>(t: &Trace, a: f64, dt: f64, out: &mut Scatter<'_>) {
    if a == 0.0 {
        return;
    }
    for c in 0..8 {
        out.add(AXIS, t.idx[c] as usize, a * t.w[c]);
    }
    let coef = (-dt * a) * t.grad;
    out.add(AXIS, t.face as usize, crate::math::comp(coef, AXIS));
    for (k, b) in (0..3).filter(|&b| b != AXIS).enumerate() {
        let c = 0.25 * crate::math::comp(coef, b);
        if c != 0.0 {
            for f in t.q[k] {
                out.add(b, f as usize, c);
            }
        }
    }
}

/// What the adjoint's faces read ([`advect_adjoint_into`]), walked an axis at a time with
/// the axis a constant (each face's index arithmetic then folds).
struct AdjointWalk<'a> {
    u: &'a Mac,
    adj: &'a Mac,
    grid: &'a Grid,
    dt: f64,
    mask: Option<&'a FaceMask>,
}

impl AdjointWalk<'_> {
    /// The faces of component `AXIS` in the z-slabs `z`, in face order (walked by (k, j, i),
    /// not by flat index: two integer divisions a face less).
    fn slabs<const AXIS: usize>(&self, z: std::ops::Range<usize>, out: &mut Scatter<'_>) {
        let [n0, n1, _] = self.grid.faces(AXIS).n;
        let mut g = z.start * n0 * n1;
        for k in z {
            for row in 0..n1 {
                for i in 0..n0 {
                    self.face::<AXIS>([i, row, k], g, out);
                    g += 1;
                }
            }
        }
    }

    /// One face's transpose, its trace found on the way.
    #[inline(always)]
    fn face<const AXIS: usize>(&self, ijk: [usize; 3], g: usize, out: &mut Scatter<'_>) {
        let a = self.adj.c[AXIS][g];
        if a == 0.0 || self.mask.is_some_and(|m| !m[AXIS][g]) {
            return;
        }
        scatter::<AXIS>(&trace::<AXIS>(self.u, self.grid, self.dt, ijk, g), a, self.dt, out);
    }
}

/// One block's share of the three components of the adjoint field: the samples of each
/// component from `first[a]` on.
struct Scatter<'a> {
    pieces: [&'a mut [f64]; 3],
    first: [usize; 3],
}

impl Scatter<'_> {
    #[inline(always)]
    fn add(&mut self, axis: usize, idx: usize, v: f64) {
        self.pieces[axis][idx - self.first[axis]] += v;
    }
}

#[cfg(test)]
mod adjoint_tests {
    use super::*;

    fn field(grid: &Grid, seed: usize) -> Mac {
        let mut u = Mac::zeros(grid);
        for a in 0..3 {
            for (f, x) in u.c[a].iter_mut().enumerate() {
                // Offset so no sample is exactly 0: a zero own-component velocity puts the
                // backtrace on a lattice plane, where trilinear interpolation has a kink.
                *x = (((f * 7919 + a * 131 + seed * 31) % 101) as f64 / 50.0 - 1.0) * 0.8 + 0.0123;
            }
        }
        u
    }

    #[test]
    fn tangent_matches_central_differences() {
        let grid = Grid { n: [7, 6, 5], dx: 0.1 };
        let (u, du) = (field(&grid, 1), field(&grid, 2));
        let dt = 0.05;
        let t = advect_tangent(&u, &du, &grid, dt, None);
        let eps = 1e-6;
        let mut up = u.clone();
        let mut um = u.clone();
        for a in 0..3 {
            for f in 0..u.c[a].len() {
                up.c[a][f] += eps * du.c[a][f];
                um.c[a][f] -= eps * du.c[a][f];
            }
        }
        let (fp, fm) = (advect(&up, &grid, dt, None), advect(&um, &grid, dt, None));
        let mut worst: f64 = 0.0;
        for a in 0..3 {
            for f in 0..t.c[a].len() {
                let fd = (fp.c[a][f] - fm.c[a][f]) / (2.0 * eps);
                worst = worst.max((fd - t.c[a][f]).abs());
            }
        }
        // Trilinear interpolation is piecewise smooth; away from cell boundaries the central
        // difference is exact to O(ε²).
        assert!(worst < 1e-6, "tangent vs central differences: {worst:e}");
    }

    /// A mask keeping about two faces in three, in no particular pattern.
    fn some_faces(grid: &Grid) -> FaceMask {
        [0, 1, 2].map(|a| (0..grid.faces(a).len()).map(|f| (f * 5 + a) % 3 != 0).collect())
    }

    #[test]
    fn adjoint_is_the_transpose_of_the_tangent() {
        let grid = Grid { n: [7, 6, 5], dx: 0.1 };
        let (u, du, w) = (field(&grid, 1), field(&grid, 2), field(&grid, 3));
        let dt = 0.05;
        let mask = some_faces(&grid);
        for m in [None, Some(&mask)] {
            let lhs = advect_tangent(&u, &du, &grid, dt, m).dot(&w);
            let rhs = du.dot(&advect_adjoint(&u, &w, &grid, dt, m));
            assert!((lhs - rhs).abs() <= 1e-12 * lhs.abs().max(rhs.abs()), "{lhs} vs {rhs}");
        }
    }

    /// The scatter from traces found beforehand gives the bits of the one that traces each
    /// face as it goes, on a tall grid (blocks of both parities), with and without a mask,
    /// some adjoints zero, at a small and a large Δt.
    #[test]
    fn traced_adjoint_is_the_adjoint_bit_for_bit() {
        let grid = Grid { n: [5, 4, 37], dx: 0.1 };
        let (u, mut w) = (field(&grid, 5), field(&grid, 7));
        for a in 0..3 {
            w.c[a].iter_mut().step_by(7).for_each(|x| *x = 0.0);
        }
        let mask = some_faces(&grid);
        for dt in [0.05, 0.6] {
            for m in [None, Some(&mask)] {
                let plain = advect_adjoint(&u, &w, &grid, dt, m);
                let traces = AdvectionTraces::new(&u, &grid, dt, m);
                let mut traced = field(&grid, 9);
                advect_adjoint_traced(&traces, &w, &grid, &mut traced);
                for a in 0..3 {
                    let same = plain.c[a].iter().zip(&traced.c[a]);
                    assert!(same.clone().all(|(x, y)| x.to_bits() == y.to_bits()), "dt {dt}");
                    assert!(same.clone().any(|(x, _)| *x != 0.0));
                }
            }
        }
    }

    /// Tall grids, so the scatter runs in many blocks of both parities, at a Δt that moves a
    /// backtrace less than a slab and at one that moves it several: still the transpose, and
    /// the same bits on one thread as on two.
    #[test]
    fn blocked_adjoint_is_the_transpose_with_any_thread_count() {
        let grid = Grid { n: [5, 4, 37], dx: 0.1 };
        let (u, du, w) = (field(&grid, 5), field(&grid, 6), field(&grid, 7));
        let mask = some_faces(&grid);
        for dt in [0.05, 0.6] {
            let lhs = advect_tangent(&u, &du, &grid, dt, Some(&mask)).dot(&w);
            let run = |t: usize| {
                let pool = rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap();
                pool.install(|| advect_adjoint(&u, &w, &grid, dt, Some(&mask)))
            };
            let (one, two) = (run(1), run(2));
            let rhs = du.dot(&two);
            assert!((lhs - rhs).abs() <= 1e-12 * lhs.abs().max(rhs.abs()), "{lhs} vs {rhs}");
            for a in 0..3 {
                assert!(one.c[a].iter().zip(&two.c[a]).all(|(x, y)| x.to_bits() == y.to_bits()));
            }
        }
    }

    #[test]
    fn cross_faces_are_the_lattice_indices() {
        // The four faces by strides are those the lattice indexes, walls included.
        let grid = Grid { n: [7, 6, 5], dx: 0.1 };
        for axis in 0..3 {
            let lat = grid.faces(axis);
            for f in 0..lat.len() {
                let ijk = lat.ijk(f);
                for b in (0..3).filter(|&b| b != axis) {
                    let n = grid.n[axis];
                    let (a0, a1) = match ijk[axis] {
                        0 => (0, 0),
                        i if i >= n => (n - 1, n - 1),
                        i => (i - 1, i),
                    };
                    let mut want = Vec::new();
                    for ia in [a0, a1] {
                        for ib in [ijk[b], ijk[b] + 1] {
                            let mut q = ijk;
                            q[axis] = ia;
                            q[b] = ib;
                            want.push(grid.faces(b).index(q[0], q[1], q[2]));
                        }
                    }
                    assert_eq!(cross_faces(&grid, axis, ijk, b).to_vec(), want, "{axis} {f} {b}");
                }
            }
        }
    }

    #[test]
    fn face_velocity_is_the_trilinear_velocity_at_the_face() {
        // The four-face mean must be the interpolation the backtrace used to do, walls
        // (clamped samples) included.
        let grid = Grid { n: [7, 6, 5], dx: 0.1 };
        let u = field(&grid, 4);
        for a in 0..3 {
            let lat = grid.faces(a);
            for f in 0..lat.len() {
                let [i, j, k] = lat.ijk(f);
                let want = u.velocity(&grid, lat.position(i, j, k));
                let got = face_velocity(&u, &grid, a, [i, j, k], f);
                assert!((want - got).abs().max_element() < 1e-14, "axis {a} face {f}");
            }
        }
    }

    #[test]
    fn the_mask_only_skips_faces() {
        let grid = Grid { n: [7, 6, 5], dx: 0.1 };
        let u = field(&grid, 5);
        let mask = some_faces(&grid);
        let (all, some) = (advect(&u, &grid, 0.05, None), advect(&u, &grid, 0.05, Some(&mask)));
        for a in 0..3 {
            for f in 0..mask[a].len() {
                let want = if mask[a][f] { all.c[a][f] } else { 0.0 };
                assert_eq!(some.c[a][f], want);
            }
        }
    }
}
