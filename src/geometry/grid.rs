//! The MAC grid: cells, faces and nodes as sample lattices, trilinear sampling, its
//! derivative in the sample point, and its transpose (a scatter).
//!
//! Layout: every lattice is stored x-fastest, z-slowest (`i + n0 * (j + n1 * k)`), so a
//! z-slab is a contiguous chunk and rayon can split a loop by slabs. Cell (i, j, k) is the
//! cube `[i, i+1]·dx × [j, j+1]·dx × [k, k+1]·dx`; the face lattice of axis `a` has one more
//! sample along `a` and sits on the cell faces normal to `a` (MAC staggering).

use crate::math::{v3, Vec3};
use rayon::prelude::*;

/// Marks "no such index" in compact index maps.
pub const NONE: u32 = u32::MAX;

/// Chunk length for deterministic parallel reductions: partial sums are formed over fixed
/// chunks and then added in order, so a sum never depends on the number of threads.
pub const REDUCE_CHUNK: usize = 4096;

/// The simulation grid: `n` cells of side `dx`, the domain `[0, n·dx]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Grid {
    /// Cells along x, y, z.
    pub n: [usize; 3],
    /// Cell side in metres.
    pub dx: f64,
}

impl Grid {
    /// Lattice of cell centres (pressure, liquid signed distance).
    pub fn cells(&self) -> Lattice {
        Lattice { n: self.n, off: [0.5; 3], dx: self.dx }
    }

    /// Calls `visit(cell, [i, j, k])` for every cell whose centre the box from `lo` to `hi`
    /// (m) may hold, within the tank: the cells from the one `lo` falls in to one past the
    /// one `hi` falls in, in lattice order.
    pub fn for_cells_in_box(&self, lo: Vec3, hi: Vec3, mut visit: impl FnMut(usize, [usize; 3])) {
        let lo = lo.to_array().map(|x| (x / self.dx).floor().max(0.0) as usize);
        let hi = hi.to_array().map(|x| (x / self.dx).ceil().max(0.0) as usize + 1);
        for k in lo[2]..self.n[2].min(hi[2]) {
            for j in lo[1]..self.n[1].min(hi[1]) {
                for i in lo[0]..self.n[0].min(hi[0]) {
                    visit(self.cell(i, j, k), [i, j, k]);
                }
            }
        }
    }

    /// Lattice of the faces normal to `axis` (velocity component `axis`).
    pub fn faces(&self, axis: usize) -> Lattice {
        let mut off = [0.5; 3];
        off[axis] = 0.0;
        Lattice { n: self.face_dims(axis), off, dx: self.dx }
    }

    /// Samples along each axis of the lattice of faces normal to `axis` (one more along it).
    #[inline]
    pub fn face_dims(&self, axis: usize) -> [usize; 3] {
        let mut n = self.n;
        n[axis] += 1;
        n
    }

    /// Lattice of cell corners (solid signed distance samples).
    pub fn nodes(&self) -> Lattice {
        Lattice { n: [self.n[0] + 1, self.n[1] + 1, self.n[2] + 1], off: [0.0; 3], dx: self.dx }
    }

    /// Number of cells.
    pub fn num_cells(&self) -> usize {
        self.n[0] * self.n[1] * self.n[2]
    }

    /// Domain extent in metres.
    pub fn size(&self) -> Vec3 {
        // Written out, as the maps below (a particle's every wall test asks for it).
        let [n0, n1, n2] = self.n;
        Vec3::new(n0 as f64 * self.dx, n1 as f64 * self.dx, n2 as f64 * self.dx)
    }

    /// Index of cell (i, j, k).
    #[inline]
    pub fn cell(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.n[0] * (j + self.n[1] * k)
    }

    /// The cells on the − and + side of face `f` of `axis`, `None` on the domain boundary.
    #[inline]
    pub fn face_cells(&self, axis: usize, f: [usize; 3]) -> (Option<usize>, Option<usize>) {
        let minus = (f[axis] > 0).then(|| {
            let mut c = f;
            c[axis] -= 1;
            self.cell(c[0], c[1], c[2])
        });
        let plus = (f[axis] < self.n[axis]).then(|| self.cell(f[0], f[1], f[2]));
        (minus, plus)
    }
}

/// A regular lattice of samples at `(index + off) · dx`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lattice {
    /// Samples along each axis.
    pub n: [usize; 3],
    /// Offset of sample 0 from the origin, in cells.
    pub off: [f64; 3],
    /// Spacing.
    pub dx: f64,
}

