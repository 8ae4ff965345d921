//! Seeding: the particles' sub-lattice, their radius, and the liquid's initial regions.

use crate::geometry::fractions::NodeSdf;
use crate::geometry::grid::Grid;
use crate::geometry::shape::Solid;
use crate::math::Vec3;
use rayon::prelude::*;

/// Sub-lattice offsets (in cells, relative to the cell's lower corner) for m per axis.
pub fn sub_offsets(m: usize) -> Vec<f64> {
    (0..m).map(|a| (a as f64 + 0.5) / m as f64).collect()
}

/// Particles per axis for a particle-per-cell count (1, 8, 27, 64).
pub fn per_axis(ppc: usize) -> usize {
    (ppc as f64).cbrt().round() as usize
}

/// The particle radius for `m` particles per axis: the mean of the nearest-particle
/// distances from the two cell centres on either side of a flat seeded surface lying on a
/// cell face. With it, linear interpolation of φ_L between those centres puts the surface
/// exactly on the face (θ = 1/2), so still water is reconstructed flat at its true height.
/// For m = 2 this is (√11 + √3)/8·dx ≈ 0.631·dx.
pub fn particle_radius(dx: f64, m: usize) -> f64 {
    let off = sub_offsets(m);
    // Liquid fills z < 0 with cells [.., −1]; centres above (z = +½) and below (z = −½).
    let nearest = |cz: f64| {
        let mut best = f64::MAX;
        for &ox in &off {
            for &oy in &off {
                for &oz in &off {
                    let p = Vec3::new(ox - 0.5, oy - 0.5, oz - 1.0);
                    best = best.min((p - Vec3::new(0.0, 0.0, cz)).length());
                }
            }
        }
        best
    };
    0.5 * (nearest(0.5) + nearest(-0.5)) * dx
}

/// Seeds m³ particles per cell on a regular sub-lattice, inside any of `regions` and outside
/// the static solids (`node_sdf`), in every cell but those `skip` marks (a narrow band's deep
/// cells).
pub fn seed(
    grid: &Grid,
    regions: &[Solid],
    ppc: usize,
    node_sdf: &NodeSdf,
    skip: Option<&[bool]>,
) -> Vec<Vec3> {
    let off = sub_offsets(per_axis(ppc));
    let liquid = Regions::new(regions);
    let slabs: Vec<Vec<Vec3>> = (0..grid.n[2])
        .into_par_iter()
        .map(|k| {
            let mut out = Vec::new();
            for j in 0..grid.n[1] {
                for i in 0..grid.n[0] {
                    if skip.is_some_and(|s| s[grid.cell(i, j, k)]) {
                        continue;
                    }
                    out.extend(
                        sites(grid, [i, j, k], &off)
                            .filter(|x| liquid.contain(*x) && node_sdf.sample(grid, *x) > 0.0),
                    );
                }
            }
            out
        })
        .collect();
    slabs.concat()
}

/// The sub-lattice sites of cell `ijk` at offsets `off` (see [`sub_offsets`]), x fastest.
pub fn sites<'a>(grid: &Grid, ijk: [usize; 3], off: &'a [f64]) -> impl Iterator<Item = Vec3> + 'a {
    let dx = grid.dx;
    let at = move |a: usize, o: f64| (ijk[a] as f64 + o) * dx;
    off.iter().flat_map(move |&oz| {
        off.iter().flat_map(move |&oy| {
            off.iter().map(move |&ox| Vec3::new(at(0, ox), at(1, oy), at(2, oz)))
        })
    })
}

/// Liquid regions with their bounds, to ask whether a point is in any of them.
pub struct Regions<'a> {
    regions: &'a [Solid],
    bounds: Vec<(Vec3, Vec3)>,
}

impl<'a> Regions<'a> {
    /// `regions` and their bounds.
    pub fn new(regions: &'a [Solid]) -> Regions<'a> {
        Regions { regions, bounds: regions.iter().map(Solid::bounds).collect() }
    }

    /// Whether `x` is inside any region (its bounds first, then its signed distance).
    pub fn contain(&self, x: Vec3) -> bool {
        self.regions
            .iter()
            .zip(&self.bounds)
            .any(|(r, (lo, hi))| x.cmpge(*lo).all() && x.cmple(*hi).all() && r.sdf(x) < 0.0)
    }
}
