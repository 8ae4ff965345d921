//! The static solids' signed distance at the grid's nodes ([`NodeSdf`], stored only where
//! there is a solid), and the cells whose centre it puts inside or near one.

use crate::geometry::grid::Grid;
use crate::geometry::shape::Solid;
use crate::math::Vec3;

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
