//! Face fractions from signed-distance samples.
//!
//! A face's solid fraction is the part of its area where the solid's signed distance is
//! negative, estimated from the distance at the face's four corners (grid nodes): the face
//! is cut into four triangles around its centre (centre value = mean of the corners) and the
//! distance is taken linear on each. The fraction is a continuous, piecewise-smooth function
//! of the corner values, so it moves smoothly with a solid's pose, as Batty et al. (2007)
//! need for the variational pressure solve. The fluid weight of a face is `1 − fraction`;
//! faces on the domain boundary are wall and have weight 0.

use crate::grid::{Grid, Lattice};
use crate::shape::Solid;

/// Fraction of a triangle's area where the linear interpolant of corner values is negative.
#[inline]
pub fn triangle_fraction_inside(a: f64, b: f64, c: f64) -> f64 {
    let mut v = [a, b, c];
    v.sort_by(|x, y| x.total_cmp(y));
    let [a, b, c] = v;
    if c < 0.0 {
        1.0
    } else if a >= 0.0 {
        0.0
    } else if b < 0.0 {
        // a, b inside, c outside: one minus the small outside corner at c.
        1.0 - (c / (c - a)) * (c / (c - b))
    } else {
        // Only a inside: the small corner at a.
        (a / (a - b)) * (a / (a - c))
    }
}

/// Fraction of a square's area inside, from its corner values in cyclic order.
#[inline]
pub fn square_fraction_inside(corners: [f64; 4]) -> f64 {
    let m = 0.25 * (corners[0] + corners[1] + corners[2] + corners[3]);
    (0..4).map(|e| triangle_fraction_inside(m, corners[e], corners[(e + 1) % 4])).sum::<f64>()
        * 0.25
}

/// The four node indices of face `f` of `axis`, in cyclic order around the face.
#[inline]
pub fn face_corner_nodes(nodes: &Lattice, axis: usize, f: [usize; 3]) -> [usize; 4] {
    let (b, c) = ((axis + 1) % 3, (axis + 2) % 3);
    let at = |db: usize, dc: usize| {
        let mut p = f;
        p[b] += db;
        p[c] += dc;
        nodes.index(p[0], p[1], p[2])
    };
    [at(0, 0), at(1, 0), at(1, 1), at(0, 1)]
}

/// A distance far outside any solid, used where there is none.
pub fn far(grid: &Grid) -> f64 {
    10.0 * grid.size().length()
}

/// Signed distance of the union of `solids` at every grid node (`far` where there are none).
pub fn node_sdf(grid: &Grid, solids: &[Solid]) -> Vec<f64> {
    let nodes = grid.nodes();
    let mut out = vec![0.0; nodes.len()];
    let far = far(grid);
    nodes.fill_par(&mut out, |i, j, k| {
        let x = nodes.position(i, j, k);
        solids.iter().map(|s| s.sdf(x)).fold(far, f64::min)
    });
    out
}

/// Fluid weight (open fraction) of every face, from node signed distances of the static
/// solids; domain-boundary faces are walls (weight 0).
pub fn face_weights(grid: &Grid, node_sdf: &[f64]) -> [Vec<f64>; 3] {
    let nodes = grid.nodes();
    [0, 1, 2].map(|axis| {
        let lat = grid.faces(axis);
        let mut w = vec![0.0; lat.len()];
        lat.fill_par(&mut w, |i, j, k| {
            let f = [i, j, k];
            if f[axis] == 0 || f[axis] == grid.n[axis] {
                return 0.0;
            }
            let c = face_corner_nodes(&nodes, axis, f).map(|n| node_sdf[n]);
            (1.0 - square_fraction_inside(c)).clamp(0.0, 1.0)
        });
        w
    })
}

