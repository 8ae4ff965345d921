//! The liquid signed distance φ_L carried into the solids (part of the step's system).
//!
//! No particle sits inside a solid, so the particles' φ_L at a cell whose centre is in a
//! static solid or a body says nothing about the liquid there. Such a cell still matters when
//! a face of it is partly open: it is a pressure unknown (liquid) or a ghost-fluid air cell,
//! and the pressure it gets pushes on the body. Its φ is therefore carried in from the cells
//! around it, a layer at a time, as the mean of its face neighbours' φ that are outside the
//! solids or already set ([`SolidExtension`]).
//!
//! The free surface then meets a body where the liquid beside it lies: a ball floating at
//! rest has, inside it, the same flat surface as the water around it, and hydrostatic
//! pressure is an exact rest state of the step. The rule before this one marked every solid
//! cell next to a liquid cell as liquid (φ = −½·dx, Batty's codes do the same), which put a
//! false free surface up to a cell above the waterline inside every curved or tilted body
//! crossing the surface; the projection made a current out of it each step, and that
//! current, fed back through the body's bobbing, drove still water around a floating ball to
//! tens of joules (issue 33).
//!
//! The map depends on which cell centres lie in a solid only, never on φ: it is linear in
//! φ, and its transpose ([`SolidExtension::transpose`]) carries ∂L/∂φ back to the cells it
//! read.

use crate::geometry::grid::Grid;
use crate::math::par::MIN_LEN;
use rayon::prelude::*;

/// How many layers into a solid φ_L is carried: enough for every cell whose centre is in a
/// solid and that has a face partly open (such a face's control volume reaches outside the
/// solid, so its cell lies within a cell diagonal of the solid's surface).
pub const LAYERS: usize = 2;

/// The cells whose centre is in a solid that φ_L is carried into, each with the cells its
/// value is the mean of, in the order they are set (a layer after the other; the cells of a
/// layer read only cells outside the solids and cells of earlier layers).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SolidExtension {
    /// The cells set, in order.
    cells: Vec<u32>,
    /// Cell `cells[i]` is `Σ weight·φ` over `sources[starts[i]..starts[i + 1]]`.
    starts: Vec<u32>,
    /// The cells read.
    sources: Vec<u32>,
    /// Each source's weight (a cell's weights sum to 1).
    weights: Vec<f64>,
}

impl SolidExtension {
    /// The extension for the cells `centre_in_solid` marks.
    pub fn new(grid: &Grid, centre_in_solid: &[bool], gravity: [f64; 3]) -> SolidExtension {
        let g2: f64 = gravity.iter().map(|x| x * x).sum();
        // A source along axis a weighs 1 − ĝ_a²: across gravity, where a liquid at rest is
        // level; along it only where nothing else is (or without gravity).
        let across: [f64; 3] =
            std::array::from_fn(
                |a| if g2 > 0.0 { 1.0 - gravity[a] * gravity[a] / g2 } else { 1.0 },
            );
        let cells = grid.cells();
        let solid: Vec<u32> = (0..centre_in_solid.len() as u32)
            .into_par_iter()
            .with_min_len(MIN_LEN)
            .filter(|&c| centre_in_solid[c as usize])
            .collect();
        let mut out = SolidExtension { starts: vec![0], ..Default::default() };
        if solid.is_empty() {
            return out;
        }
        // 0: outside the solids (φ from the particles), 1 + l: set in layer l, u8::MAX: not
        // set yet.
        const UNSET: u8 = u8::MAX;
        let mut level: Vec<u8> =
            centre_in_solid.iter().map(|&s| if s { UNSET } else { 0 }).collect();
        let mut left = solid;
        for layer in 0..LAYERS as u8 {
            // The cells of this layer and their sources, found against the levels before it.
            let found: Vec<(u32, [u32; 6], [f64; 6], u8)> = left
                .par_iter()
                .filter_map(|&c| {
                    let ci = c as usize;
                    let ijk = cells.ijk(ci);
                    let mut src = [0u32; 6];
                    let mut w = [0.0; 6];
                    let mut n = 0u8;
                    for f in 0..6 {
                        if let Some(nb) = cells.neighbour(ci, ijk, f / 2, f % 2) {
                            if level[nb] <= layer {
                                src[n as usize] = nb as u32;
                                w[n as usize] = across[f / 2];
                                n += 1;
                            }
                        }
                    }
                    let n_us = n as usize;
                    let total: f64 = w[..n_us].iter().sum();
                    // Weights below round-off count as none (gravity along an axis).
                    if total > 1e-9 {
                        w[..n_us].iter_mut().for_each(|x| *x /= total);
                    } else {
                        w[..n_us].iter_mut().for_each(|x| *x = 1.0 / n as f64);
                    }
                    (n > 0).then_some((c, src, w, n))
                })
                .collect();
            if found.is_empty() {
                break;
            }
            for &(c, src, w, n) in &found {
                level[c as usize] = layer + 1;
                out.cells.push(c);
                out.sources.extend_from_slice(&src[..n as usize]);
                out.weights.extend_from_slice(&w[..n as usize]);
                out.starts.push(out.sources.len() as u32);
            }
            left.retain(|&c| level[c as usize] == UNSET);
        }
        out
    }