/// The eight samples and weights of a trilinear interpolation, and the weights' derivative
/// with respect to the sample point (zero along an axis where the point was clamped).
#[derive(Clone, Copy, Debug)]
pub struct Stencil {
    /// Flat indices of the 8 corners.
    pub idx: [usize; 8],
    /// Interpolation weights (sum to 1).
    pub w: [f64; 8],
    /// d w / d x for each corner.
    pub dw: [Vec3; 8],
}

/// A sample point's place along one axis of a lattice: the lower and upper sample indices
/// and the fraction between them.
type Located = (usize, usize, f64);

/// [`Located`] for the coordinate divided by the spacing `t`, on an axis of `n` samples at
/// `(i + off)·dx`, clamped to its ends: [`place`] without the derivative.
#[inline]
fn locate(t: f64, off: f64, n: usize) -> Located {
    let p = place(t - off, n, 1.0);
    (p.lo, p.hi, p.t)
}

/// Trilinear interpolation of `field` on a lattice of `n` samples at the place `at` along
/// each axis.
#[inline(always)]
fn trilinear(field: &[f64], n: [usize; 3], at: [Located; 3]) -> f64 {
    let [(i0, i1, tx), (j0, j1, ty), (k0, k1, tz)] = at;
    let (n0, n01) = (n[0], n[0] * n[1]);
    let row = |j: usize, k: usize| {
        let b = j * n0 + k * n01;
        field[b + i0] * (1.0 - tx) + field[b + i1] * tx
    };
    let plane = |k: usize| row(j0, k) * (1.0 - ty) + row(j1, k) * ty;
    plane(k0) * (1.0 - tz) + plane(k1) * tz
}

/// [`trilinear`] on a lattice of two samples or more along every axis (the face lattices of
/// a grid at least two cells across), where each upper index is the lower one plus one
/// ([`place`]): the corners are one base index and fixed offsets, each row a pair read with
/// one bounds check instead of two indices and two checks. The same products and sums in
/// the same order, so the same bits.
#[inline(always)]
fn trilinear_paired(field: &[f64], n: [usize; 3], at: [Located; 3]) -> f64 {
    let [(i0, _, tx), (j0, _, ty), (k0, _, tz)] = at;
    let (n0, n01) = (n[0], n[0] * n[1]);
    let row = |b: usize| {
        let r = &field[b..b + 2];
        r[0] * (1.0 - tx) + r[1] * tx
    };
    let plane = |b: usize| row(b) * (1.0 - ty) + row(b + n0) * ty;
    let base = i0 + j0 * n0 + k0 * n01;
    plane(base) * (1.0 - tz) + plane(base + n01) * tz
}

/// A sample point's place along one axis with the derivative of its fraction: the lower
/// and upper sample indices, the fraction between them, and d(fraction)/dx (0 where the
/// point is clamped to an end).
#[derive(Clone, Copy)]
struct Place {
    lo: usize,
    hi: usize,
    t: f64,
    live: f64,
}

/// ⌊g⌋ for `g` ≥ 0, 0 below (and for NaN), as `g as usize` gives it. Through i64: x86-64
/// converts an f64 to an i64 in one instruction, to a u64 in about ten (half the instructions
/// of a `place`); and an index back to f64 likewise.
#[inline(always)]
pub fn floor_index(g: f64) -> usize {
    (g as i64).max(0) as usize
}

/// [`Place`] of the point at `g` sample spacings from the first of `n` samples `dx` apart.
#[inline]
fn place(g: f64, n: usize, dx: f64) -> Place {
    // Index to f64 through i64 (one instruction; from usize, about six), as below.
    let top = (n - 1) as i64 as f64;
    // A clamp, not branches: the particles' velocity takes three places a lattice.
    let gc = g.clamp(0.0, top);
    let lo = floor_index(gc).min(n.saturating_sub(2));
    Place {
        lo,
        hi: (lo + 1).min(n - 1),
        t: gc - lo as i64 as f64,
        live: if g > 0.0 && g < top { 1.0 / dx } else { 0.0 },
    }
}

/// The trilinear stencil on a lattice of `n` samples at the places `p` along its axes.
#[inline(always)]
fn stencil_at(n: [usize; 3], p: [Place; 3]) -> Stencil {
    let mut st = Stencil { idx: [0; 8], w: [0.0; 8], dw: [Vec3::ZERO; 8] };
    for c in 0..8 {
        let bit = [c & 1, (c >> 1) & 1, (c >> 2) & 1];
        let mut f = [0.0; 3];
        let mut df = [0.0; 3];
        let mut ii = [0usize; 3];
        for a in 0..3 {
            if bit[a] == 1 {
                f[a] = p[a].t;
                df[a] = p[a].live;
                ii[a] = p[a].hi;
            } else {
                f[a] = 1.0 - p[a].t;
                df[a] = -p[a].live;
                ii[a] = p[a].lo;
            }
        }
        st.idx[c] = ii[0] + n[0] * (ii[1] + n[1] * ii[2]);
        st.w[c] = f[0] * f[1] * f[2];
        st.dw[c] = Vec3::new(df[0] * f[1] * f[2], f[0] * df[1] * f[2], f[0] * f[1] * df[2]);
    }
    st
}

