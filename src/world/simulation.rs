//! One step of the liquid, as a pipeline of named stages (the paper's Algorithm 2):
//!
//! 0. advect the marker particles through uₜ (RK2), pushed out of solids;
//! 1. advect the velocity semi-Lagrangianly;
//! 2. add gravity;
//! 3. rebuild the liquid signed distance φ_L from the particles;
//! 4. project: build the pressure system, solve it, update the velocity;
//! 5. correct the velocity: extrapolate into air, zero it inside static solids, give faces
//!    inside a body the body's velocity;
//! 6. integrate the bodies (x += Δt·v, quaternion update), or let rapier resolve contact.
//!
//! Stage 3 runs before stage 1: φ_L depends on the particles alone, and advection then
//! computes only the faces the rest of the step reads (those of liquid cells and those the
//! bodies cover), so air away from the liquid costs nothing.
//!
//! Bodies enter stage 3 as solid fractions β on the faces they cover (the fluid weight is
//! what is left) and as J, and stage 4 as the rank-6 term Δt·Jᵀ M_S⁻¹ J of one monolithic
//! solve (Batty et al. 2007): v += Δt·M_S⁻¹ J p.
//!
//! Every stage is timed; the solve's iterations and residual are reported every step.

use crate::error::{Error, Result};
use crate::experiments::scene::{Coupling, Scene};
use crate::geometry::body::RigidBody;
use crate::geometry::fractions;
use crate::geometry::grid::{Grid, Mac};
use crate::math::Vec3;
use crate::stages::advect::{advect, needed_faces};
#[cfg(feature = "contact")]
use crate::stages::contact::ContactWorld;
use crate::stages::density::{self, DensityInputs};
use crate::stages::extrapolate::correct_velocity;
use crate::stages::forces::add_gravity;
use crate::stages::pressure::BodyCoupling;
use crate::stages::pressure::{PressureParams, PressureSystem};
use crate::stages::surface::{self, Bins};
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
    /// Stage 3 (bodies): face fractions, J, combined weights.
    pub geometry: f64,
    /// Stage 6: rigid integration or contact.
    pub rigid: f64,
}

/// Pressure force and torque on one body in one step, as written to `summary.json`.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct BodyForce {
    /// Body name.
    pub name: String,
    /// Pressure force J·p (first three rows), N.
    pub force: [f64; 3],
    /// Pressure torque about the centre of mass, N·m.
    pub torque: [f64; 3],
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
    /// Pressure force and torque on each dynamic body.
    pub bodies: Vec<BodyForce>,
    /// Extra pressure solves made to hold contact impulses (0 without contact).
    pub contact_iterations: usize,
    /// Largest velocity change contact still made after the last solve, m/s (0 when it
    /// converged or contact was off).
    pub contact_residual: f64,
    /// Wall time per stage.
    pub stage_seconds: StageSeconds,
}

/// Where the solids are this step: combined face weights and the bodies' faces.
#[derive(Clone, Debug)]
pub struct Geometry {
    /// Fluid weight of every face: static weight minus the bodies' fractions, in [0, 1].
    pub weights: [Vec<f64>; 3],
    /// Cells whose centre is inside a static solid or a body.
    pub centre_in_solid: Vec<bool>,
    /// Faces covered by each body.
    pub body_faces: Vec<fractions::BodyFaces>,
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
    /// Rigid bodies.
    pub bodies: Vec<RigidBody>,
    pressure: Vec<f64>,
    phi: Vec<f64>,
    /// φ_L of the initial particles, when the surface is frozen.
    frozen_phi: Option<Vec<f64>>,
    /// Liquid volume of the frozen particles.
    frozen_volume: f64,
    step: usize,
}

