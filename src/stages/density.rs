//! Particle density projection (Kugelstadt, Longva, Thuerey & Bender 2019, "Implicit
//! density projection for volume conserving liquids"), part of stage 0.
//!
//! Trilinear interpolation of a discretely divergence-free MAC field is not divergence-free
//! between the samples, and marker particles drift together where it converges, most of all
//! in the half cell next to a wall: the grid sees a full cell, the particles fill part of it,
//! and volume is lost. The projection measures the particles' density on cell centres and
//! solves one more Poisson problem on the same operator as the pressure, whose gradient is a
//! displacement that carries each over-full cell's excess volume out of it. The surface is
//! held fixed in the backward pass, so this costs no gradient; it is a scene option
//! (`solver.density_correction`).

use crate::error::{Error, Result};
use crate::geometry::grid::{Grid, Mac};
use crate::math::Vec3;
use crate::solvers::LinearSolve;
use crate::stages::extrapolate::correct_velocity;
use crate::stages::pressure::{PressureParams, PressureSystem};
use crate::stages::surface::{self, Bins};
use rayon::prelude::*;

/// What the projection did.
#[derive(Clone, Copy, Debug, Default)]
pub struct DensityStats {
    /// Excess volume (m³) in over-full cells before the push.
    pub excess_volume: f64,
    /// CG iterations of the projection solve.
    pub cg_iterations: usize,
}

/// Geometry the projection needs.
pub struct DensityInputs<'a> {
    /// The grid.
    pub grid: &'a Grid,
    /// Face fluid weights of the solids.
    pub weights: &'a [Vec<f64>; 3],
    /// Solid signed distance at nodes.
    pub node_sdf: &'a [f64],
    /// Cells whose centre is in a solid.
    pub centre_in_solid: &'a [bool],
    /// Particle radius for φ_L.
    pub radius: f64,
    /// Marker particles seeded per cell (the density of a full cell).
    pub particles_per_cell: usize,
    /// The ghost-fluid θ clamp of the projection's operator.
    pub theta_min: f64,
    /// How to solve it (the tolerance is raised to at least 1e-6: a volume to a millionth
    /// of the excess is plenty).
    pub solve: LinearSolve,
}

/// Pushes particles out of over-full cells. `step` names the step in errors.
pub fn correct(particles: &mut [Vec3], g: &DensityInputs<'_>, step: usize) -> Result<DensityStats> {
    let grid = g.grid;
    let ppc = g.particles_per_cell;
    let bins = Bins::new(particles, grid);
    let mut phi = surface::liquid_sdf(particles, &bins, grid, g.radius);
    surface::extend_into_solids(&mut phi, grid, g.centre_in_solid);
    let dens = surface::particle_density(particles, grid, ppc);
    // Unit Δt and density: the "velocity" update below is then a displacement in metres
    // whose volume flux out of each cell equals the right-hand side.
    let params = PressureParams { dt: 1.0, density: 1.0, theta_min: g.theta_min };
    let sys = PressureSystem::build(grid, &phi, g.weights, params);
    let vol = grid.dx.powi(3);
    // Densities within 1e-6 of full are full: round-off in the deposit must not start a solve.
    let b: Vec<f64> = sys
        .cell_of_row
        .iter()
        .map(|&c| if dens[c as usize] > 1.0 + 1e-6 { (dens[c as usize] - 1.0) * vol } else { 0.0 })
        .collect();
    let excess_volume: f64 = b.iter().sum();
    if excess_volume == 0.0 {
        return Ok(DensityStats::default());
    }
    let how = LinearSolve { tolerance: g.solve.tolerance.max(1e-6), ..g.solve };
    let (q, stats) = sys.solve(&b, &how);
    if !stats.converged {
        return Err(Error::NotConverged {
            step,
            iterations: stats.iterations,
            residual: stats.relative_residual,
            tolerance: how.tolerance,
        });
    }
    let mut d = Mac::zeros(grid);
    let mut valid = sys.update_velocity(&q, &mut d);
    correct_velocity(&mut d, &mut valid, g.weights, grid, 1);
    let nodes = grid.nodes();
    let size = grid.size();
    let margin = 1e-3 * grid.dx;
    let cap = 0.5 * grid.dx;
    particles.par_iter_mut().for_each(|x| {
        let mut dx = d.velocity(grid, *x);
        let len = dx.length();
        if len > cap {
            dx *= cap / len;
        }
        let mut y = *x + dx;
        let (s, gr) = nodes.sample_grad(g.node_sdf, y);
        if s < margin && gr.length() > 1e-12 {
            y += (margin - s) * gr.normalize();
        }
        *x = y.clamp(Vec3::splat(margin), size - Vec3::splat(margin));
    });
    Ok(DensityStats { excess_volume, cg_iterations: stats.iterations })
}