/// The gradient, with respect to the point, of the trilinear interpolation of `field` (a
/// lattice of `n` samples) at the places `p`, by differences and lerps: the slopes along x
/// of the four rows, lerped in y and z; the differences along y of the rows' lerps, lerped
/// in z; the difference along z of the two planes' (a fifth of the arithmetic of
/// [`Stencil::value_and_gradient`]).
#[inline(always)]
fn trilinear_gradient(field: &[f64], n: [usize; 3], p: [Place; 3]) -> Vec3 {
    let (n0, n01) = (n[0], n[0] * n[1]);
    let [px, py, pz] = p;
    // A row's value and slope along x.
    let row = |j: usize, k: usize| {
        let b = j * n0 + k * n01;
        let (lo, hi) = (field[b + px.lo], field[b + px.hi]);
        (lo + px.t * (hi - lo), hi - lo)
    };
    // A plane's value, slope along x, difference along y.
    let plane = |k: usize| {
        let ((a0, s0), (a1, s1)) = (row(py.lo, k), row(py.hi, k));
        (a0 + py.t * (a1 - a0), s0 + py.t * (s1 - s0), a1 - a0)
    };
    let ((v0, x0, y0), (v1, x1, y1)) = (plane(pz.lo), plane(pz.hi));
    Vec3::new(
        (x0 + pz.t * (x1 - x0)) * px.live,
        (y0 + pz.t * (y1 - y0)) * py.live,
        (v1 - v0) * pz.live,
    )
}

/// The transpose of the trilinear interpolation at the places `p` on a lattice of `n`
/// samples: adds `c` times each corner's weight into `field`.
#[inline(always)]
fn trilinear_scatter(field: &mut [f64], n: [usize; 3], p: [Place; 3], c: f64) {
    let (n0, n01) = (n[0], n[0] * n[1]);
    let [px, py, pz] = p;
    for (k, wz) in [(pz.lo, 1.0 - pz.t), (pz.hi, pz.t)] {
        for (j, wy) in [(py.lo, 1.0 - py.t), (py.hi, py.t)] {
            let b = j * n0 + k * n01;
            let cw = c * wz * wy;
            field[b + px.lo] += cw * (1.0 - px.t);
            field[b + px.hi] += cw * px.t;
        }
    }
}

impl Stencil {
    /// The interpolated value of `field` and its gradient with respect to the point.
    #[inline(always)]
    pub fn value_and_gradient(&self, field: &[f64]) -> (f64, Vec3) {
        let mut v = 0.0;
        let mut g = Vec3::ZERO;
        for c in 0..8 {
            let f = field[self.idx[c]];
            v += self.w[c] * f;
            g += self.dw[c] * f;
        }
        (v, g)
    }
}

impl Lattice {
    /// Total number of samples.
    #[inline]
    pub fn len(&self) -> usize {
        self.n[0] * self.n[1] * self.n[2]
    }

    /// True when the lattice has no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Samples per z-slab.
    #[inline]
    pub fn slab(&self) -> usize {
        self.n[0] * self.n[1]
    }