    /// The cells set, in the order they are set.
    pub fn cells(&self) -> &[u32] {
        &self.cells
    }

    /// The cells cell number `i` of [`SolidExtension::cells`] reads, with their weights.
    fn sources(&self, i: usize) -> impl Iterator<Item = (usize, f64)> + '_ {
        let r = self.starts[i] as usize..self.starts[i + 1] as usize;
        self.sources[r.clone()].iter().map(|&s| s as usize).zip(self.weights[r].iter().copied())
    }

    /// Sets φ of each cell of the extension to the weighted mean of its sources, in order.
    pub fn apply(&self, phi: &mut [f64]) {
        for (i, &c) in self.cells.iter().enumerate() {
            phi[c as usize] = self.sources(i).map(|(s, w)| w * phi[s]).sum();
        }
    }

    /// The transpose of [`SolidExtension::apply`]: `phi_bar` of the extended φ becomes, in
    /// place, that of φ before it (a cell set carries nothing of its own: its value was
    /// overwritten).
    pub fn transpose(&self, phi_bar: &mut [f64]) {
        for (i, &c) in self.cells.iter().enumerate().rev() {
            let g = std::mem::take(&mut phi_bar[c as usize]);
            for (s, w) in self.sources(i) {
                phi_bar[s] += w * g;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::grid::Grid;
    use crate::math::Vec3;

    fn ball_grid() -> (Grid, Vec<bool>) {
        let grid = Grid { n: [10, 10, 10], dx: 0.1 };
        let cells = grid.cells();
        let centre = Vec3::new(0.5, 0.5, 0.5);
        let solid = (0..grid.num_cells())
            .map(|c| {
                let [i, j, k] = cells.ijk(c);
                (cells.position(i, j, k) - centre).length() < 0.32
            })
            .collect();
        (grid, solid)
    }

    /// A flat free surface crosses a ball: inside the ball the extension puts it at the
    /// same height (to round-off) wherever a cell reads only neighbours at its own height, and
    /// never makes a cell above the surface liquid.
    #[test]
    fn flat_surface_continues_through_a_ball() {
        let (grid, solid) = ball_grid();
        let cells = grid.cells();
        let h = 0.52;
        let height = |c: usize| {
            let [i, j, k] = cells.ijk(c);
            cells.position(i, j, k).y
        };
        let mut phi: Vec<f64> =
            (0..grid.num_cells()).map(|c| if solid[c] { 1.0 } else { height(c) - h }).collect();
        let ext = SolidExtension::new(&grid, &solid, [0.0, -9.81, 0.0]);
        ext.apply(&mut phi);
        assert!(!ext.cells().is_empty());
        for &c in ext.cells() {
            let c = c as usize;
            let y = height(c);
            assert_eq!(phi[c] < 0.0, y < h, "cell at height {y}: φ {}", phi[c]);
        }
    }

    /// ⟨E·a, b⟩ = ⟨a, Eᵀ·b⟩ for random a and b.
    #[test]
    fn transpose_is_the_transpose() {
        let (grid, solid) = ball_grid();
        let ext = SolidExtension::new(&grid, &solid, [0.0, -9.81, 0.0]);
        let n = grid.num_cells();
        let mut rng = 12345u64;
        let mut next = || {
            rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (rng >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let a: Vec<f64> = (0..n).map(|_| next()).collect();
        let b: Vec<f64> = (0..n).map(|_| next()).collect();
        let mut ea = a.clone();
        ext.apply(&mut ea);
        let mut etb = b.clone();
        ext.transpose(&mut etb);
        let lhs: f64 = ea.iter().zip(&b).map(|(x, y)| x * y).sum();
        let rhs: f64 = a.iter().zip(&etb).map(|(x, y)| x * y).sum();
        assert!((lhs - rhs).abs() < 1e-12 * lhs.abs().max(1.0), "{lhs} vs {rhs}");
    }
}
