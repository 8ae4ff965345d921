//! The solid fraction of a tetrahedron and of a box from the signed distance at their
//! corners, in closed form for a distance linear on each tetrahedron, and the snap that
//! makes round-off dust 0 or 1. Generic over [`Scalar`], so dual numbers carry derivatives.

use crate::math::dual::Scalar;

/// Fraction of a tetrahedron's volume where the linear interpolant of its vertex values is
/// negative. It depends on the values only (affine invariance), so their order is free.
/// Generic over [`Scalar`] so it also gives derivatives (see `dual.rs`).
#[inline]
pub fn tet_fraction_inside<T: Scalar>(v: [T; 4]) -> T {
    let mut v = v;
    v.sort_by(|x, y| x.val().total_cmp(&y.val()));
    let [a, b, c, d] = v;
    let one = T::cst(1.0);
    if d.val() < 0.0 {
        one
    } else if a.val() >= 0.0 {
        T::cst(0.0)
    } else if b.val() >= 0.0 {
        // One vertex inside: a corner tetrahedron.
        a * a * a / ((a - b) * (a - c) * (a - d))
    } else if c.val() < 0.0 {
        // One vertex outside.
        one - d * d * d / ((d - a) * (d - b) * (d - c))
    } else {
        // Two inside (a, b), two outside (c, d): a wedge. In the unit simplex with a at the
        // origin and b, c, d on the axes e1, e2, e3, the wedge has vertices v0, v1 and the
        // four edge crossings; split it into three tetrahedra (volumes relative to 1/6).
        let z = T::cst(0.0);
        let s = a / (a - c);
        let t = a / (a - d);
        let u = b / (b - c);
        let w = b / (b - d);
        let p02 = [z, s, z];
        let p03 = [z, z, t];
        let p12 = [one - u, u, z];
        let p13 = [one - w, z, w];
        let v1 = [one, z, z];
        let det = |o: [T; 3], x: [T; 3], y: [T; 3], q: [T; 3]| {
            let e = |p: [T; 3]| [p[0] - o[0], p[1] - o[1], p[2] - o[2]];
            let (x, y, q) = (e(x), e(y), e(q));
            (x[0] * (y[1] * q[2] - y[2] * q[1]) - x[1] * (y[0] * q[2] - y[2] * q[0])
                + x[2] * (y[0] * q[1] - y[1] * q[0]))
                .abs()
        };
        det([z; 3], p02, p03, v1) + det(p02, p03, v1, p13) + det(p02, v1, p12, p13)
    }
}

/// Fraction of a box's volume inside, from its 8 corner values indexed `x + 2y + 4z`
/// (bits along the world axes). The box is split into 24 congruent tetrahedra (box centre,
/// a face centre, an edge of that face), with the centre values the means of the corners,
/// and φ linear on each. The split has all the symmetries of the cube, so a mirror-symmetric
/// body gets mirror-symmetric fractions (a 6-tetrahedron Kuhn split favours one diagonal and
/// gave a symmetric floating box a spurious torque).
#[inline]
pub fn box_fraction_inside<T: Scalar>(c: [T; 8]) -> T {
    // Most boxes a body's bounding box covers lie wholly on one side of its surface; every
    // tetrahedron would then give exactly 1 (all inside) or 0, constants.
    if c.iter().all(|x| x.val() < 0.0) {
        return T::cst(1.0);
    }
    if c.iter().all(|x| x.val() >= 0.0) {
        return T::cst(0.0);
    }
    let mut centre = T::cst(0.0);
    for x in c {
        centre = centre + x;
    }
    let centre = centre / T::cst(8.0);
    let mut sum = T::cst(0.0);
    for axis in 0..3 {
        let (b, d) = ((axis + 1) % 3, (axis + 2) % 3);
        for side in 0..2 {
            // The face's corners in cyclic order.
            let corner = |u: usize, v: usize| c[(side << axis) | (u << b) | (v << d)];
            let ring = [corner(0, 0), corner(1, 0), corner(1, 1), corner(0, 1)];
            let fc = (ring[0] + ring[1] + ring[2] + ring[3]) * T::cst(0.25);
            for e in 0..4 {
                sum = sum + tet_fraction_inside([centre, fc, ring[e], ring[(e + 1) % 4]]);
            }
        }
    }
    sum / T::cst(24.0)
}

/// Fractions within 1e-9 of 0 or 1 are 0 or 1: round-off dust (a face inside a body came out
/// at 2e-12 on one side of a mirror-symmetric scene and 0 on the other) must not make a face
/// a pressure unknown's only, nearly closed, opening. The threshold is a discontinuity of
/// the step in the body's pose, so it sits far below anything a gradient check resolves. A
/// snapped fraction is a constant (no derivative).
#[inline]
pub fn snap<T: Scalar>(f: T) -> T {
    let v = f.val();
    if v < 1e-9 {
        T::cst(0.0)
    } else if v > 1.0 - 1e-9 {
        T::cst(1.0)
    } else {
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tet_fraction_cases_are_consistent() {
        assert!((tet_fraction_inside([-1.0, 1.0, 1.0, 1.0]) - 0.125).abs() < 1e-15);
        assert!((tet_fraction_inside([-1.0, -1.0, 1.0, 1.0]) - 0.5).abs() < 1e-14);
        assert!((tet_fraction_inside([1.0, -1.0, -1.0, -1.0]) - 0.875).abs() < 1e-15);
        // Continuity across the case boundaries: a value crossing zero changes little.
        for v in [[-0.3, -1e-12, 0.4, 0.9], [-0.3, 1e-12, 0.4, 0.9], [-0.3, -0.2, 0.4, 1e-12]] {
            let w = v.map(|x: f64| if x.abs() < 1e-9 { 0.0 } else { x });
            assert!((tet_fraction_inside(v) - tet_fraction_inside(w)).abs() < 1e-9, "{v:?}");
        }
    }

    #[test]
    fn box_fraction_of_a_plane_is_exact_in_any_direction() {
        // φ linear: the per-tet rule is exact. Axis-aligned planes cut off their offset.
        for &h in &[0.0, 0.2, 0.5, 0.77, 1.0] {
            for axis in 0..3 {
                let c: [f64; 8] = std::array::from_fn(|i| ((i >> axis) & 1) as f64 - h);
                assert!((box_fraction_inside(c) - h).abs() < 1e-14, "axis {axis} h {h}");
            }
        }
        // The oblique plane x + y + z = 1.5 halves the box by symmetry; x + y + z = 0.5
        // cuts off the corner tetrahedron of volume 1/48.
        let plane = |c0: f64| -> [f64; 8] {
            std::array::from_fn(|i| ((i & 1) + ((i >> 1) & 1) + ((i >> 2) & 1)) as f64 - c0)
        };
        assert!((box_fraction_inside(plane(1.5)) - 0.5).abs() < 1e-14);
        assert!((box_fraction_inside(plane(0.5)) - 1.0 / 48.0).abs() < 1e-14);
    }

    #[test]
    fn fraction_is_continuous_in_corner_values() {
        // Moving one corner through zero changes the fraction continuously.
        let f = |t: f64| box_fraction_inside([t, 0.3, 0.5, -0.2, 0.1, -0.4, 0.6, 0.2]);
        for &t in &[-1e-9, 0.0, 1e-9] {
            assert!((f(t) - f(0.0)).abs() < 1e-8);
        }
    }
}
