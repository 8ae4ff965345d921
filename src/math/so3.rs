//! The rotation group's charts, in one place: the world-frame tangent q → exp(θ)·q in which
//! orientation gradients are given, and the rotation-vector chart q = exp(r)·q₀ in which
//! L-BFGS sees an orientation.

use super::{Rotation, Vec3};

/// ∂L/∂θ in the world-frame tangent δq = ½·[0, δθ]⊗q, from an adjoint ∂L/∂q in the
/// quaternion embedding (the transpose of that map).
pub fn tangent_gradient(q: Rotation, qbar: Rotation) -> Vec3 {
    let t = qbar * q.conjugate();
    Vec3::new(t.x, t.y, t.z) * 0.5
}

/// The adjoint in the quaternion embedding whose tangent part is `g` = ∂L/∂θ (the inverse of
/// [`tangent_gradient`] on the tangent space): 2·[0, g]⊗q.
pub fn from_tangent_gradient(q: Rotation, g: Vec3) -> Rotation {
    (Rotation::from_xyzw(g.x, g.y, g.z, 0.0) * q) * 2.0
}

/// The rotation vector r with q = exp(r)·q₀ (the short way round).
pub fn log_chart(q: Rotation, q0: Rotation) -> Vec3 {
    let mut r = q * q0.inverse();
    if r.w < 0.0 {
        r = -r;
    }
    r.to_scaled_axis()
}

/// exp(r)·q₀, normalised.
pub fn exp_chart(r: Vec3, q0: Rotation) -> Rotation {
    (Rotation::from_scaled_axis(r) * q0).normalize()
}

/// The gradient in the chart's coordinate r from the tangent gradient `g` at exp(r)·q₀:
/// J_l(r)ᵀ·g.
pub fn chart_gradient(r: Vec3, g: Vec3) -> Vec3 {
    let j = left_jacobian(r.to_array());
    let g = g.to_array();
    Vec3::from_array(std::array::from_fn(|c| (0..3).map(|rr| j[rr][c] * g[rr]).sum()))
}

/// The left Jacobian of SO(3) at r: exp(r + δ) ≈ exp(J_l(r)·δ)·exp(r) (Barfoot, State
/// Estimation for Robotics, eq. 7.77a).
pub fn left_jacobian(r: [f64; 3]) -> [[f64; 3]; 3] {
    let t2 = r.iter().map(|x| x * x).sum::<f64>();
    let t = t2.sqrt();
    // (1 − cos θ)/θ² and (θ − sin θ)/θ³, by their series near 0.
    let (a, b) = if t < 1e-4 {
        (0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0)
    } else {
        ((1.0 - t.cos()) / t2, (t - t.sin()) / (t2 * t))
    };
    let k = [[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]];
    let mut j = [[0.0; 3]; 3];
    for (i, row) in j.iter_mut().enumerate() {
        for (c, e) in row.iter_mut().enumerate() {
            let k2: f64 = (0..3).map(|m| k[i][m] * k[m][c]).sum();
            *e = f64::from(u8::from(i == c)) + a * k[i][c] + b * k2;
        }
    }
    j
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::{comp, v3};

    /// exp(r + δ) = exp(J_l(r)·δ)·exp(r) to first order, checked by central differences.
    #[test]
    fn left_jacobian_matches_finite_differences() {
        let r = [0.3, -0.7, 0.4];
        let j = left_jacobian(r);
        let exp = |a: [f64; 3]| Rotation::from_scaled_axis(v3(a));
        let h = 1e-6;
        for c in 0..3 {
            let mut rp = r;
            let mut rm = r;
            rp[c] += h;
            rm[c] -= h;
            // The world-frame rotation between exp(r ± h e_c) and exp(r).
            let dp = (exp(rp) * exp(r).inverse()).to_scaled_axis();
            let dm = (exp(rm) * exp(r).inverse()).to_scaled_axis();
            let col = (dp - dm) / (2.0 * h);
            for (i, row) in j.iter().enumerate() {
                let err = (row[c] - comp(col, i)).abs();
                assert!(err < 1e-8, "J[{i}][{c}] = {} vs {}", row[c], comp(col, i));
            }
        }
        assert_eq!(left_jacobian([0.0; 3]), [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
    }

    #[test]
    fn tangent_gradient_round_trips() {
        let q = Rotation::from_axis_angle(Vec3::new(1.0, 2.0, -1.0).normalize(), 1.3);
        let g = Vec3::new(0.4, -0.7, 1.9);
        let back = tangent_gradient(q, from_tangent_gradient(q, g));
        assert!((back - g).length() < 1e-12);
    }

    #[test]
    fn chart_round_trips() {
        let q0 = Rotation::from_axis_angle(Vec3::new(0.2, 1.0, 0.3).normalize(), 0.4);
        let r = Vec3::new(0.3, -0.2, 0.5);
        assert!((log_chart(exp_chart(r, q0), q0) - r).length() < 1e-14);
    }
}
