//! One step of the liquid, as a pipeline of named stages (the paper's Algorithm 2):
//!
//! 0. advect the marker particles through uₜ (RK2), pushed out of solids;
//! 1. advect the velocity semi-Lagrangianly;
//! 2. add gravity;
//! 3. rebuild the liquid signed distance φ_L from the particles;
//! 4. project: build the pressure system, solve it, update the velocity;
//! 5. correct the velocity: extrapolate into air, zero it inside static solids.
//!
//! Every stage is timed; the solve's iterations and residual are reported every step.

use crate::advect::advect;
use crate::density::{self, DensityInputs};
use crate::error::{Error, Result};
use crate::extrapolate::correct_velocity;
use crate::forces::add_gravity;
use crate::fractions;
use crate::grid::{Grid, Mac};
use crate::math::Vec3;
use crate::pressure::{PressureParams, PressureSystem};
use crate::scene::Scene;
use crate::surface::{self, Bins};
use serde::Serialize;
use std::time::Instant;

/// Wall time of each stage of one step, in seconds.
#[derive(Clone, Copy, Debug, Default, Serialize, PartialEq)]
pub struct StageSeconds {
    /// Stage 0: marker particles.
    pub advect_particles: f64,
    /// Stage 1: velocity advection.
    pub advect_velocity: f64,
    /// Stage 2: gravity.
    pub forces: f64,
    /// Stage 3: liquid signed distance (binning + φ_L).
    pub surface: f64,
    /// Stage 4: pressure system, solve and velocity update.
    pub pressure: f64,
    /// Stage 5: extrapolation and solid velocities.
    pub correct_velocity: f64,
}

/// What one step did, as written to `summary.json`.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct StepReport {
    /// Step number, from 1.
    pub step: usize,
    /// Simulated time at the end of the step, s.
    pub time: f64,
    /// Unknowns of the pressure solve (liquid cells).
    pub liquid_cells: usize,
    /// CG iterations.
    pub cg_iterations: usize,
    /// ‖b − A p‖₂ / ‖b‖₂ at the end of the solve.
    pub cg_relative_residual: f64,
    /// Largest |∇·u| over liquid cells after projection, 1/s.
    pub max_divergence: f64,
    /// Liquid volume from the marker particles, m³ (see [`surface::liquid_volume`]).
    pub liquid_volume: f64,
    /// Largest liquid speed at a liquid cell centre, m/s.
    pub max_speed: f64,
    /// Kinetic energy of the liquid, ½ Σ ρ·w_f·dx³·u_f² over faces next to liquid, J.
    pub kinetic_energy: f64,
    /// Wall time per stage.
    pub stage_seconds: StageSeconds,
}

/// Geometry that does not move: tank walls and obstacles.
#[derive(Clone, Debug)]
pub struct StaticGeometry {
    /// Signed distance of the obstacles at grid nodes.
    pub node_sdf: Vec<f64>,
    /// Fluid weight of every face (0 on walls).
    pub weights: [Vec<f64>; 3],
    /// Cells whose centre lies inside an obstacle.
    pub centre_in_solid: Vec<bool>,
}

/// A running simulation.
#[derive(Clone, Debug)]
pub struct Simulation {
    scene: Scene,
    grid: Grid,
    statics: StaticGeometry,
    radius: f64,
    /// Fluid velocity on faces.
    pub u: Mac,
    /// Marker particle positions.
    pub particles: Vec<Vec3>,
    pressure: Vec<f64>,
    phi: Vec<f64>,
    step: usize,
}

impl Simulation {
    /// Sets up a scene: static geometry, particles seeded in the liquid regions, fluid at rest.
    pub fn new(scene: Scene) -> Result<Simulation> {
        scene.check()?;
        let grid = scene.grid();
        let node_sdf = fractions::node_sdf(&grid, &scene.obstacles());
        let weights = fractions::face_weights(&grid, &node_sdf);
        let centre_in_solid = fractions::cell_centre_in_solid(&grid, &node_sdf);
        let ppc = scene.solver.particles_per_cell;
        let particles = surface::seed(&grid, &scene.liquid_regions(), ppc, &node_sdf);
        let radius = surface::particle_radius(grid.dx, surface::per_axis(ppc));
        Ok(Simulation {
            u: Mac::zeros(&grid),
            particles,
            pressure: vec![0.0; grid.num_cells()],
            phi: vec![0.0; grid.num_cells()],
            statics: StaticGeometry {
                node_sdf,
                weights,
                centre_in_solid,
            },
            radius,
            grid,
            scene,
            step: 0,
        })
    }

    /// The scene.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// The grid.
    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// Static geometry.
    pub fn statics(&self) -> &StaticGeometry {
        &self.statics
    }

    /// Steps taken so far.
    pub fn steps_taken(&self) -> usize {
        self.step
    }

    /// Simulated time.
    pub fn time(&self) -> f64 {
        self.step as f64 * self.scene.time.dt
    }

    /// Pressure at cell centres from the last solve (Pa, zero outside the liquid).
    pub fn pressure(&self) -> &[f64] {
        &self.pressure
    }

    /// Liquid signed distance at cell centres from the last step.
    pub fn liquid_phi(&self) -> &[f64] {
        &self.phi
    }

    /// Liquid volume of the current particles, m³.
    pub fn liquid_volume(&self) -> f64 {
        let bins = Bins::new(&self.particles, &self.grid);
        surface::liquid_volume(
            &self.particles,
            &bins,
            &self.grid,
            self.scene.solver.particles_per_cell,
        )
    }