/// True where a cell's centre lies inside a static solid (mean of its corner distances < 0).
pub fn cell_centre_in_solid(grid: &Grid, node_sdf: &[f64]) -> Vec<bool> {
    let nodes = grid.nodes();
    let cells = grid.cells();
    (0..cells.len())
        .map(|c| {
            let [i, j, k] = cells.ijk(c);
            let mut s = 0.0;
            for d in 0..8 {
                s += node_sdf[nodes.index(i + (d & 1), j + ((d >> 1) & 1), k + ((d >> 2) & 1))];
            }
            s < 0.0
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn triangle_fraction_limits() {
        assert_eq!(triangle_fraction_inside(1.0, 2.0, 3.0), 0.0);
        assert_eq!(triangle_fraction_inside(-1.0, -2.0, -3.0), 1.0);
        // Symmetric split: a plane through the midpoints of two edges cuts off 1/4.
        assert!((triangle_fraction_inside(-1.0, 1.0, 1.0) - 0.25).abs() < 1e-15);
        assert!((triangle_fraction_inside(1.0, -1.0, -1.0) - 0.75).abs() < 1e-15);
    }

    #[test]
    fn square_fraction_of_a_plane_is_exact() {
        // A plane φ = x − x0 cutting the unit square: the fraction inside is x0 for any
        // position, since φ is linear and the triangle split is exact for linear φ.
        for &x0 in &[0.1, 0.37, 0.5, 0.83] {
            let c = [0.0 - x0, 1.0 - x0, 1.0 - x0, 0.0 - x0];
            assert!((square_fraction_inside(c) - x0).abs() < 1e-14, "x0 = {x0}");
        }
    }

    #[test]
    fn fraction_is_continuous_in_corner_values() {
        // Moving one corner through zero changes the fraction continuously.
        let f = |t: f64| square_fraction_inside([t, 0.3, 0.5, -0.2]);
        for &t in &[-1e-9, 0.0, 1e-9] {
            assert!((f(t) - f(0.0)).abs() < 1e-8);
        }
    }
}

/// The faces a rigid body covers, with its solid fraction β on each (β > 0 only).
#[derive(Clone, Debug, Default)]
pub struct BodyFaces {
    /// Per axis, (face index, β) sorted by face index.
    pub faces: [Vec<(usize, f64)>; 3],
}

/// Solid fractions of one body on the faces near it, from its signed distance at the
/// nodes of its bounding box grown by one cell. `sdf` evaluates the body's signed distance.
pub fn body_faces(
    grid: &Grid,
    bounds: (crate::math::Vec3, crate::math::Vec3),
    sdf: impl Fn(crate::math::Vec3) -> f64 + Sync,
) -> BodyFaces {
    let nodes = grid.nodes();
    let (lo, hi) = bounds;
    let lo = lo.to_array();
    let hi = hi.to_array();
    // Node index range [n0, n1] per axis covering the grown box.
    let range: [(usize, usize); 3] = [0, 1, 2].map(|a| {
        let n0 = ((lo[a] / grid.dx).floor() - 1.0).max(0.0) as usize;
        let n1 = (((hi[a] / grid.dx).ceil() + 1.0).max(0.0) as usize).min(grid.n[a]);
        (n0.min(grid.n[a]), n1)
    });
    let ext = range.map(|(a, b)| b - a + 1);
    let local = |i: usize, j: usize, k: usize| {
        (i - range[0].0) + ext[0] * ((j - range[1].0) + ext[1] * (k - range[2].0))
    };
    let mut phi = vec![0.0; ext[0] * ext[1] * ext[2]];
    {
        use rayon::prelude::*;
        phi.par_iter_mut().enumerate().for_each(|(l, v)| {
            let i = l % ext[0] + range[0].0;
            let j = (l / ext[0]) % ext[1] + range[1].0;
            let k = l / (ext[0] * ext[1]) + range[2].0;
            *v = sdf(nodes.position(i, j, k));
        });
    }
    let mut out = BodyFaces::default();
    for axis in 0..3 {
        let lat = grid.faces(axis);
        let (b, c) = ((axis + 1) % 3, (axis + 2) % 3);
        let mut fr = [(0usize, 0usize); 3];
        fr[axis] = range[axis];
        fr[b] = (range[b].0, range[b].1.saturating_sub(1));
        fr[c] = (range[c].0, range[c].1.saturating_sub(1));
        if range[b].1 == range[b].0 || range[c].1 == range[c].0 {
            continue;
        }
        for k in fr[2].0..=fr[2].1 {
            for j in fr[1].0..=fr[1].1 {
                for i in fr[0].0..=fr[0].1 {
                    let f = [i, j, k];
                    let corner = |db: usize, dc: usize| {
                        let mut p = f;
                        p[b] += db;
                        p[c] += dc;
                        phi[local(p[0], p[1], p[2])]
                    };
                    let beta = square_fraction_inside([
                        corner(0, 0),
                        corner(1, 0),
                        corner(1, 1),
                        corner(0, 1),
                    ]);
                    if beta > 0.0 {
                        out.faces[axis].push((lat.index(i, j, k), beta));
                    }
                }
            }
        }
    }
    out
}

/// Column i of J for one body, for every cell next to a covered face:
/// `J_i = Σ_f σ_if·dx²·β_f·[e_f ; r_f × e_f]` with σ = +1 on the cell's + face, −1 on its
/// − face, and `r_f` from the centre of mass to the face centre. `J·p` is then the pressure
/// force and torque on the body (−∇p integrated over the solid part of each face), and
/// `(Jᵀ·[v; ω])_i` the volume flux the body's motion pushes out of cell i. Sorted by cell.
pub fn body_jacobian(
    grid: &Grid,
    faces: &BodyFaces,
    com: crate::math::Vec3,
) -> Vec<(usize, [f64; 6])> {
    let area = grid.dx * grid.dx;
    let mut acc: std::collections::BTreeMap<usize, [f64; 6]> = Default::default();
    for axis in 0..3 {
        let lat = grid.faces(axis);
        let e = crate::math::unit(axis);
        for &(f, beta) in &faces.faces[axis] {
            let ijk = lat.ijk(f);
            let r = lat.position(ijk[0], ijk[1], ijk[2]) - com;
            let t = r.cross(e);
            let col = [e.x, e.y, e.z, t.x, t.y, t.z].map(|x| x * area * beta);
            let (minus, plus) = grid.face_cells(axis, ijk);
            for (cell, sign) in [(minus, 1.0), (plus, -1.0)] {
                if let Some(c) = cell {
                    let entry = acc.entry(c).or_insert([0.0; 6]);
                    for d in 0..6 {
                        entry[d] += sign * col[d];
                    }
                }
            }
        }
    }
    acc.into_iter().collect()
}
