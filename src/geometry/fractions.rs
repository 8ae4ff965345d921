//! Face fractions from signed-distance samples.
//!
//! The solid fraction of a face is the solid part of the face's *control volume*: the box
//! that spans the face and reaches from the cell centre on one side to the cell centre on
//! the other, the volume a face velocity stands for in the variational pressure solve
//! (Batty et al. 2007). It is computed from the signed distance sampled every dx/2 (the
//! control volume is 2×2×2 sub-boxes, [`SUBSAMPLE`]), each sub-box split into 24 congruent
//! tetrahedra (box centre, a face centre, an edge of that face; see
//! [`box_fraction_inside`]) with the distance taken linear on each, where the volume of
//! `{phi < 0}` has a closed form. The result is continuous and piecewise smooth in the
//! samples for every orientation of the boundary.
//!
//! (An earlier version used the *area* fraction of the face from its 4 corners, as Batty's
//! 2D code does. That jumps from 0 to 1 when a body's face lies in the plane of a grid face
//! and moves by a hair: the pressure force on a box floating at a grid-aligned depth
//! flickered by 10% from step to step. Control volumes have no such plane.)
//!
//! A body thinner than half a cell would fall between samples dx/2 apart (a quarter-cell plate
//! lost 75% of its volume, and its buoyancy): its fractions sample the distance more finely,
//! at a level chosen once from its thickness ([`samples_per_cell`]).
//!
//! The fluid weight of a face is `1 - fraction`; faces on the domain boundary are walls
//! and have weight 0. A static solid thinner than 2 cells also closes the faces between the
//! cell centres it separates ([`face_weights`]), which volume fractions alone do not.

use crate::geometry::grid::{Grid, Lattice};
use crate::geometry::shape::Solid;
use crate::geometry::spin::Spin;
use crate::math::dual::{Dual, Scalar};
use crate::math::Vec3;

/// A body's face fractions with their derivatives along its six pose directions, per axis
/// (see [`crate::geometry::body::RigidBody::face_fractions_dual`]).
pub type DualFaces = [Vec<(usize, Dual<6>)>; 3];

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

/// The sample lattice of face control-volume corners for `axis`: cell-centre coordinates
/// along `axis`, node coordinates across it.
pub fn cv_lattice(grid: &Grid, axis: usize) -> Lattice {
    let mut n = [grid.n[0] + 1, grid.n[1] + 1, grid.n[2] + 1];
    n[axis] = grid.n[axis];
    let mut off = [0.0; 3];
    off[axis] = 0.5;
    Lattice { n, off, dx: grid.dx }
}

/// The 8 control-volume corners of interior face `f` of `axis` in `cv_lattice`
/// coordinates, indexed `x + 2y + 4z`.
#[inline]
pub fn cv_corners(axis: usize, f: [usize; 3]) -> [[usize; 3]; 8] {
    let mut out = [[0usize; 3]; 8];
    for (c, o) in out.iter_mut().enumerate() {
        for d in 0..3 {
            let bit = (c >> d) & 1;
            o[d] = if d == axis { f[d] - 1 + bit } else { f[d] + bit };
        }
    }
    out
}

/// Sub-boxes per axis of a control volume: the signed distance is sampled every dx/2, so a
/// control volume is 2×2×2 boxes. Linear interpolation misses a sliver wherever a sample sits
/// on a body's flat face next to an edge (the distance has a kink there); at one sample per
/// dx that lost 5% of a 4-cell cube's volume, and with it 5% of its buoyancy. A body thinner
/// than half a cell is sampled more finely ([`samples_per_cell`]).
pub const SUBSAMPLE: usize = 2;

/// The finest sampling [`samples_per_cell`] chooses: every dx/16, for bodies down to a
/// sixteenth of a cell (a 0.1-cell plate's fractions then cost 512 distance samples per
/// dx/2 box within a box's diagonal of its surface, against one for a thick body).
pub const MAX_SAMPLES_PER_CELL: usize = 16;

/// Sub-boxes per cell side for a body `thickness` thick (m) on cells of side `dx`:
/// [`SUBSAMPLE`] for bodies at least half a cell thick, else doubled until a sample spacing
/// is no more than the thickness, up to [`MAX_SAMPLES_PER_CELL`]. A plate between two samples
/// along its normal, both outside it, vanishes from linearly interpolated fractions (a
/// quarter-cell plate sampled every dx/2 lost 75% of its volume); with samples at most its
/// thickness apart, one always lies inside, and the volume correction of [`body_faces`]
/// takes up the rest. Chosen once per body from its shape, never from its pose, so the
/// fractions stay continuous as the body moves.
pub fn samples_per_cell(thickness: f64, dx: f64) -> usize {
    let mut r = SUBSAMPLE;
    while r < MAX_SAMPLES_PER_CELL && dx / r as f64 > thickness {
        r *= 2;
    }
    r
}