    /// Advances one step.
    pub fn step(&mut self) -> Result<StepReport> {
        let dt = self.scene.time.dt;
        let grid = self.grid;
        let mut times = StageSeconds::default();
        let mut clock = Instant::now();
        let mut lap = |slot: &mut f64| {
            let now = Instant::now();
            *slot = (now - clock).as_secs_f64();
            clock = now;
        };

        // 0. Marker particles ride the current (divergence-free, extrapolated) field.
        surface::advect(
            &mut self.particles,
            &self.u,
            &grid,
            dt,
            &self.statics.node_sdf,
        );
        if self.scene.solver.density_correction {
            let inputs = DensityInputs {
                grid: &grid,
                weights: &self.statics.weights,
                node_sdf: &self.statics.node_sdf,
                centre_in_solid: &self.statics.centre_in_solid,
                radius: self.radius,
            };
            density::correct(
                &mut self.particles,
                &inputs,
                &self.scene.solver,
                self.step + 1,
            )?;
        }
        lap(&mut times.advect_particles);

        // 1. Self-advection of the velocity.
        let mut u = advect(&self.u, &grid, dt);
        lap(&mut times.advect_velocity);

        // 2. Gravity.
        add_gravity(&mut u, self.scene.fluid.gravity, dt);
        lap(&mut times.forces);

        // 3. Where the liquid is now.
        let bins = Bins::new(&self.particles, &grid);
        let mut phi = surface::liquid_sdf(&self.particles, &bins, &grid, self.radius);
        surface::extend_into_solids(&mut phi, &grid, &self.statics.centre_in_solid);
        lap(&mut times.surface);

        // 4. Projection.
        let solver = &self.scene.solver;
        let params = PressureParams {
            dt,
            density: self.scene.fluid.density,
            theta_min: solver.theta_min,
        };
        let sys = PressureSystem::build(&grid, &phi, &self.statics.weights, params);
        let b = sys.rhs(&u, &self.statics.weights);
        let (p, stats) = sys.solve(
            &b,
            solver.preconditioner,
            solver.tolerance,
            solver.max_iterations,
        );
        if !stats.converged {
            return Err(Error::NotConverged {
                step: self.step + 1,
                iterations: stats.iterations,
                residual: stats.relative_residual,
                tolerance: solver.tolerance,
            });
        }
        let mut valid = sys.update_velocity(&p, &mut u, &self.statics.weights, &phi);
        let flux = sys.fluid_flux(&u, &self.statics.weights);
        let max_divergence = flux.iter().fold(0.0f64, |m, f| m.max(f.abs())) / grid.dx.powi(3);
        let kinetic_energy = self.kinetic_energy(&u, &valid);
        lap(&mut times.pressure);

        // 5. Velocity correction.
        correct_velocity(
            &mut u,
            &mut valid,
            &self.statics.weights,
            &grid,
            solver.extrapolation_layers,
        );
        lap(&mut times.correct_velocity);

        self.step += 1;
        if !u.is_finite() {
            return Err(Error::NonFinite {
                step: self.step,
                what: "the fluid velocity".into(),
            });
        }
        self.u = u;
        self.pressure = sys.scatter(&p);
        self.phi = phi;
        Ok(StepReport {
            step: self.step,
            time: self.time(),
            liquid_cells: sys.len(),
            cg_iterations: stats.iterations,
            cg_relative_residual: stats.relative_residual,
            max_divergence,
            liquid_volume: surface::liquid_volume(
                &self.particles,
                &bins,
                &grid,
                solver.particles_per_cell,
            ),
            max_speed: self.max_liquid_speed(&sys),
            kinetic_energy,
            stage_seconds: times,
        })
    }

    /// ½ Σ ρ·w_f·dx³·u_f² over the faces the projection updated.
    fn kinetic_energy(&self, u: &Mac, valid: &[Vec<u8>; 3]) -> f64 {
        let m = self.scene.fluid.density * self.grid.dx.powi(3);
        // Sequential on purpose: the sum is cheap and its order fixed.
        let mut e = 0.0;
        for a in 0..3 {
            for (f, &uf) in u.c[a].iter().enumerate() {
                if valid[a][f] != 0 {
                    e += self.statics.weights[a][f] * uf * uf;
                }
            }
        }
        0.5 * m * e
    }

    /// Largest speed at the centre of a liquid cell (faces averaged per axis).
    fn max_liquid_speed(&self, sys: &PressureSystem) -> f64 {
        let cells = self.grid.cells();
        sys.cell_of_row
            .iter()
            .map(|&c| {
                let ijk = cells.ijk(c as usize);
                let v = [0, 1, 2].map(|a| {
                    let lat = self.grid.faces(a);
                    let mut hi = ijk;
                    hi[a] += 1;
                    0.5 * (self.u.c[a][lat.index(ijk[0], ijk[1], ijk[2])]
                        + self.u.c[a][lat.index(hi[0], hi[1], hi[2])])
                });
                (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
            })
            .fold(0.0, f64::max)
    }

    /// Cells that are liquid in the last step's φ_L.
    pub fn liquid_cells(&self) -> impl Iterator<Item = usize> + '_ {
        self.phi
            .iter()
            .enumerate()
            .filter(|(_, p)| **p < 0.0)
            .map(|(c, _)| c)
    }
}
