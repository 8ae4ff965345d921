//! Semi-Lagrangian advection of the velocity field (stage 1).
//!
//! Each face sample at `x_g` is traced back with one forward-Euler step through the current
//! field, `x_b = x_g − Δt·U(x_g)`, and takes the trilinear value of its own component there:
//! `u_new(x_g) = I(u, x_b)`. The paper picks forward Euler for the backtrace because its
//! derivative is simple: the map is `W(u)·u`, and its adjoint is `(W + ∂W/∂u·u)ᵀ` (eq. 4).

use crate::grid::{Grid, Mac};

/// Advects `u` through itself for `dt`.
pub fn advect(u: &Mac, grid: &Grid, dt: f64) -> Mac {
    let mut out = Mac::zeros(grid);
    for (axis, dst) in out.c.iter_mut().enumerate() {
        let lat = grid.faces(axis);
        let src = &u.c[axis];
        lat.fill_par(dst, |i, j, k| {
            let xg = lat.position(i, j, k);
            let xb = xg - dt * u.velocity(grid, xg);
            lat.sample(src, xb)
        });
    }
    out
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
        let out = advect(&u, &grid, 0.1);
        for a in 0..3 {
            for (x, y) in out.c[a].iter().zip(&u.c[a]) {
                assert!((x - y).abs() < 1e-14);
            }
        }
    }
}

/// Tangent of [`advect`] at `u` in direction `du`:
/// `δu_new(x_g) = I(δu, x_b) − Δt·∇I(u, x_b)·δU(x_g)`, with `x_b = x_g − Δt·U(x_g)`.
pub fn advect_tangent(u: &Mac, du: &Mac, grid: &Grid, dt: f64) -> Mac {
    let mut out = Mac::zeros(grid);
    for (axis, dst) in out.c.iter_mut().enumerate() {
        let lat = grid.faces(axis);
        lat.fill_par(dst, |i, j, k| {
            let xg = lat.position(i, j, k);
            let xb = xg - dt * u.velocity(grid, xg);
            let (_, grad) = lat.sample_grad(&u.c[axis], xb);
            let dvel = du.velocity(grid, xg);
            lat.sample(&du.c[axis], xb) - dt * grad.dot(dvel)
        });
    }
    out
}

/// Adjoint of [`advect`] at `u`: `(W + ∂W/∂u·u)ᵀ·adj` (paper, eq. 4), the exact transpose of
/// [`advect_tangent`]. A scatter, run in face order on one thread so it is deterministic.
pub fn advect_adjoint(u: &Mac, adj: &Mac, grid: &Grid, dt: f64) -> Mac {
    let mut out = Mac::zeros(grid);
    let lats = [grid.faces(0), grid.faces(1), grid.faces(2)];
    for axis in 0..3 {
        let lat = lats[axis];
        for g in 0..lat.len() {
            let a = adj.c[axis][g];
            if a == 0.0 {
                continue;
            }
            let [i, j, k] = lat.ijk(g);
            let xg = lat.position(i, j, k);
            let xb = xg - dt * u.velocity(grid, xg);
            let sb = lat.stencil(xb);
            let mut grad = crate::math::Vec3::ZERO;
            for c in 0..8 {
                out.c[axis][sb.idx[c]] += a * sb.w[c];
                grad += sb.dw[c] * u.c[axis][sb.idx[c]];
            }
            let coef = (-dt * a) * grad;
            for (comp, l) in lats.iter().enumerate() {
                let cc = crate::math::comp(coef, comp);
                if cc == 0.0 {
                    continue;
                }
                let sg = l.stencil(xg);
                for c in 0..8 {
                    out.c[comp][sg.idx[c]] += cc * sg.w[c];
                }
            }
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
        let t = advect_tangent(&u, &du, &grid, dt);
        let eps = 1e-6;
        let mut up = u.clone();
        let mut um = u.clone();
        for a in 0..3 {
            for f in 0..u.c[a].len() {
                up.c[a][f] += eps * du.c[a][f];
                um.c[a][f] -= eps * du.c[a][f];
            }
        }
        let (fp, fm) = (advect(&up, &grid, dt), advect(&um, &grid, dt));
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

    #[test]
    fn adjoint_is_the_transpose_of_the_tangent() {
        let grid = Grid { n: [7, 6, 5], dx: 0.1 };
        let (u, du, w) = (field(&grid, 1), field(&grid, 2), field(&grid, 3));
        let dt = 0.05;
        let lhs = advect_tangent(&u, &du, &grid, dt).dot(&w);
        let rhs = du.dot(&advect_adjoint(&u, &w, &grid, dt));
        assert!((lhs - rhs).abs() <= 1e-12 * lhs.abs().max(rhs.abs()), "{lhs} vs {rhs}");
    }
}