impl Simulation {
    /// Sets up a scene: static geometry, particles seeded in the liquid regions, fluid at rest.
    pub fn new(scene: Scene) -> Result<Simulation> {
        scene.check()?;
        let grid = scene.grid();
        let obstacles = scene.obstacles();
        let node_sdf = fractions::node_sdf(&grid, &obstacles);
        let weights = fractions::face_weights(&grid, &obstacles);
        let centre_in_solid = fractions::cell_centre_in_solid(&grid, &node_sdf);
        let ppc = scene.solver.particles_per_cell;
        let particles = surface::seed(&grid, &scene.liquid_regions(), ppc, &node_sdf);
        let radius = surface::particle_radius(grid.dx, surface::per_axis(ppc));
        let bodies = scene.bodies()?;
        let mut particles = particles;
        let margin = 1e-3 * grid.dx;
        particles.retain(|x| bodies.iter().all(|b| b.sdf(*x) > margin));
        let (frozen_phi, frozen_volume) = if scene.solver.freeze_surface {
            let bins = Bins::new(&particles, &grid);
            let vol = surface::liquid_volume(&particles, &grid, ppc);
            (Some(surface::liquid_sdf(&particles, &bins, &grid, radius)), vol)
        } else {
            (None, 0.0)
        };
        Ok(Simulation {
            frozen_phi,
            frozen_volume,
            bodies,
            u: Mac::zeros(&grid),
            particles,
            pressure: vec![0.0; grid.num_cells()],
            phi: vec![0.0; grid.num_cells()],
            statics: StaticGeometry { node_sdf, weights, centre_in_solid },
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
        if self.frozen_phi.is_some() {
            return self.frozen_volume;
        }
        surface::liquid_volume(&self.particles, &self.grid, self.scene.solver.particles_per_cell)
    }

    /// Where the solids are now: static weights minus each body's face fractions.
    pub fn geometry(&self) -> Geometry {
        self.geometry_of(&self.bodies)
    }

    /// Where the solids are with the bodies in the given states.
    pub fn geometry_of(&self, bodies: &[RigidBody]) -> Geometry {
        let faces = bodies
            .iter()
            .map(|b| fractions::body_faces(&self.grid, b.bounds(), |p| b.sdf(p), Some(b.volume())))
            .collect();
        self.geometry_with(bodies, faces)
    }

    /// [`Simulation::geometry_of`] with the bodies' face fractions already known (the
    /// backward pass has them on the tape).
    pub fn geometry_with(
        &self,
        bodies: &[RigidBody],
        faces_of: Vec<fractions::BodyFaces>,
    ) -> Geometry {
        assert_eq!(bodies.len(), faces_of.len());
        let grid = &self.grid;
        let mut weights = self.statics.weights.clone();
        let mut centre_in_solid = self.statics.centre_in_solid.clone();
        let mut body_faces = Vec::with_capacity(bodies.len());
        let cells = grid.cells();
        for (b, faces) in bodies.iter().zip(faces_of) {
            for a in 0..3 {
                for &(f, beta) in &faces.faces[a] {
                    // β is already snapped to 0 or 1 where it is within round-off of
                    // them, so w + β = 1 holds exactly on every face a body alone covers.
                    weights[a][f] = (weights[a][f] - beta).clamp(0.0, 1.0);
                }
            }
            let (lo, hi) = b.bounds();
            let lo = lo.to_array().map(|x| ((x / grid.dx).floor().max(0.0)) as usize);
            let hi = hi.to_array();
            for k in lo[2]..grid.n[2].min((hi[2] / grid.dx).ceil() as usize + 1) {
                for j in lo[1]..grid.n[1].min((hi[1] / grid.dx).ceil() as usize + 1) {
                    for i in lo[0]..grid.n[0].min((hi[0] / grid.dx).ceil() as usize + 1) {
                        if b.sdf(cells.position(i, j, k)) < 0.0 {
                            centre_in_solid[grid.cell(i, j, k)] = true;
                        }
                    }
                }
            }
            body_faces.push(faces);
        }
        Geometry { weights, centre_in_solid, body_faces }
    }

    /// Advances one step.
    pub fn step(&mut self) -> Result<StepReport> {
        crate::geometry::grid::on_pool(|| self.step_inner(None))
    }

    /// Advances one step and records on `tape` what the backward pass needs.
    pub fn step_taped(&mut self, tape: &mut crate::gradients::Tape) -> Result<StepReport> {
        crate::geometry::grid::on_pool(|| self.step_inner(Some(tape)))
    }

    /// The liquid signed distance from the particles (before extension into solids): the
    /// frozen one, or the current particles'.
    pub(crate) fn particle_phi(&self) -> Vec<f64> {
        match &self.frozen_phi {
            Some(phi) => phi.clone(),
            None => surface::liquid_sdf(
                &self.particles,
                &Bins::new(&self.particles, &self.grid),
                &self.grid,
                self.radius,
            ),
        }
    }

    fn step_inner(&mut self, mut tape: Option<&mut crate::gradients::Tape>) -> Result<StepReport> {
        let u_start = tape.as_ref().map(|_| self.u.clone());
        let bodies_start: Vec<crate::gradients::BodyState> =
            self.bodies.iter().map(crate::gradients::BodyState::of).collect();
        let dt = self.scene.time.dt;
        let grid = self.grid;
        let mut times = StageSeconds::default();
        let mut clock = Instant::now();
        let mut lap = |slot: &mut f64| {
            let now = Instant::now();
            *slot = (now - clock).as_secs_f64();
            clock = now;
        };

        // 3a. The solids where they are at the start of the step (bodies move in stage 6).
        let geo = self.geometry();
        lap(&mut times.geometry);

        // 0. Marker particles ride the current (divergence-free, extrapolated) field.
        let frozen = self.frozen_phi.is_some();
        if !frozen {
            surface::advect(&mut self.particles, &self.u, &grid, dt, &self.statics.node_sdf);
            surface::push_out_of_bodies(&mut self.particles, &self.bodies, 1e-3 * grid.dx);
        }
        if !frozen && self.scene.solver.density_correction {
            let inputs = DensityInputs {
                grid: &grid,
                weights: &geo.weights,
                node_sdf: &self.statics.node_sdf,
                centre_in_solid: &geo.centre_in_solid,
                radius: self.radius,
            };
            density::correct(&mut self.particles, &inputs, &self.scene.solver, self.step + 1)?;
            surface::push_out_of_bodies(&mut self.particles, &self.bodies, 1e-3 * grid.dx);
        }
        lap(&mut times.advect_particles);

        // 3. Where the liquid is now (with a frozen surface: where it was at the start). It
        // depends on the particles only, and tells advection which faces the step reads.
        let particle_phi = self.particle_phi();
        let mut phi = particle_phi.clone();
        surface::extend_into_solids(&mut phi, &grid, &geo.centre_in_solid);
        lap(&mut times.surface);

        // 1. Self-advection of the velocity, on the faces the rest of the step reads.
        let needed = needed_faces(&grid, &phi, &geo.body_faces);
        let mut u = advect(&self.u, &grid, dt, Some(&needed));
        lap(&mut times.advect_velocity);

        // 2. Gravity, on the liquid and on the bodies.
        let gravity = self.scene.fluid.gravity;
        add_gravity(&mut u, gravity, dt);
        for b in self.bodies.iter_mut().filter(|b| b.dynamic) {
            b.v += dt * crate::math::v3(gravity);
        }
        lap(&mut times.forces);

        // 4. Projection, coupled with the dynamic bodies.
        let solver = self.scene.solver.clone();
        let params =
            PressureParams { dt, density: self.scene.fluid.density, theta_min: solver.theta_min };
        let mut sys = PressureSystem::build(&grid, &phi, &geo.weights, params);
        let dynamic: Vec<usize> =
            (0..self.bodies.len()).filter(|&i| self.bodies[i].dynamic).collect();
        let mut couplings: Vec<BodyCoupling> = dynamic
            .iter()
            .map(|&i| {
                let b = &self.bodies[i];
                let jac = fractions::body_jacobian(&grid, &geo.body_faces[i], b.x);
                BodyCoupling::new(&sys.row_of_cell, &jac, dt_minv(b, dt))
            })
            .collect();
        let weak = solver.coupling == Coupling::Weak;
        if !weak {
            sys.bodies = std::mem::take(&mut couplings);
        }
        let couplings = if weak { &couplings } else { &sys.bodies };
        let v_start: Vec<[f64; 6]> =
            dynamic.iter().map(|&i| generalized_velocity(&self.bodies[i])).collect();
        // Contact inside the solve. Resolving contact only after the projection would leave
        // the liquid divergence-free around a body velocity that contact then changes (a
        // heavy body resting on the floor pumped (1 − ρ/ρ_b)·g·Δt of flow into the liquid
        // every step). So: solve, ask rapier what contact does to the bodies' new velocities,
        // and solve again with that change (`kick`) held as an impulse on the bodies, until
        // contact changes nothing; the liquid then moves with the body velocity that stands.
        let contact_on = self.contact_enabled();
        let mut kick = vec![[0.0f64; 6]; dynamic.len()];
        let mut contact_iterations = 0;
        let mut contact_residual = 0.0;
        let mut last_p: Option<Vec<f64>> = None;
        let u_advected = u;
        let (p, stats, mut u, mut valid, forces) = loop {
            let vel: Vec<[f64; 6]> = v_start
                .iter()
                .zip(&kick)
                .map(|(v, k)| std::array::from_fn(|d| v[d] + k[d]))
                .collect();
            let b = if weak {
                // Partitioned: the bodies are boundaries moving at their current velocity.
                let mut b = sys.rhs(&u_advected, &geo.weights, &[]);
                for (c, v) in couplings.iter().zip(&vel) {
                    c.add_jt(&v.map(|x| -x), &mut b);
                }
                b
            } else {
                sys.rhs(&u_advected, &geo.weights, &vel)
            };
            // Warm start: the last solve's pressure (this step's previous contact iteration,
            // or the last step's).
            let guess = match &last_p {
                Some(p) => p.clone(),
                None => sys.cell_of_row.iter().map(|&c| self.pressure[c as usize]).collect(),
            };
            let (p, stats) = sys.solve_from(
                &b,
                guess,
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
            let mut u = u_advected.clone();
            let valid = sys.update_velocity(&p, &mut u);
            let mut forces = Vec::with_capacity(dynamic.len());
            for ((coupling, &i), v) in couplings.iter().zip(&dynamic).zip(&vel) {
                let f = coupling.force(&p);
                let dv = coupling.dt_minv_times(&f);
                let body = &mut self.bodies[i];
                body.v = Vec3::new(v[0] + dv[0], v[1] + dv[1], v[2] + dv[2]);
                body.w = Vec3::new(v[3] + dv[3], v[4] + dv[4], v[5] + dv[5]);
                forces.push(BodyForce {
                    name: body.name.clone(),
                    force: [f[0], f[1], f[2]],
                    torque: [f[3], f[4], f[5]],
                });
            }
            if contact_on {
                let change = self.contact_change(&dynamic, dt);
                let largest = change.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs()));
                if largest > self.contact_tolerance(dt) {
                    if contact_iterations == MAX_CONTACT_ITERATIONS {
                        contact_residual = largest;
                        break (p, stats, u, valid, forces);
                    }
                    for (k, c) in kick.iter_mut().zip(&change) {
                        for d in 0..6 {
                            k[d] += c[d];
                        }
                    }
                    contact_iterations += 1;
                    last_p = Some(p);
                    continue;
                }
            }
            break (p, stats, u, valid, forces);
        };
        let mut flux = sys.fluid_flux(&u, &geo.weights);
        for (coupling, &i) in couplings.iter().zip(&dynamic) {
            coupling.add_jt(&generalized_velocity(&self.bodies[i]), &mut flux);
        }
        let max_divergence = flux.iter().fold(0.0f64, |m, f| m.max(f.abs())) / grid.dx.powi(3);
        let kinetic_energy =
            kinetic_energy(&u, &valid, &geo.weights, self.scene.fluid.density, grid.dx);
        lap(&mut times.pressure);

        // 5. Velocity correction: the bodies' velocity on the faces they cover (which then
        // count as known), extrapolation into air, zero in static solids and walls.
        crate::stages::extrapolate::apply_body_velocities(
            &mut u,
            &self.bodies,
            &geo.body_faces,
            &geo.weights,
            &grid,
        );
        crate::stages::extrapolate::mark_body_faces(&mut valid, &geo.body_faces);
        correct_velocity(
            &mut u,
            &mut valid,
            &self.statics.weights,
            &grid,
            solver.extrapolation_layers,
        );
        lap(&mut times.correct_velocity);

        if let Some(t) = tape.take() {
            t.steps.push(crate::gradients::StepRecord {
                u: u_start.expect("cloned when taping"),
                bodies: bodies_start,
                v_after: self.bodies.iter().map(generalized_velocity).collect(),
                p: p.clone(),
                phi: if self.frozen_phi.is_some() { Vec::new() } else { particle_phi },
                contact_kick: kick.clone(),
                body_faces: geo.body_faces.clone(),
            });
        }

        // 6. Rigid integration (or contact).
        self.move_bodies(dt)?;
        lap(&mut times.rigid);

        self.step += 1;
        if !u.is_finite() {
            return Err(Error::NonFinite { step: self.step, what: "the fluid velocity".into() });
        }
        for b in &self.bodies {
            if !(b.x.is_finite() && b.v.is_finite() && b.w.is_finite() && b.q.is_finite()) {
                return Err(Error::NonFinite { step: self.step, what: format!("body {}", b.name) });
            }
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
            liquid_volume: self.liquid_volume(),
            max_speed: self.max_liquid_speed(&sys),
            kinetic_energy,
            bodies: forces,
            contact_iterations,
            contact_residual,
            stage_seconds: times,
        })
    }