/// The refined control-volume corner lattice of `axis` (spacing dx / [`SUBSAMPLE`]).
pub fn cv_fine_lattice(grid: &Grid, axis: usize) -> Lattice {
    let cv = cv_lattice(grid, axis);
    let r = SUBSAMPLE;
    Lattice {
        n: cv.n.map(|n| r * (n - 1) + 1),
        off: cv.off.map(|o| o * r as f64),
        dx: grid.dx / r as f64,
    }
}

/// Solid fraction of the control volume of interior face `f` of `axis`, from the signed
/// distance on the refined lattice (`at` takes refined lattice coordinates).
#[inline]
pub fn cv_fraction<T: Scalar>(axis: usize, f: [usize; 3], at: impl Fn([usize; 3]) -> T) -> T {
    let r = SUBSAMPLE;
    let base = cv_corners(axis, f)[0].map(|x| x * r);
    let mut sum = T::cst(0.0);
    for sk in 0..r {
        for sj in 0..r {
            for si in 0..r {
                let c: [T; 8] = std::array::from_fn(|b| {
                    at([
                        base[0] + si + (b & 1),
                        base[1] + sj + ((b >> 1) & 1),
                        base[2] + sk + ((b >> 2) & 1),
                    ])
                });
                sum = sum + box_fraction_inside(c);
            }
        }
    }
    snap(sum / T::cst((r * r * r) as f64))
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

/// The static solids' signed distance at the grid's nodes ([`node_sdf`]), stored only when
/// some node is nearer a solid than [`far`]: in a tank without obstacles every distance is
/// `far`, and 8 bytes a node (9 MB at a million cells) would sit unread through every step.
#[derive(Clone, Debug, PartialEq)]
pub struct NodeSdf {
    /// The distance at every node; empty when there is no solid.
    values: Vec<f64>,
    /// [`far`] of the grid: the distance everywhere without a solid.
    far: f64,
}

impl NodeSdf {
    /// The distance to `solids` on `grid`'s nodes.
    pub fn new(grid: &Grid, solids: &[Solid]) -> NodeSdf {
        NodeSdf::from_values(grid, node_sdf(grid, solids))
    }

    /// The node distances `values` (one a node of `grid`), dropped when no node is nearer
    /// a solid than [`far`].
    pub fn from_values(grid: &Grid, values: Vec<f64>) -> NodeSdf {
        use rayon::prelude::*;
        assert_eq!(values.len(), grid.nodes().len(), "a distance a node");
        let far = far(grid);
        let any = values.par_iter().any(|&d| d < far);
        NodeSdf { values: if any { values } else { Vec::new() }, far }
    }

    /// Whether there is any static solid.
    pub fn has_solids(&self) -> bool {
        !self.values.is_empty()
    }

    /// The distance at every node, when there is a solid.
    pub fn values(&self) -> Option<&[f64]> {
        self.has_solids().then_some(self.values.as_slice())
    }

    /// The distance at `x` (trilinear between the nodes; [`far`] without a solid).
    #[inline]
    pub fn sample(&self, grid: &Grid, x: Vec3) -> f64 {
        match self.values() {
            Some(v) => grid.nodes().sample(v, x),
            None => self.far,
        }
    }
}

/// Static solids thinner than this many cells everywhere are sealed (see [`face_weights`]
/// and [`is_thin`]). A plate at least 2 cells thick fills some face's whole control volume
/// wherever it sits, and seals by its fractions alone.
pub const SEAL_BELOW_CELLS: f64 = 2.0;

/// Whether `solid` is thinner than [`SEAL_BELOW_CELLS`] everywhere: no point of it, sampled
/// every dx/2 over its bounds within the tank, lies a cell or more inside (its inscribed
/// radius is under a cell, to within the sampling). A plate under 2 cells thick is thin; a
/// ball or a box with a part 2 cells across or more is not, whatever its size.
pub fn is_thin(grid: &Grid, solid: &Solid) -> bool {
    use rayon::prelude::*;
    let half = Lattice { n: grid.n.map(|n| 2 * n + 1), off: [0.0; 3], dx: grid.dx / 2.0 };
    let (lo, hi) = solid.bounds();
    let (lo, hi) = (lo.to_array(), hi.to_array());
    let range = |d: usize| {
        let a = (lo[d] / half.dx).floor().max(0.0) as usize;
        let b = ((hi[d] / half.dx).ceil().max(0.0) as usize + 1).min(half.n[d]);
        a..b.max(a)
    };
    let (ri, rj, rk) = (range(0), range(1), range(2));
    !rk.into_par_iter().any(|k| {
        rj.clone().any(|j| ri.clone().any(|i| solid.sdf(half.position(i, j, k)) <= -grid.dx))
    })
}

/// Fluid weight (open fraction) of every face: one minus the solid fraction of its control
/// volume in the union of `solids`; domain-boundary faces are walls (weight 0).
///
/// A solid thinner than [`SEAL_BELOW_CELLS`] everywhere ([`is_thin`]) also closes (weight 0)
/// every face whose segment between the two cell centres it joins meets the solid
/// ([`seal_thin_solid`]). Volume
/// fractions alone do not seal a thin plate: a quarter-cell plate inside a face's control
/// volume leaves three quarters of it open, and the face carries flow across the plate as if
/// it were a grid of holes (98% of the flow got through). The crossed segments are a cut of
/// the grid's cell-to-cell graph along the plate (every path of cell centres from one side to
/// the other meets it), so a plate of any orientation and any thickness is watertight; the
/// cells whose centre it holds are closed off. Thicker solids keep their volume fractions
/// unchanged, and so do thin parts of a thick solid (give a thin fin as its own obstacle).
pub fn face_weights(grid: &Grid, solids: &[Solid]) -> [Vec<f64>; 3] {
    let mut weights = volume_weights(grid, solids);
    for s in solids {
        if is_thin(grid, s) {
            seal_thin_solid(grid, s, &mut weights);
        }
    }
    weights
}

/// Closes (weight 0) every interior face whose segment from cell centre to cell centre
/// meets `solid` (a ray cast, exact for any thickness).
pub fn seal_thin_solid(grid: &Grid, solid: &Solid, weights: &mut [Vec<f64>; 3]) {
    use crate::math::Vec3;
    use parry3d_f64::query::Ray;
    let (lo, hi) = solid.bounds();
    let (lo, hi) = (lo.to_array(), hi.to_array());
    for (axis, w) in weights.iter_mut().enumerate() {
        let lat = grid.faces(axis);
        // Faces whose segment (along `axis`) or whose centre (across it) may meet the bounds.
        let range = |d: usize| {
            let a = ((lo[d] / grid.dx).floor() - 1.0).max(0.0) as usize;
            let b = (((hi[d] / grid.dx).ceil() + 2.0).max(0.0) as usize).min(lat.n[d]);
            a..b
        };
        let dir = crate::math::unit(axis);
        for k in range(2) {
            for j in range(1) {
                for i in range(0) {
                    let f = [i, j, k];
                    if f[axis] == 0 || f[axis] == grid.n[axis] {
                        continue;
                    }
                    let origin: Vec3 = lat.position(i, j, k) - 0.5 * grid.dx * dir;
                    let ray = Ray::new(origin, dir);
                    if solid.sdf(origin) < 0.0
                        || solid.shape.intersects_ray(&solid.pose, &ray, grid.dx)
                    {
                        w[lat.index(i, j, k)] = 0.0;
                    }
                }
            }
        }
    }
}

/// [`face_weights`] from volume fractions alone.
fn volume_weights(grid: &Grid, solids: &[Solid]) -> [Vec<f64>; 3] {
    let far = far(grid);
    [0, 1, 2].map(|axis| {
        let cv = cv_fine_lattice(grid, axis);
        let mut sdf = Vec::new();
        if !solids.is_empty() {
            sdf = vec![far; cv.len()];
            cv.fill_par(&mut sdf, |i, j, k| {
                let x = cv.position(i, j, k);
                solids.iter().map(|s| s.sdf(x)).fold(far, f64::min)
            });
        }
        let lat = grid.faces(axis);
        let mut w = vec![0.0; lat.len()];
        lat.fill_par(&mut w, |i, j, k| {
            let f = [i, j, k];
            if f[axis] == 0 || f[axis] == grid.n[axis] {
                return 0.0;
            }
            if sdf.is_empty() {
                return 1.0;
            }
            let c = cv_fraction(axis, f, |p| sdf[cv.index(p[0], p[1], p[2])]);
            (1.0 - c).clamp(0.0, 1.0)
        });
        w
    })
}

/// True where a cell's centre lies inside a static solid (mean of its corner distances < 0).
pub fn cell_centre_in_solid(grid: &Grid, node_sdf: &NodeSdf) -> Vec<bool> {
    cells_within(grid, node_sdf, 0.0)
}

/// Cells whose centre lies within `reach` of a static solid (or inside it): the distance at
/// the centre, the mean of its 8 corner distances, under `reach`.
pub fn cells_within(grid: &Grid, node_sdf: &NodeSdf, reach: f64) -> Vec<bool> {
    let nodes = grid.nodes();
    let cells = grid.cells();
    let Some(node_sdf) = node_sdf.values() else {
        return vec![false; cells.len()];
    };
    (0..cells.len())
        .map(|c| {
            let [i, j, k] = cells.ijk(c);
            let mut s = 0.0;
            for d in 0..8 {
                s += node_sdf[nodes.index(i + (d & 1), j + ((d >> 1) & 1), k + ((d >> 2) & 1))];
            }
            s / 8.0 < reach
        })
        .collect()
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

/// The faces a rigid body covers, with its solid fraction β on each (β > 0 only).
#[derive(Clone, Debug, Default)]
pub struct BodyFaces {
    /// Per axis, (face index, β) sorted by face index.
    pub faces: [Vec<(usize, f64)>; 3],
}

impl BodyFaces {
    /// The largest relative error, over the three axes, of the volume the fractions hold,
    /// |Σβ·dx³ − V| / V. The volume correction of [`body_faces`] makes it zero unless its λ
    /// had to be clamped (a body too small or too thin for the grid): then the pressure's
    /// buoyancy is off by as much.
    pub fn volume_error(&self, grid: &Grid, volume: f64) -> f64 {
        let cell = grid.dx.powi(3);
        self.faces
            .iter()
            .map(|f| (f.iter().map(|(_, b)| b).sum::<f64>() * cell - volume).abs() / volume)
            .fold(0.0, f64::max)
    }
}

/// Solid fraction of a box of side `side` at `origin` with corner distances `c` (indexed
/// `x + 2y + 4z`), from `m`³ sub-boxes sampled through `sdf` (`m` = 1: the corners alone,
/// [`box_fraction_inside`]). A box a corner of which lies farther from the surface than the
/// box's diagonal is wholly on that corner's side (a distance changes by at most the distance
/// moved), and is 0 or 1 without sampling: sub-boxes would give the same constant. So only
/// the boxes near the surface cost m³.
fn refined_box_fraction<T: Scalar>(
    c: [T; 8],
    origin: crate::math::Vec3,
    side: f64,
    m: usize,
    sdf: impl Fn(crate::math::Vec3) -> T,
) -> T {
    let diag = 3f64.sqrt() * side;
    if m == 1 || c.iter().any(|x| x.val() >= diag) {
        return box_fraction_inside(c);
    }
    if c.iter().any(|x| x.val() < -diag) {
        return T::cst(1.0);
    }
    let h = side / m as f64;
    let n = m + 1;
    let samples: Vec<T> = (0..n * n * n)
        .map(|l| {
            let p = [l % n, (l / n) % n, l / (n * n)].map(|x| x as f64 * h);
            sdf(origin + crate::math::Vec3::new(p[0], p[1], p[2]))
        })
        .collect();
    let mut sum = T::cst(0.0);
    for k in 0..m {
        for j in 0..m {
            for i in 0..m {
                let corners: [T; 8] = std::array::from_fn(|b| {
                    let q = [i + (b & 1), j + ((b >> 1) & 1), k + ((b >> 2) & 1)];
                    samples[q[0] + n * (q[1] + n * q[2])]
                });
                sum = sum + box_fraction_inside(corners);
            }
        }
    }
    sum / T::cst((m * m * m) as f64)
}

/// Solid fractions of one body on the interior faces near it (control-volume fractions, as
/// for static solids), from its signed distance `sdf` over its bounding box grown by a cell,
/// sampled `per_cell` times per cell side (even: [`SUBSAMPLE`], or [`samples_per_cell`] for
/// the body's thickness).
///
/// With `volume = Some(V)`, the fractions are made volume-consistent: per axis, the partial
/// fractions are corrected as β' = β + λ·β·(1 − β), with λ chosen so that Σ β'·dx³ = V. A
/// hydrostatic pressure then pushes on the body with exactly ρ·g·V. Without the correction,
/// linear interpolation of a convex distance field under-counts the body (1.5% for a ball of
/// radius 2.4 cells), and a neutrally buoyant body sinks. Full (β = 1) and empty faces are
/// untouched, β' stays in [0, 1] (|λ| ≤ 1), and the map stays smooth in the body's pose.
pub fn body_faces(
    grid: &Grid,
    bounds: (crate::math::Vec3, crate::math::Vec3),
    sdf: impl Fn(crate::math::Vec3) -> f64 + Sync,
    volume: Option<f64>,
    per_cell: usize,
) -> BodyFaces {
    BodyFaces { faces: body_faces_generic(grid, bounds, sdf, volume, per_cell) }
}

/// [`body_faces`] for any scalar: with `sdf` returning a `Dual<N>` (the distance and its
/// derivative along N pose directions), the fractions come with their derivatives.
pub fn body_faces_generic<T: Scalar + Send + Sync>(
    grid: &Grid,
    bounds: (crate::math::Vec3, crate::math::Vec3),
    sdf: impl Fn(crate::math::Vec3) -> T + Sync,
    volume: Option<f64>,
    per_cell: usize,
) -> [Vec<(usize, T)>; 3] {
    use rayon::prelude::*;
    let (lo, hi) = (bounds.0.to_array(), bounds.1.to_array());
    let cell_lo = |d: usize| ((lo[d] / grid.dx).floor() - 1.0).max(0.0) as usize;
    let cell_hi = |d: usize| (((hi[d] / grid.dx).ceil() + 1.0).max(0.0) as usize).min(grid.n[d]);
    // Faces [flo, fhi) per axis: interior along `axis`, any cell across it.
    let ranges: [Option<([usize; 3], [usize; 3])>; 3] = [0, 1, 2].map(|axis| {
        let mut flo = [0usize; 3];
        let mut fhi = [0usize; 3];
        for d in 0..3 {
            if d == axis {
                flo[d] = cell_lo(d).max(1);
                fhi[d] = cell_hi(d).min(grid.n[d] - 1) + 1;
            } else {
                flo[d] = cell_lo(d).min(grid.n[d] - 1);
                fhi[d] = cell_hi(d).min(grid.n[d]);
            }
        }
        (0..3).all(|d| fhi[d] > flo[d]).then_some((flo, fhi))
    });
    // The control volumes of every axis are made of boxes dx/2 on a side on one lattice
    // (`half`): along `axis` the boxes of face i start at (i − 1/2 + s/2)·dx, across it at
    // (j + s/2)·dx, s = 0, 1. Each box's solid fraction is computed once, for all three axes
    // (each box is in one control volume per axis), from the distance at its corners, or,
    // for a thin body, from `per_cell / 2` sub-boxes a side wherever its corners leave its
    // inside unknown.
    let r = per_cell;
    assert!(r >= SUBSAMPLE && r % SUBSAMPLE == 0, "per_cell must be even, got {r}");
    let half = Lattice { n: grid.n.map(|n| 2 * n + 1), off: [0.0; 3], dx: grid.dx / 2.0 };
    let mut hlo = [usize::MAX; 3];
    let mut hhi = [0usize; 3];
    for (axis, range) in ranges.iter().enumerate() {
        let Some((flo, fhi)) = range else { continue };
        for d in 0..3 {
            let lo = if d == axis { 2 * (flo[d] - 1) + 1 } else { 2 * flo[d] };
            let hi = if d == axis { 2 * (fhi[d] - 1) + 1 } else { 2 * fhi[d] };
            hlo[d] = hlo[d].min(lo);
            hhi[d] = hhi[d].max(hi + 1);
        }
    }
    let mut out: [Vec<(usize, T)>; 3] = Default::default();
    if ranges.iter().all(Option::is_none) {
        return out;
    }
    // Corner samples, then box fractions, over the boxes between them.
    let ext: [usize; 3] = [0, 1, 2].map(|d| hhi[d] - hlo[d]);
    let mut block = vec![T::cst(0.0); ext[0] * ext[1] * ext[2]];
    block.par_iter_mut().enumerate().for_each(|(l, v)| {
        let i = l % ext[0] + hlo[0];
        let j = (l / ext[0]) % ext[1] + hlo[1];
        let k = l / (ext[0] * ext[1]) + hlo[2];
        *v = sdf(half.position(i, j, k));
    });
    let bext = ext.map(|e| e - 1);
    let mut boxes = vec![T::cst(0.0); bext[0] * bext[1] * bext[2]];
    boxes.par_iter_mut().enumerate().for_each(|(l, v)| {
        let b = [l % bext[0], (l / bext[0]) % bext[1], l / (bext[0] * bext[1])];
        let c: [T; 8] = std::array::from_fn(|n| {
            let q = [0, 1, 2].map(|d| b[d] + ((n >> d) & 1));
            block[q[0] + ext[0] * (q[1] + ext[1] * q[2])]
        });
        let origin = half.position(b[0] + hlo[0], b[1] + hlo[1], b[2] + hlo[2]);
        *v = refined_box_fraction(c, origin, half.dx, r / SUBSAMPLE, &sdf);
    });
    for (axis, range) in ranges.iter().enumerate() {
        let Some((flo, fhi)) = *range else { continue };
        let lat = grid.faces(axis);
        for k in flo[2]..fhi[2] {
            for j in flo[1]..fhi[1] {
                for i in flo[0]..fhi[0] {
                    // The control volume's first box, in `boxes` coordinates.
                    let first = [0, 1, 2].map(|d| {
                        let f = [i, j, k][d];
                        (if d == axis { 2 * f - 1 } else { 2 * f }) - hlo[d]
                    });
                    let mut sum = T::cst(0.0);
                    for n in 0..8 {
                        let q = [0, 1, 2].map(|d| first[d] + ((n >> d) & 1));
                        sum = sum + boxes[q[0] + bext[0] * (q[1] + bext[1] * q[2])];
                    }
                    let beta = snap(sum / T::cst(8.0));
                    if beta.val() > 0.0 {
                        out[axis].push((lat.index(i, j, k), beta));
                    }
                }
            }
        }
        if let Some(v) = volume {
            let cell = grid.dx.powi(3);
            let faces = &mut out[axis];
            let one = T::cst(1.0);
            let mut sum = T::cst(0.0);
            let mut partial = T::cst(0.0);
            for (_, b) in faces.iter() {
                sum = sum + *b;
                partial = partial + *b * (one - *b);
            }
            if partial.val() > 0.0 {
                let raw = (T::cst(v / cell) - sum) / partial;
                let lambda =
                    if raw.val().abs() > 1.0 { T::cst(raw.val().clamp(-1.0, 1.0)) } else { raw };
                // Snapped fractions (0 or 1) are not touched, so the sum is exact.
                for (_, b) in faces.iter_mut() {
                    *b = *b + lambda * *b * (one - *b);
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
/// The torque rows are projected by the body's [`Spin`] (`P·(r_f × e_f)`: what of its
/// rotation reaches the liquid, see [`crate::geometry::body::RigidBody::spin`]).
pub fn body_jacobian(
    grid: &Grid,
    faces: &BodyFaces,
    com: crate::math::Vec3,
    spin: Spin,
) -> Vec<(usize, [f64; 6])> {
    let area = grid.dx * grid.dx;
    let mut acc: std::collections::BTreeMap<usize, [f64; 6]> = Default::default();
    for axis in 0..3 {
        let lat = grid.faces(axis);
        let e = crate::math::unit(axis);
        for &(f, beta) in &faces.faces[axis] {
            let ijk = lat.ijk(f);
            let r = lat.position(ijk[0], ijk[1], ijk[2]) - com;
            let t = spin.project(r.cross(e));
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

#[cfg(test)]
mod node_sdf_tests {
    use super::*;
    use crate::math::{Pose, SharedShape};

    /// Without a solid nothing is stored and every distance is `far`, as the dense array
    /// would sample; with one, the samples are the dense array's to the bit, and the cells
    /// inside it are the dense array's.
    #[test]
    fn node_distance_is_stored_only_with_a_solid() {
        let grid = Grid { n: [12, 10, 8], dx: 0.1 };
        let none = NodeSdf::new(&grid, &[]);
        assert!(!none.has_solids() && none.values().is_none());
        let x = Vec3::new(0.37, 0.52, 0.41);
        assert_eq!(none.sample(&grid, x), far(&grid));
        assert!(cell_centre_in_solid(&grid, &none).iter().all(|&s| !s));
        let ball = Solid::new(
            SharedShape::ball(0.2),
            Pose::from_parts(Vec3::splat(0.4), Default::default()),
        );
        let dense = node_sdf(&grid, std::slice::from_ref(&ball));
        let sdf = NodeSdf::new(&grid, &[ball]);
        assert_eq!(sdf.values(), Some(dense.as_slice()));
        for p in [x, Vec3::splat(0.4), Vec3::new(0.05, 0.93, 0.77)] {
            let want = grid.nodes().sample(&dense, p);
            assert_eq!(sdf.sample(&grid, p).to_bits(), want.to_bits());
        }
        let inside = cell_centre_in_solid(&grid, &sdf);
        assert!(inside.iter().any(|&s| s) && !inside.iter().all(|&s| s));
    }
}

#[cfg(test)]
mod derivative_tests {
    use super::*;
    use crate::geometry::body::RigidBody;
    use crate::math::{Pose, Rotation, SharedShape, Vec3};

    /// ∂β/∂pose from dual numbers against central differences of the f64 fractions, for a
    /// ball and a tilted box at generic poses (on a kink of the distance, where a sample sits
    /// exactly on a flat face or on a box's medial plane, the derivative is one-sided).
    #[test]
    fn fraction_pose_derivatives_match_central_differences() {
        let grid = Grid { n: [16, 12, 16], dx: 0.05 };
        let shapes = [
            (SharedShape::ball(0.12), Rotation::IDENTITY),
            (
                SharedShape::cuboid(0.1, 0.07, 0.12),
                Rotation::from_axis_angle(Vec3::new(0.3, 1.0, 0.2).normalize(), 0.35),
            ),
            // 0.15 cells thick: sampled every dx/8.
            (
                SharedShape::cuboid(0.1, 0.004, 0.12),
                Rotation::from_axis_angle(Vec3::new(0.3, 1.0, 0.2).normalize(), 0.35),
            ),
        ];
        for (shape, rot) in shapes {
            let pose = Pose::from_parts(Vec3::new(0.3813, 0.2871, 0.4127), rot);
            let mut b = RigidBody::with_density("b".into(), shape, pose, 1000.0);
            let dual = b.face_fractions_dual(&grid);
            let eps = 1e-6;
            let mut worst: f64 = 0.0;
            for k in 0..6 {
                let e = crate::math::unit(k % 3) * eps;
                let (x0, q0) = (b.x, b.q);
                let mut at = |sgn: f64| {
                    if k < 3 {
                        b.x = x0 + sgn * e;
                    } else {
                        b.q = (Rotation::from_scaled_axis(sgn * e) * q0).normalize();
                    }
                    let f = b.face_fractions(&grid);
                    b.x = x0;
                    b.q = q0;
                    f
                };
                let (fp, fm) = (at(1.0), at(-1.0));
                for a in 0..3 {
                    let get = |l: &[(usize, f64)], f: usize| {
                        l.iter().find(|(g, _)| *g == f).map(|x| x.1).unwrap_or(0.0)
                    };
                    for (f, d) in &dual[a] {
                        let fd = (get(&fp.faces[a], *f) - get(&fm.faces[a], *f)) / (2.0 * eps);
                        worst = worst.max((fd - d.d[k]).abs());
                    }
                }
            }
            // |∂β/∂x| reaches ~20 per metre here; central differences with ε = 1e-6 carry
            // truncation error near the tetrahedra's case switches: measured 2.2e-6 and 7e-7
            // (about 1e-7 of the derivative's scale), and 3.0e-6 for the thin plate.
            assert!(worst < 1e-5, "worst |dual − central difference| = {worst:e}");
        }
    }
}

#[cfg(test)]
mod thin_tests {
    use super::*;
    use crate::geometry::body::RigidBody;
    use crate::math::{Pose, Rotation, SharedShape, Vec3};

    /// Deterministic numbers in [0, 1).
    fn lcg(state: &mut u64) -> f64 {
        *state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (*state >> 11) as f64 / (1u64 << 53) as f64
    }

    fn random_unit(state: &mut u64) -> Vec3 {
        let z = 2.0 * lcg(state) - 1.0;
        let a = std::f64::consts::TAU * lcg(state);
        let r = (1.0 - z * z).sqrt();
        Vec3::new(r * a.cos(), r * a.sin(), z)
    }

    #[test]
    fn thick_bodies_keep_the_half_cell_sampling() {
        let dx = 0.05;
        for (cells, r) in
            [(4.0, 2), (0.5, 2), (0.49, 4), (0.25, 4), (0.2, 8), (0.1, 16), (0.01, 16)]
        {
            assert_eq!(samples_per_cell(cells * dx, dx), r, "{cells} cells");
        }
    }

    /// A quarter-cell plate at 20 poses: its fractions hold its whole volume (the volume
    /// correction's λ within ±1), which sampling every dx/2 misses for most of them.
    #[test]
    fn thin_plates_keep_their_volume_at_any_pose() {
        let grid = Grid { n: [16, 16, 16], dx: 0.05 };
        let mut state = 7;
        let (mut worst, mut worst_coarse) = (0.0f64, 0.0f64);
        for _ in 0..20 {
            let x = Vec3::new(0.35, 0.35, 0.35)
                + 0.1 * Vec3::new(lcg(&mut state), lcg(&mut state), lcg(&mut state));
            let q = Rotation::from_axis_angle(random_unit(&mut state), 3.0 * lcg(&mut state));
            let shape = SharedShape::cuboid(0.15, 0.25 * grid.dx / 2.0, 0.1);
            let b = RigidBody::with_density("plate".into(), shape, Pose::from_parts(x, q), 1000.0);
            assert_eq!(b.samples_per_cell(grid.dx), 8);
            worst = worst.max(b.face_fractions(&grid).volume_error(&grid, b.volume()));
            let coarse = body_faces(&grid, b.bounds(), |p| b.sdf(p), Some(b.volume()), SUBSAMPLE);
            worst_coarse = worst_coarse.max(coarse.volume_error(&grid, b.volume()));
        }
        // Measured 7e-16 against 0.81 sampled every dx/2.
        assert!(worst < 1e-14, "volume error {worst:e}");
        assert!(worst_coarse > 0.3, "every dx/2 the plate's volume is missed by {worst_coarse}");
    }

    /// Whether the open faces `w` join a cell on the − side of the plane n·x = d − t/2 to one
    /// on the + side of n·x = d + t/2 (a breadth-first walk over cells).
    fn leaks(grid: &Grid, w: &[Vec<f64>; 3], n: Vec3, d: f64, t: f64) -> bool {
        let cells = grid.cells();
        let side = |c: usize| {
            let [i, j, k] = cells.ijk(c);
            n.dot(cells.position(i, j, k)) - d
        };
        let mut seen = vec![false; cells.len()];
        let mut queue: Vec<usize> = (0..cells.len()).filter(|&c| side(c) < -t / 2.0).collect();
        for &c in &queue {
            seen[c] = true;
        }
        while let Some(c) = queue.pop() {
            if side(c) > t / 2.0 {
                return true;
            }
            let ijk = cells.ijk(c);
            for axis in 0..3 {
                let lat = grid.faces(axis);
                for step in [0, 1] {
                    let mut f = ijk;
                    f[axis] += step;
                    if w[axis][lat.index(f[0], f[1], f[2])] <= 0.0 {
                        continue;
                    }
                    let (minus, plus) = grid.face_cells(axis, f);
                    if let Some(o) = if step == 0 { minus } else { plus } {
                        if !seen[o] {
                            seen[o] = true;
                            queue.push(o);
                        }
                    }
                }
            }
        }
        false
    }

    /// A static plate across the whole tank, 0.05 to 1.9 cells thick, at 40 random
    /// orientations and offsets: no path of open faces crosses it. By volume fractions alone
    /// most of them leak.
    #[test]
    fn thin_static_plates_are_watertight_at_any_orientation() {
        let grid = Grid { n: [12, 12, 12], dx: 1.0 / 12.0 };
        let centre = Vec3::splat(0.5);
        let mut state = 11;
        let mut leaky_by_volume = 0;
        for case in 0..40 {
            let n = random_unit(&mut state);
            let t = grid.dx * (0.05 + 1.85 * lcg(&mut state));
            let p = centre + grid.dx * (lcg(&mut state) - 0.5) * n;
            let plate = Solid::new(
                SharedShape::cuboid(2.0, t / 2.0, 2.0),
                Pose::from_parts(p, Rotation::from_rotation_arc(Vec3::Y, n)),
            );
            assert!(is_thin(&grid, &plate), "case {case}: t = {t}");
            let d = n.dot(p);
            let w = face_weights(&grid, std::slice::from_ref(&plate));
            assert!(!leaks(&grid, &w, n, d, t), "case {case}: n {n:?}, t {t}");
            leaky_by_volume += usize::from(leaks(&grid, &volume_weights(&grid, &[plate]), n, d, t));
        }
        // Measured 40 of 40.
        assert!(leaky_by_volume >= 30, "{leaky_by_volume} of 40 leak by volume fractions");
    }

    /// Solids with a part 2 cells across or more keep their volume fractions exactly.
    #[test]
    fn thick_static_solids_keep_their_volume_fractions() {
        let grid = Grid { n: [12, 12, 12], dx: 1.0 / 12.0 };
        let tilt = Rotation::from_axis_angle(Vec3::new(0.3, 1.0, 0.2).normalize(), 0.6);
        let at = Vec3::new(0.47, 0.52, 0.49);
        for (shape, thin) in [
            (SharedShape::ball(2.2 * grid.dx), false),
            (SharedShape::cuboid(0.3, 1.1 * grid.dx, 0.3), false),
            (SharedShape::cuboid(0.3, 0.9 * grid.dx, 0.3), true),
            (SharedShape::ball(0.5 * grid.dx), true),
        ] {
            let s = Solid::new(shape, Pose::from_parts(at, tilt));
            assert_eq!(is_thin(&grid, &s), thin, "{s:?}");
            if !thin {
                let solids = [s];
                assert_eq!(face_weights(&grid, &solids), volume_weights(&grid, &solids));
            }
        }
    }
}