    /// Flat index of sample (i, j, k).
    #[inline]
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.n[0] * (j + self.n[1] * k)
    }

    /// (i, j, k) of a flat index.
    #[inline]
    pub fn ijk(&self, idx: usize) -> [usize; 3] {
        let i = idx % self.n[0];
        let r = idx / self.n[0];
        [i, r % self.n[1], r / self.n[1]]
    }

    /// The flat index of the sample next to sample `idx` (at `ijk`) along `axis`, on its
    /// lower (`side` 0) or upper (`side` 1) side; None past the lattice's end.
    #[inline(always)]
    pub fn neighbour(
        &self,
        idx: usize,
        ijk: [usize; 3],
        axis: usize,
        side: usize,
    ) -> Option<usize> {
        let stride = [1, self.n[0], self.n[0] * self.n[1]][axis];
        if side == 0 {
            (ijk[axis] > 0).then(|| idx - stride)
        } else {
            (ijk[axis] + 1 < self.n[axis]).then(|| idx + stride)
        }
    }

    /// World position of sample (i, j, k).
    #[inline]
    pub fn position(&self, i: usize, j: usize, k: usize) -> Vec3 {
        // Through i64: see `place`.
        Vec3::new(
            (i as i64 as f64 + self.off[0]) * self.dx,
            (j as i64 as f64 + self.off[1]) * self.dx,
            (k as i64 as f64 + self.off[2]) * self.dx,
        )
    }

    /// The trilinear stencil at `x`. The point is clamped to the lattice's hull, so a sample
    /// outside the domain takes the nearest boundary value (and has zero derivative across
    /// the clamped axis). Always inlined, as [`Lattice::sample`] is: left as a call it returns
    /// its 320 bytes through memory, which the advection's adjoint pays for on every face.
    #[inline(always)]
    pub fn stencil(&self, x: Vec3) -> Stencil {
        // Written out, as in `sample_scaled`.
        let at = |a: usize, x: f64| place(x / self.dx - self.off[a], self.n[a], self.dx);
        stencil_at(self.n, [at(0, x.x), at(1, x.y), at(2, x.z)])
    }

    /// Lower corner index and fraction along `axis` (clamped) for the coordinate divided by
    /// the spacing, `t = x/dx`.
    #[inline]
    fn locate_scaled(&self, axis: usize, t: f64) -> Located {
        locate(t, self.off[axis], self.n[axis])
    }

    /// Trilinear interpolation of `field` at `x` (the same value as [`Lattice::stencil`]
    /// gives, without the derivative: this is the hot path of advection). Always inlined: the
    /// compiler otherwise leaves it a call from the advection's loop.
    #[inline(always)]
    pub fn sample(&self, field: &[f64], x: Vec3) -> f64 {
        self.sample_scaled(field, [x.x / self.dx, x.y / self.dx, x.z / self.dx])
    }

    /// [`Lattice::sample`] at the point whose coordinates divided by the spacing are `t`
    /// (the same bits: the three face lattices of a velocity share one division).
    #[inline(always)]
    pub fn sample_scaled(&self, field: &[f64], t: [f64; 3]) -> f64 {
        // Written out: as an array map this was left as a call (`try_map`) once `place` grew.
        let at = |a: usize| self.locate_scaled(a, t[a]);
        if self.n.iter().all(|&m| m > 1) {
            return trilinear_paired(field, self.n, [at(0), at(1), at(2)]);
        }
        trilinear(field, self.n, [at(0), at(1), at(2)])
    }

    /// Trilinear interpolation and its gradient with respect to `x`.
    #[inline]
    pub fn sample_grad(&self, field: &[f64], x: Vec3) -> (f64, Vec3) {
        self.stencil(x).value_and_gradient(field)
    }

    /// Fills `out` (one value per sample) in parallel over z-slabs.
    pub fn fill_par<F>(&self, out: &mut [f64], f: F)
    where
        F: Fn(usize, usize, usize) -> f64 + Sync,
    {
        assert_eq!(out.len(), self.len());
        let slab = self.slab().max(1);
        out.par_chunks_mut(slab).enumerate().for_each(|(k, chunk)| {
            for j in 0..self.n[1] {
                for i in 0..self.n[0] {
                    chunk[i + self.n[0] * j] = f(i, j, k);
                }
            }
        });
    }
}

/// A MAC velocity field: one array per component, on the face lattices.
#[derive(Clone, Debug, PartialEq)]
pub struct Mac {
    /// u, v, w.
    pub c: [Vec<f64>; 3],
}

/// The places of a point on the three face lattices, `[a][b]` along axis b of the faces
/// normal to `a`, for the point's coordinates over the spacing `t`: along axis b the faces
/// normal to b sit on the cell faces (offset 0, n + 1 samples) and the other two lattices on
/// the centres (offset ½, n), so two places an axis, `at(g, n)` for the point `g` spacings
/// from the first of `n` samples, serve all three (the same values as each lattice's own).
#[inline(always)]
fn face_places<T: Copy>(grid: &Grid, t: [f64; 3], at: impl Fn(f64, usize) -> T) -> [[T; 3]; 3] {
    // Written out: array maps here were left as calls (`try_map`) by the compiler in some
    // builds, a call per particle.
    let n = grid.n;
    let [f0, f1, f2] = [at(t[0], n[0] + 1), at(t[1], n[1] + 1), at(t[2], n[2] + 1)];
    let [c0, c1, c2] = [at(t[0] - 0.5, n[0]), at(t[1] - 0.5, n[1]), at(t[2] - 0.5, n[2])];
    [[f0, c1, c2], [c0, f1, c2], [c0, c1, f2]]
}

/// [`face_places`] with the derivative, for the stencils of the Jacobian and the transpose.
#[inline]
fn face_stencil_places(grid: &Grid, x: Vec3) -> [[Place; 3]; 3] {
    let t = [x.x / grid.dx, x.y / grid.dx, x.z / grid.dx];
    face_places(grid, t, |g, n| place(g, n, grid.dx))
}