    /// Whether rapier contact is on and could act this step (see [`contact_possible`]).
    fn contact_enabled(&self) -> bool {
        #[cfg(feature = "contact")]
        {
            self.scene.contact.enabled
                && contact_possible(&self.bodies, self.grid.size(), self.scene.time.dt)
        }
        #[cfg(not(feature = "contact"))]
        false
    }

    /// What rapier's contact step would do to each dynamic body's [v; ω] now: its
    /// velocity after the step minus before.
    fn contact_change(&self, dynamic: &[usize], dt: f64) -> Vec<[f64; 6]> {
        #[cfg(feature = "contact")]
        {
            let mut after = self.bodies.clone();
            ContactWorld::new(self.grid.size(), &after, &self.scene.contact).step(&mut after, dt);
            dynamic
                .iter()
                .map(|&i| {
                    let (a, b) =
                        (generalized_velocity(&after[i]), generalized_velocity(&self.bodies[i]));
                    std::array::from_fn(|d| a[d] - b[d])
                })
                .collect()
        }
        #[cfg(not(feature = "contact"))]
        {
            let _ = dt;
            vec![[0.0; 6]; dynamic.len()]
        }
    }

    /// A contact velocity change below this (a thousandth of what gravity adds in a step) is
    /// taken as none.
    fn contact_tolerance(&self, dt: f64) -> f64 {
        1e-3 * crate::math::v3(self.scene.fluid.gravity).length().max(1.0) * dt
    }

