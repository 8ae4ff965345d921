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