/// [`Mac::velocity`] with what it derives from the grid taken once: for a loop over many
/// points (the particles' advection and displacement), where the compiler otherwise
/// recomputes each lattice's clamp bounds at every point. The same bits as
/// [`Mac::velocity`].
#[derive(Clone, Copy)]
pub struct MacSampler<'a> {
    mac: &'a Mac,
    grid: &'a Grid,
    /// Per axis, for the faces normal to it (`n + 1` samples) and the centres (`n`): the
    /// largest coordinate a place is clamped to, and the largest lower index.
    bounds: [[(f64, usize); 2]; 3],
    /// Whether every axis has two cells or more (the paired rows apply).
    paired: bool,
}

impl<'a> MacSampler<'a> {
    /// The sampler of `mac` on `grid`.
    pub fn new(mac: &'a Mac, grid: &'a Grid) -> MacSampler<'a> {
        // As `place` makes them, for `n` samples.
        let bound = |n: usize| ((n - 1) as i64 as f64, n.saturating_sub(2));
        let bounds = [0, 1, 2].map(|a| [bound(grid.n[a] + 1), bound(grid.n[a])]);
        MacSampler { mac, grid, bounds, paired: grid.n.iter().all(|&n| n > 1) }
    }

    /// The velocity at `x`: [`Mac::velocity`].
    #[inline(always)]
    pub fn velocity(&self, x: Vec3) -> Vec3 {
        if !self.paired {
            return self.mac.velocity(self.grid, x);
        }
        let dx = self.grid.dx;
        let t = [x.x / dx, x.y / dx, x.z / dx];
        // `locate` with the bounds taken once: `place`'s lower index and fraction.
        let at = |g: f64, (top, max_lo): (f64, usize)| -> Located {
            let gc = g.clamp(0.0, top);
            let lo = floor_index(gc).min(max_lo);
            (lo, lo + 1, gc - lo as i64 as f64)
        };
        let b = &self.bounds;
        let [f0, f1, f2] = [at(t[0], b[0][0]), at(t[1], b[1][0]), at(t[2], b[2][0])];
        let [c0, c1, c2] =
            [at(t[0] - 0.5, b[0][1]), at(t[1] - 0.5, b[1][1]), at(t[2] - 0.5, b[2][1])];
        let (c, grid) = (&self.mac.c, self.grid);
        Vec3::new(
            trilinear_paired(&c[0], grid.face_dims(0), [f0, c1, c2]),
            trilinear_paired(&c[1], grid.face_dims(1), [c0, f1, c2]),
            trilinear_paired(&c[2], grid.face_dims(2), [c0, c1, f2]),
        )
    }
}

impl Mac {
    /// The zero field on `grid`.
    pub fn zeros(grid: &Grid) -> Self {
        Mac { c: [0, 1, 2].map(|a| vec![0.0; grid.faces(a).len()]) }
    }

    /// Velocity at `x`, each component interpolated on its own face lattice.
    #[inline(always)]
    pub fn velocity(&self, grid: &Grid, x: Vec3) -> Vec3 {
        let t = [x.x / grid.dx, x.y / grid.dx, x.z / grid.dx];
        let [a0, a1, a2] = face_places(grid, t, |g, n| locate(g, 0.0, n));
        let c = &self.c;
        if grid.n.iter().all(|&n| n > 1) {
            return Vec3::new(
                trilinear_paired(&c[0], grid.face_dims(0), a0),
                trilinear_paired(&c[1], grid.face_dims(1), a1),
                trilinear_paired(&c[2], grid.face_dims(2), a2),
            );
        }
        Vec3::new(
            trilinear(&c[0], grid.face_dims(0), a0),
            trilinear(&c[1], grid.face_dims(1), a1),
            trilinear(&c[2], grid.face_dims(2), a2),
        )
    }

    /// Velocity at `x` and its Jacobian: row `a` is the gradient of component `a`. Always
    /// inlined, each component's stencil used where it is made: as a call it returned the
    /// three stencils (960 bytes) through memory, to be read back.
    #[inline(always)]
    pub fn velocity_jacobian(&self, grid: &Grid, x: Vec3) -> (Vec3, [Vec3; 3]) {
        let places = face_stencil_places(grid, x);
        let mut v = [0.0; 3];
        let mut j = [Vec3::ZERO; 3];
        for a in 0..3 {
            let st = stencil_at(grid.face_dims(a), places[a]);
            (v[a], j[a]) = st.value_and_gradient(&self.c[a]);
        }
        (v3(v), j)
    }

    /// The velocity's Jacobian at `x` (as [`Mac::velocity_jacobian`]'s, to rounding): row `a`
    /// the gradient of component `a`.
    #[inline(always)]
    pub fn velocity_gradient(&self, grid: &Grid, x: Vec3) -> [Vec3; 3] {
        let places = face_stencil_places(grid, x);
        [0, 1, 2].map(|a| trilinear_gradient(&self.c[a], grid.face_dims(a), places[a]))
    }