    /// Stage 6: integrate the bodies, through rapier when contact is on; without contact, a
    /// body that leaves the tank is an error.
    fn move_bodies(&mut self, dt: f64) -> Result<()> {
        #[cfg(feature = "contact")]
        if self.scene.contact.enabled && contact_possible(&self.bodies, self.grid.size(), dt) {
            // A fresh world per step: the fluid step changed every velocity, and rebuilding
            // a handful of colliders costs microseconds.
            ContactWorld::new(self.grid.size(), &self.bodies, &self.scene.contact)
                .step(&mut self.bodies, dt);
            return Ok(());
        }
        let size = self.grid.size();
        for b in self.bodies.iter_mut() {
            b.integrate(dt);
            let (lo, hi) = b.bounds();
            if lo.min_element() < 0.0 || (hi - size).max_element() > 0.0 {
                return Err(Error::BodyLeftTank {
                    step: self.step + 1,
                    body: b.name.clone(),
                    bounds: (lo.to_array(), hi.to_array()),
                });
            }
        }
        Ok(())
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
        self.phi.iter().enumerate().filter(|(_, p)| **p < 0.0).map(|(c, _)| c)
    }
}

/// Solves with contact impulses per step at most (see the projection in `step_inner`); a
/// contact that still changes the velocities after them is left to the contact stage.
/// rapier's iterative, soft contact solve answers each call with some noise (a few mm/s and
/// mrad/s on a cube resting flat), so the iteration seldom meets its tolerance exactly: a
/// resting cube stirred the liquid to 0.38 m/s with no extra solve, 0.06 with one, 0.018
/// with two, 0.0096 with four and 0.0094 with eight.
const MAX_CONTACT_ITERATIONS: usize = 4;

