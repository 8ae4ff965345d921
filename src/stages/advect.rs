//! Semi-Lagrangian advection of the velocity field (stage 1).
//!
//! Each face sample at `x_g` is traced back with one forward-Euler step through the current
//! field, `x_b = x_g − Δt·U(x_g)`, and takes the trilinear value of its own component there:
//! `u_new(x_g) = I(u, x_b)`. The paper picks forward Euler for the backtrace because its
//! derivative is simple: the map is `W(u)·u`, and its adjoint is `(W + ∂W/∂u·u)ᵀ` (eq. 4).

use crate::geometry::grid::{Grid, Mac};
use crate::math::Vec3;

/// Faces whose advected value the step reads, per axis (see [`needed_faces`]); `None` in the
/// functions below means every face.
pub type FaceMask = [Vec<bool>; 3];

/// The faces whose advected value the rest of the step reads: those of liquid cells (φ_L < 0
/// after extension into solids: the projection's faces) and those a body covers (the velocity correction mixes the fluid
/// velocity there with the body's). Every other face is overwritten by extrapolation or set
/// to zero before the step ends, so advecting it would be wasted work: with the mask, air
/// far from the liquid costs nothing here.
pub fn needed_faces(
    grid: &Grid,
    phi: &[f64],
    body_faces: &[crate::geometry::fractions::BodyFaces],
) -> FaceMask {
    let cells = grid.cells();
    let mut mask = [0, 1, 2].map(|a| vec![false; grid.faces(a).len()]);
    for (a, m) in mask.iter_mut().enumerate() {
        let lat = grid.faces(a);
        for (c, _) in phi.iter().enumerate().filter(|(_, p)| **p < 0.0) {
            let [i, j, k] = cells.ijk(c);
            m[lat.index(i, j, k)] = true;
            let mut hi = [i, j, k];
            hi[a] += 1;
            m[lat.index(hi[0], hi[1], hi[2])] = true;
        }
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
#[inline]
fn cross_faces(grid: &Grid, axis: usize, ijk: [usize; 3], b: usize) -> [usize; 4] {
    let lat = grid.faces(b);
    // Along `axis` the face sits half a cell from the component-b faces on either side.
    let n = grid.n[axis];
    let (a0, a1) = match ijk[axis] {
        0 => (0, 0),
        i if i >= n => (n - 1, n - 1),
        i => (i - 1, i),
    };
    let mut out = [0; 4];
    for (s, &ia) in [a0, a1].iter().enumerate() {
        for (t, ib) in [ijk[b], ijk[b] + 1].into_iter().enumerate() {
            let mut q = ijk;
            q[axis] = ia;
            q[b] = ib;
            out[2 * s + t] = lat.index(q[0], q[1], q[2]);
        }
    }
    out
}

/// The velocity at the centre of face `ijk` (flat index `f`) of component `axis`: its own
/// value and, for the other two components, the mean of the four nearest faces. The same
/// value as `u.velocity(grid, position)` at a fraction of the cost.
#[inline]
pub fn face_velocity(u: &Mac, grid: &Grid, axis: usize, ijk: [usize; 3], f: usize) -> Vec3 {
    let mut v = [0.0; 3];
    v[axis] = u.c[axis][f];
    for b in (0..3).filter(|&b| b != axis) {
        let q = cross_faces(grid, axis, ijk, b);
        v[b] = 0.25 * ((u.c[b][q[0]] + u.c[b][q[1]]) + (u.c[b][q[2]] + u.c[b][q[3]]));
    }
    crate::math::v3(v)
}

/// Transpose of [`face_velocity`]: adds `Σ_b coef_b · ∂v_b/∂u` into `out`.
#[inline]
fn face_velocity_adjoint(
    out: &mut Mac,
    grid: &Grid,
    axis: usize,
    ijk: [usize; 3],
    f: usize,
    coef: Vec3,
) {
    out.c[axis][f] += crate::math::comp(coef, axis);
    for b in (0..3).filter(|&b| b != axis) {
        let c = 0.25 * crate::math::comp(coef, b);
        if c != 0.0 {
            for q in cross_faces(grid, axis, ijk, b) {
                out.c[b][q] += c;
            }
        }
    }
}

/// Advects `u` through itself for `dt`. With a mask, faces outside it are left at zero.
pub fn advect(u: &Mac, grid: &Grid, dt: f64, mask: Option<&FaceMask>) -> Mac {
    let mut out = Mac::zeros(grid);
    advect_into(u, grid, dt, mask, &mut out);
    out
}

/// [`advect`] written over `out` (a field of the grid's size): every face is set.
pub fn advect_into(u: &Mac, grid: &Grid, dt: f64, mask: Option<&FaceMask>, out: &mut Mac) {
    for (axis, dst) in out.c.iter_mut().enumerate() {
        let lat = grid.faces(axis);
        let src = &u.c[axis];
        let m = mask.map(|m| &m[axis]);
        lat.fill_par(dst, |i, j, k| {
            let f = lat.index(i, j, k);
            if m.is_some_and(|m| !m[f]) {
                return 0.0;
            }
            let xb = lat.position(i, j, k) - dt * face_velocity(u, grid, axis, [i, j, k], f);
            lat.sample(src, xb)
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
/// [`advect_tangent`] with the same mask. A scatter, run in face order on one thread so it is
/// deterministic.
pub fn advect_adjoint(u: &Mac, adj: &Mac, grid: &Grid, dt: f64, mask: Option<&FaceMask>) -> Mac {
    let mut out = Mac::zeros(grid);
    for axis in 0..3 {
        let lat = grid.faces(axis);
        for g in 0..lat.len() {
            let a = adj.c[axis][g];
            if a == 0.0 || mask.is_some_and(|m| !m[axis][g]) {
                continue;
            }
            let ijk = lat.ijk(g);
            let xb =
                lat.position(ijk[0], ijk[1], ijk[2]) - dt * face_velocity(u, grid, axis, ijk, g);
            let sb = lat.stencil(xb);
            let mut grad = Vec3::ZERO;
            for c in 0..8 {
                out.c[axis][sb.idx[c]] += a * sb.w[c];
                grad += sb.dw[c] * u.c[axis][sb.idx[c]];
            }
            face_velocity_adjoint(&mut out, grid, axis, ijk, g, (-dt * a) * grad);
        }
    }
    out
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