    /// [`Mac::velocity_gradient`] at `x`, and [`Mac::scatter_velocity`] of `coef` at `x` into
    /// `into`, from one set of places (the same bits as the two calls).
    #[inline(always)]
    pub fn gradient_and_scatter(
        &self,
        grid: &Grid,
        x: Vec3,
        coef: Vec3,
        into: &mut Mac,
    ) -> [Vec3; 3] {
        let places = face_stencil_places(grid, x);
        let mut j = [Vec3::ZERO; 3];
        for (a, c) in coef.to_array().into_iter().enumerate() {
            let n = grid.face_dims(a);
            j[a] = trilinear_gradient(&self.c[a], n, places[a]);
            if c != 0.0 {
                trilinear_scatter(&mut into.c[a], n, places[a], c);
            }
        }
        j
    }

    /// Transpose of [`Mac::velocity`] in the field: adds `coef_a · ∂v_a(x)/∂u` into `self`
    /// (component a's trilinear weights at `x`, times `coef_a`).
    #[inline]
    pub fn scatter_velocity(&mut self, grid: &Grid, x: Vec3, coef: Vec3) {
        let places = face_stencil_places(grid, x);
        for (a, c) in coef.to_array().into_iter().enumerate() {
            if c != 0.0 {
                trilinear_scatter(&mut self.c[a], grid.face_dims(a), places[a], c);
            }
        }
    }

    /// Largest |component| over all faces (a cheap bound used in reports).
    pub fn max_abs(&self) -> f64 {
        self.c.iter().map(|c| max_abs(c)).fold(0.0f64, f64::max)
    }

    /// Largest |component| over all faces, NaN when one is NaN: the check that a state is
    /// finite and in range, one pass for both.
    pub fn max_abs_or_nan(&self) -> f64 {
        let (most, nan) = self
            .c
            .iter()
            .map(|c| max_abs_and_nan(c))
            .fold((0.0f64, false), |(m, n), (a, b)| (m.max(a), n | b));
        if nan {
            f64::NAN
        } else {
            most
        }
    }

    /// True when every component is finite.
    pub fn is_finite(&self) -> bool {
        self.c.iter().all(|c| c.iter().all(|x| x.is_finite()))
    }

    /// Euclidean inner product over all faces.
    pub fn dot(&self, other: &Mac) -> f64 {
        (0..3).map(|a| dot(&self.c[a], &other.c[a])).sum()
    }
}

/// Largest |x| over `v` (0 when empty; NaN ignored, as `f64::max` ignores it), on two
/// threads when long: a maximum does not depend on the order it is taken in.
pub fn max_abs(v: &[f64]) -> f64 {
    max_abs_and_nan(v).0
}

/// Largest |x| over `v` (NaN ignored) and whether some x is NaN: in pieces of
/// [`crate::math::par::MIN_LEN`], each folded in four lanes the compiler vectorises (a fold
/// of one element at a time through rayon's iterator is not, and took about four times as
/// long).
fn max_abs_and_nan(v: &[f64]) -> (f64, bool) {
    let piece = |v: &[f64]| {
        let (mut most, mut nan) = ([0.0f64; 4], [false; 4]);
        let quads = v.chunks_exact(4);
        let rest = quads.remainder();
        for q in quads {
            for l in 0..4 {
                most[l] = most[l].max(q[l].abs());
                nan[l] |= q[l].is_nan();
            }
        }
        let mut m = most.iter().fold(0.0f64, |a, b| a.max(*b));
        let mut n = nan.contains(&true);
        for x in rest {
            m = m.max(x.abs());
            n |= x.is_nan();
        }
        (m, n)
    };
    v.par_chunks(crate::math::par::MIN_LEN)
        .map(piece)
        .reduce(|| (0.0, false), |(m, n), (a, b)| (m.max(a), n | b))
}