/// Whether any body can touch a wall or another body within the next `dt`: each body's
/// bounding box, grown by the farthest any of its points can move (|v|·Δt + |ω|·Δt times
/// the box diagonal, which bounds the distance from the centre of mass) plus a margin of a
/// hundredth of the diagonal as a safety margin, reaches a wall or another grown box.
/// (rapier's predictive contacts start further out, but act only on bodies that would close
/// the gap within the step, which the reach covers.) When none can, contact
/// is no work: the bodies fly freely (the same integration as without contact), and rapier
/// is not called.
pub fn contact_possible(bodies: &[RigidBody], domain: Vec3, dt: f64) -> bool {
    let grown: Vec<(Vec3, Vec3, bool)> = bodies
        .iter()
        .map(|b| {
            let (lo, hi) = b.bounds();
            let diag = (hi - lo).length();
            let reach = if b.dynamic { (b.v.length() + b.w.length() * diag) * dt } else { 0.0 };
            let pad = reach + 0.01 * diag;
            (lo - Vec3::splat(pad), hi + Vec3::splat(pad), b.dynamic)
        })
        .collect();
    let touches_wall = |(lo, hi, dynamic): &(Vec3, Vec3, bool)| {
        *dynamic && (lo.min_element() <= 0.0 || (*hi - domain).max_element() >= 0.0)
    };
    if grown.iter().any(touches_wall) {
        return true;
    }
    grown.iter().enumerate().any(|(i, a)| {
        grown[i + 1..].iter().any(|b| {
            (a.2 || b.2)
                && (0..3).all(|d| {
                    crate::math::comp(a.0, d) <= crate::math::comp(b.1, d)
                        && crate::math::comp(b.0, d) <= crate::math::comp(a.1, d)
                })
        })
    })
}