/// Deterministic parallel dot product: fixed chunks, partial sums added in order.
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    debug_assert_eq!(a.len(), b.len());
    let parts: Vec<f64> = a
        .par_chunks(REDUCE_CHUNK)
        .zip(b.par_chunks(REDUCE_CHUNK))
        .map(|(x, y)| x.iter().zip(y).map(|(p, q)| p * q).sum::<f64>())
        .collect();
    parts.iter().sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid() -> Grid {
        Grid { n: [5, 4, 3], dx: 0.25 }
    }

    #[test]
    fn neighbours_are_the_samples_one_step_away_inside_the_lattice() {
        for lat in [grid().cells(), grid().faces(1)] {
            for idx in 0..lat.len() {
                let ijk = lat.ijk(idx);
                for (axis, side) in (0..3).flat_map(|a| [(a, 0), (a, 1)]) {
                    let q = (ijk[axis] + 2 * side).checked_sub(1).filter(|&q| q < lat.n[axis]);
                    let want = q.map(|q| {
                        let mut p = ijk;
                        p[axis] = q;
                        lat.index(p[0], p[1], p[2])
                    });
                    assert_eq!(lat.neighbour(idx, ijk, axis, side), want, "{ijk:?} {axis} {side}");
                }
            }
        }
    }

    #[test]
    fn trilinear_reproduces_linear_fields() {
        // Trilinear interpolation is exact for affine functions inside the hull.
        let g = grid();
        for axis in 0..3 {
            let lat = g.faces(axis);
            let mut f = vec![0.0; lat.len()];
            lat.fill_par(&mut f, |i, j, k| {
                let p = lat.position(i, j, k);
                1.0 + 2.0 * p.x - 3.0 * p.y + 0.5 * p.z
            });
            let x = Vec3::new(0.61, 0.43, 0.37);
            let (val, grad) = lat.sample_grad(&f, x);
            assert!((val - (1.0 + 2.0 * x.x - 3.0 * x.y + 0.5 * x.z)).abs() < 1e-12);
            assert!((grad - Vec3::new(2.0, -3.0, 0.5)).length() < 1e-12);
        }
    }

    /// The paired reads (`trilinear_paired`: `Mac::velocity`, `MacSampler`,
    /// `Lattice::sample`) give the general reads' bits, inside the grid and clamped outside
    /// it; a grid one cell thick along an axis takes the general reads.
    #[test]
    fn paired_reads_are_the_general_reads_bit_for_bit() {
        for g in [grid(), Grid { n: [5, 1, 3], dx: 0.25 }] {
            let mut mac = Mac::zeros(&g);
            for (a, c) in mac.c.iter_mut().enumerate() {
                for (f, v) in c.iter_mut().enumerate() {
                    *v = ((f * 7919 + a * 104_729) % 1013) as f64 / 97.0 - 5.0;
                }
            }
            let sampler = MacSampler::new(&mac, &g);
            let bits = |v: Vec3| v.to_array().map(f64::to_bits);
            for s in 0..500usize {
                let r = |k: usize| ((s * 7 + k * 13).wrapping_mul(2_654_435_761) % 1000) as f64;
                // From a fifth of the tank below it to a fifth above.
                let x = (Vec3::new(r(1), r(2), r(3)) * 1.4e-3 - 0.2) * g.size();
                let t = [x.x / g.dx, x.y / g.dx, x.z / g.dx];
                let at = face_places(&g, t, |q, n| locate(q, 0.0, n));
                let general = Vec3::new(
                    trilinear(&mac.c[0], g.face_dims(0), at[0]),
                    trilinear(&mac.c[1], g.face_dims(1), at[1]),
                    trilinear(&mac.c[2], g.face_dims(2), at[2]),
                );
                assert_eq!(bits(mac.velocity(&g, x)), bits(general), "{x}");
                assert_eq!(bits(sampler.velocity(x)), bits(general), "{x}");
                let lat = g.faces(1);
                let places = [0, 1, 2].map(|a| lat.locate_scaled(a, t[a]));
                let want = trilinear(&mac.c[1], lat.n, places);
                assert_eq!(lat.sample(&mac.c[1], x).to_bits(), want.to_bits(), "{x}");
            }
        }
    }

    #[test]
    fn sample_gradient_matches_central_differences() {
        let g = grid();
        let lat = g.cells();
        let f: Vec<f64> = (0..lat.len()).map(|i| ((i * 37) % 11) as f64 * 0.3).collect();
        let x = Vec3::new(0.52, 0.33, 0.41);
        let (_, grad) = lat.sample_grad(&f, x);
        let h = 1e-6;
        for a in 0..3 {
            let e = crate::math::unit(a) * h;
            let fd = (lat.sample(&f, x + e) - lat.sample(&f, x - e)) / (2.0 * h);
            assert!((fd - crate::math::comp(grad, a)).abs() < 1e-7, "axis {a}: {fd} vs {grad}");
        }
    }

    #[test]
    fn fast_sample_matches_stencil() {
        let g = grid();
        let lat = g.faces(2);
        let f: Vec<f64> = (0..lat.len()).map(|i| ((i * 31) % 7) as f64).collect();
        for x in [Vec3::new(0.3, 0.2, 0.1), Vec3::new(-1.0, 0.5, 9.0), Vec3::new(1.24, 0.99, 0.74)]
        {
            let (v, _) = lat.sample_grad(&f, x);
            assert!((lat.sample(&f, x) - v).abs() < 1e-13);
        }
    }

    #[test]
    fn velocity_is_each_lattice_sampled() {
        // The velocity's shared places along each axis give the bits of each face lattice's
        // own sample, inside, on the ends and beyond them (clamped); so does the Jacobian.
        // The lerped gradient and the transpose are the stencil's to rounding.
        let g = grid();
        let u = Mac {
            c: [0, 1, 2].map(|a| {
                (0..g.faces(a).len()).map(|i| ((i * 29 + 7 * a) % 13) as f64 * 0.37).collect()
            }),
        };
        let points = (0..400).map(|i| {
            let h = |s: u64| ((i as u64 ^ s).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40) as f64;
            let size = g.size();
            Vec3::new(h(1) / (1u64 << 24) as f64 * 1.4 - 0.2, h(2) / (1u64 << 24) as f64, 0.0)
                * Vec3::new(size.x, size.y, 0.0)
                + Vec3::new(0.0, 0.0, (i % 7) as f64 * size.z / 5.0 - 0.1)
        });
        for x in points.chain([Vec3::ZERO, g.size(), Vec3::new(0.125, 0.25, 0.375)]) {
            let v = u.velocity(&g, x);
            let (vj, j) = u.velocity_jacobian(&g, x);
            let coef = Vec3::new(0.3, -1.7, 2.9);
            let mut scattered = Mac::zeros(&g);
            scattered.scatter_velocity(&g, x, coef);
            for a in 0..3 {
                let lat = g.faces(a);
                let own = lat.sample(&u.c[a], x);
                assert_eq!(crate::math::comp(v, a).to_bits(), own.to_bits(), "{x:?} axis {a}");
                let (own, grad) = lat.sample_grad(&u.c[a], x);
                assert_eq!(crate::math::comp(vj, a).to_bits(), own.to_bits(), "{x:?} axis {a}");
                assert_eq!(j[a].to_array().map(f64::to_bits), grad.to_array().map(f64::to_bits));
                // The lerps' gradient and the transpose: the stencil's to rounding (values
                // up to 4.44, a few operations).
                let lerped = u.velocity_gradient(&g, x)[a];
                let most = 16.0 * f64::EPSILON * 4.44 / g.dx;
                assert!((lerped - grad).abs().max_element() <= most, "{lerped} against {grad}");
                let s = lat.stencil(x);
                let mut own = vec![0.0; lat.len()];
                for k in 0..8 {
                    own[s.idx[k]] += crate::math::comp(coef, a) * s.w[k];
                }
                let most = 8.0 * f64::EPSILON * 2.9;
                assert!(own.iter().zip(&scattered.c[a]).all(|(p, q)| (p - q).abs() <= most));
            }
            // Together from one set of places: the same bits as apart.
            let mut together = Mac::zeros(&g);
            let j = u.gradient_and_scatter(&g, x, coef, &mut together);
            assert_eq!(j, u.velocity_gradient(&g, x));
            assert_eq!(together, scattered);
        }
    }

    #[test]
    fn max_abs_is_the_serial_maximum() {
        // Long enough to split; the largest magnitude negative, a NaN ignored.
        let mut v: Vec<f64> = (0..100_000).map(|i| ((i * 7919) % 1000) as f64 * 1e-3).collect();
        v[73_001] = -3.5;
        v[12] = f64::NAN;
        assert_eq!(max_abs(&v), 3.5);
        assert_eq!(max_abs(&v), v.iter().fold(0.0f64, |m, x| m.max(x.abs())));
        assert_eq!(max_abs(&[]), 0.0);
    }

    #[test]
    fn max_abs_or_nan_sees_a_nan_anywhere() {
        let g = Grid { n: [40, 30, 20], dx: 0.1 };
        let mut u = Mac::zeros(&g);
        u.c[1][777] = -2.5;
        u.c[2][5] = f64::INFINITY;
        assert_eq!(u.max_abs_or_nan(), f64::INFINITY);
        u.c[2][5] = 1.0;
        assert_eq!(u.max_abs_or_nan(), 2.5);
        // In a remainder past the last four, and in the middle of a piece.
        for (a, f) in [(0, g.faces(0).len() - 1), (2, 9_001)] {
            let mut v = u.clone();
            v.c[a][f] = f64::NAN;
            assert!(v.max_abs_or_nan().is_nan(), "axis {a} face {f}");
            assert_eq!(v.max_abs(), 2.5);
        }
    }

    #[test]
    fn ijk_inverts_index() {
        let lat = grid().faces(1);
        for idx in 0..lat.len() {
            let [i, j, k] = lat.ijk(idx);
            assert_eq!(lat.index(i, j, k), idx);
        }
    }
}