/// ½ Σ ρ·w_f·dx³·u_f² over the faces the projection updated. Sequential on purpose: the
/// sum is cheap and its order fixed.
fn kinetic_energy(
    u: &Mac,
    valid: &[Vec<u8>; 3],
    weights: &[Vec<f64>; 3],
    rho: f64,
    dx: f64,
) -> f64 {
    let mut e = 0.0;
    for a in 0..3 {
        for (f, &uf) in u.c[a].iter().enumerate() {
            if valid[a][f] != 0 {
                e += weights[a][f] * uf * uf;
            }
        }
    }
    0.5 * rho * dx.powi(3) * e
}

/// `[v; ω]`.
pub fn generalized_velocity(b: &RigidBody) -> [f64; 6] {
    [b.v.x, b.v.y, b.v.z, b.w.x, b.w.y, b.w.z]
}

/// Δt·M_S⁻¹ for a body: `diag(Δt/m·I, Δt·(R I Rᵀ)⁻¹)`.
pub fn dt_minv(b: &RigidBody, dt: f64) -> [[f64; 6]; 6] {
    let mut m = [[0.0; 6]; 6];
    for d in 0..3 {
        m[d][d] = dt / b.mass;
    }
    let inv = b.world_inertia().inverse();
    for r in 0..3 {
        for c in 0..3 {
            m[3 + r][3 + c] = dt * inv.col(c).to_array()[r];
        }
    }
    m
}
