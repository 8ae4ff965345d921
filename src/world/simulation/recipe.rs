//! The step as a recipe: the stages of [`Stage::ALL`] in their order, each a call into
//! `stages/` (where its adjoint sits beside it). The backward pass
//! (`gradients/backward.rs`) runs the same stages' adjoints in the reverse order.

use super::stepping::{largest_magnitude, Pressures, LARGEST};
use super::{volume_warning, BodyHandle, Simulation, EXTERNAL_REACH};
use crate::error::{Error, Result};
use crate::geometry::body::{BodyState, RigidBody};
use crate::geometry::grid::Mac;
use crate::math::pool;
use crate::math::{v3, Twist, TwistParts};
use crate::solvers::cg::CgStats;
use crate::stages::band::Band;
use crate::stages::contact::contact_possible;
use crate::stages::density::DensityStats;
use crate::stages::extrapolate::{
    correct_with_bodies, surface_faces, AirBodyFaces, Correction, ExtrapolationLayers, SurfaceFaces,
};
use crate::stages::forces::body_velocity;
use crate::stages::particles::{ParticleRecord, ParticleStage, Potential};
use crate::stages::project::{project, HeldContact, HeldSolve, Projection};
use crate::stages::rigid::{integrate, Tank};
use crate::stages::surface::{self, Bins, Pockets};
use crate::stages::system::{
    generalized_velocity, predicted_velocity, volume_source, Geometry, StepSystem,
};
use crate::stages::{Stage, StageClock, StageSeconds};
use crate::world::step::{kinetic_energy, BodyForce, Energy, StepParams, StepReport};
use crate::world::tape::{StepRecord, Tape};
use rayon::prelude::*;

/// A contact velocity change below this (a thousandth of what gravity adds in a step) is
/// taken as none.
fn contact_tolerance(gravity: [f64; 3], dt: f64) -> f64 {
    1e-3 * v3(gravity).length().max(1.0) * dt
}

/// The stages' timings of one step.
struct Timed {
    clock: StageClock,
    times: StageSeconds,
}

impl Timed {
    fn lap(&mut self, stage: Stage) {
        self.clock.lap(stage, &mut self.times);
    }
}

impl Simulation {
    /// [`Simulation::step_inner`]'s stages, in the order of [`Stage::ALL`].
    pub(super) fn step_stages(
        &mut self,
        dt: f64,
        tape: Option<&mut Tape>,
        mut pressures: Pressures,
        report: bool,
    ) -> Result<StepReport> {
        let start = tape
            .as_ref()
            .map(|_| (self.u.clone(), self.bodies.iter().map(RigidBody::state).collect()));
        let taped = start.is_some();
        let mut timed = Timed { clock: StageClock::new(), times: StageSeconds::default() };
        let (grid, gravity) = (self.grid, self.settings.fluid.gravity);

        let geometry = self.geometry();
        let (volume_errors, warnings) = self.check_volumes(&geometry);
        timed.lap(Stage::Geometry);

        // Band, AdvectParticles, Density (nothing with a frozen surface).
        let (mut record, density) =
            self.move_particles(&geometry, dt, taped, &mut pressures, &mut timed)?;

        let phi = self.surface(record.as_mut(), &geometry);
        let taped_phi = if taped && self.frozen_phi.is_none() { phi.clone() } else { Vec::new() };
        let crowding = self.controlled_density();
        timed.lap(Stage::Surface);

        // A replayed step is given its pressures: its system needs no operator.
        let solves = !matches!(pressures, Pressures::Replay(_));
        let sys = self.assemble(geometry, phi, crowding.as_deref(), dt, solves);
        timed.lap(Stage::Assemble);

        // The pressure solve's preconditioner is factored beside the advection, which does
        // not read it (both are loops too short to keep two threads busy alone).
        let out = self.spare.velocity(&grid);
        let how = self.settings.solver.linear();
        let (u_hat, ()) = rayon::join(
            || predicted_velocity(&self.u, &grid, dt, gravity, &sys.needed, out),
            || sys.pressure.prepare(&how),
        );
        timed.lap(Stage::AdvectVelocity);

        let v_hat: Vec<Twist> =
            sys.coupled.iter().map(|&i| body_velocity(&self.bodies[i], v3(gravity), dt)).collect();
        timed.lap(Stage::Forces);

        // The correction's extrapolation layers read the system's masks only: found beside
        // the solve, on a thread of their own when the step is serial, else in what the
        // solve's short loops leave of the other worker.
        let (layers, blend) =
            (self.settings.solver.extrapolation_layers, self.settings.solver.blend());
        // The faces the extrapolation knows in part (none unless `solver.surface_blend`).
        let (weights, statics) = (&sys.geometry.weights, &self.statics.weights);
        let faces = &sys.geometry.body_faces;
        let surface = surface_faces(&sys.pressure, &sys.phi, faces, weights, statics, blend);
        let (projected, layered) = pool::alongside(
            || self.pressure_stage(&sys, u_hat, &v_hat, dt, &mut pressures),
            || {
                let projected = sys.projected_mask();
                let faces = &sys.geometry.body_faces;
                let layered = ExtrapolationLayers::new(&projected, faces, &grid, layers);
                (projected, layered)
            },
        );
        let (mut proj, mut u, contact) = projected?;
        let report = report && solves;
        let (max_divergence, kinetic_energy) = self.projected_measures(&sys, &u, &proj, report);
        timed.lap(Stage::Pressure);

        let air_body_faces = self.correct_velocity(&sys, &mut u, layered, &surface);
        timed.lap(Stage::CorrectVelocity);

        // Whether rapier integrates the bodies: contact possible at their new velocities.
        let contact_moves = self.contact_on(dt);
        if let Pressures::Record(solves) = &mut pressures {
            solves.contact |= contact || contact_moves;
        }
        if let (Some(t), Some(start)) = (tape, start) {
            // The contact iteration's replaced solves: the record's alone from here.
            let held = std::mem::take(&mut proj.held);
            let taped = Taped { phi: taped_phi, air_body_faces, particles: record, held };
            let contact = (contact, contact_moves);
            t.steps.push(self.record(start, &proj, &sys, taped, contact));
        }
        self.rigid(dt, contact_moves)?;
        timed.lap(Stage::Rigid);

        let measured =
            Measured { volume_errors, warnings, density, max_divergence, kinetic_energy };
        self.finish(dt, u, sys, proj, measured, timed.times, report)
    }

    /// [`Stage::Assemble`]: the step's system from the solids where they are and φ_L; with
    /// volume control (the particles' density per cell, `crowding`) its sources.
    fn assemble(
        &self,
        geometry: Geometry,
        phi: Vec<f64>,
        crowding: Option<&[f64]>,
        dt: f64,
        solves: bool,
    ) -> StepSystem {
        let grid = self.grid;
        let params = StepParams { solves, ..self.step_params(dt) };
        let memory = self.spare.systems().take();
        let mut sys = StepSystem::assemble(&grid, &self.bodies, geometry, phi, params, memory);
        if let (Some(d), true) = (crowding, sys.pressure.has_air) {
            let rate = self.settings.solver.volume_rate();
            let cell = grid.dx.powi(3);
            let rows = &sys.pressure.cell_of_row;
            sys.volume_source =
                rows.iter().map(|&c| volume_source(rate, d[c as usize], cell, dt)).collect();
        }
        sys
    }

    /// [`Stage::CorrectVelocity`] on `u` (`layered`: the faces the projection updated and
    /// the extrapolation's layers, found beside the solve; `surface`: the faces it knows in
    /// part); returns what the backward pass needs of it.
    fn correct_velocity(
        &self,
        sys: &StepSystem,
        u: &mut Mac,
        layered: ([Vec<u8>; 3], ExtrapolationLayers),
        surface: &SurfaceFaces,
    ) -> AirBodyFaces {
        let (projected, layers) = layered;
        let step = Correction {
            bodies: &self.bodies,
            faces: &sys.geometry.body_faces,
            weights: &sys.geometry.weights,
            static_weights: &self.statics.weights,
            grid: &self.grid,
        };
        let layer_count = self.settings.solver.extrapolation_layers;
        correct_with_bodies(u, &projected, Some(&layers), surface, step, layer_count)
    }

    /// The step's record for the backward pass, from its start (`start`: the fluid velocity
    /// and the bodies' states), taken before [`Stage::Rigid`].
    fn record(
        &self,
        (u, bodies): (Mac, Vec<BodyState>),
        proj: &Projection,
        sys: &StepSystem,
        taped: Taped,
        (held, rigid_contact): (bool, bool),
    ) -> StepRecord {
        StepRecord {
            u,
            bodies,
            v_hat: proj.v_hat.clone(),
            v_after: self.bodies.iter().map(generalized_velocity).collect(),
            p: proj.p.clone(),
            phi: taped.phi,
            body_faces: sys.geometry.body_faces.clone(),
            loads: self.bodies.iter().map(RigidBody::load).collect(),
            air_body_faces: taped.air_body_faces,
            contact: held || rigid_contact,
            rigid_contact,
            held: taped.held,
            particles: taped.particles,
            volume_control: !sys.volume_source.is_empty(),
        }
    }

    /// [`Stage::Rigid`]: the bodies integrated, through rapier when `contact`.
    fn rigid(&mut self, dt: f64, contact: bool) -> Result<()> {
        let grid = self.grid;
        let tank = Tank { size: grid.size(), external_reach: EXTERNAL_REACH * grid.dx };
        let contact = contact.then_some(&self.settings.contact);
        integrate(&mut self.bodies, dt, tank, contact, self.step + 1)
    }

    /// Whether rapier contact is on and could act this step (see [`contact_possible`]).
    fn contact_on(&self, dt: f64) -> bool {
        self.settings.contact.enabled && contact_possible(&self.bodies, self.grid.size(), dt)
    }

    /// [`Stage::Geometry`]'s check: each body's volume error on the grid, and a warning
    /// for a body whose face fractions cannot hold its volume.
    fn check_volumes(&mut self, geometry: &Geometry) -> (Vec<f64>, Vec<String>) {
        let grid = self.grid;
        let volume_errors: Vec<f64> = self
            .bodies
            .iter()
            .zip(&geometry.body_faces)
            .map(|(b, f)| f.volume_error(&grid, b.volume()))
            .collect();
        let mut warnings = Vec::new();
        let found: Vec<(BodyHandle, String)> = self
            .bodies
            .iter()
            .zip(&self.handles)
            .zip(&volume_errors)
            .filter_map(|((b, h), e)| Some((*h, volume_warning(b, *e, grid.dx)?)))
            .collect();
        for (h, w) in found {
            self.warn_about(&mut warnings, "volume", h, w);
        }
        (volume_errors, warnings)
    }

    /// The stage list's particle part ([`Stage::Band`], [`Stage::AdvectParticles`],
    /// [`Stage::Density`]; nothing with a frozen surface). Returns what the backward pass
    /// needs when `taped`.
    fn move_particles(
        &mut self,
        geometry: &Geometry,
        dt: f64,
        taped: bool,
        pressures: &mut Pressures,
        timed: &mut Timed,
    ) -> Result<(Option<ParticleRecord>, DensityStats)> {
        if self.frozen_phi.is_some() {
            return Ok((None, DensityStats::default()));
        }
        let change = self.update_band(geometry, dt);
        timed.lap(Stage::Band);
        let step = self.step + 1;
        let density_on = self.settings.solver.density_correction;
        // A re-run takes each density pass's potential from the record, in order.
        let mut next_pass = match pressures {
            Pressures::Replay(replay) if density_on => Some(|| replay.next_density(step)),
            _ => None,
        };
        let potential = match next_pass.as_mut() {
            Some(next) => Potential::Recorded(next),
            None => Potential::Solve,
        };
        let mut particles = std::mem::take(&mut self.particles);
        let (substeps, start, moved, settled) = {
            let stage = ParticleStage {
                grid: &self.grid,
                dt,
                u: &self.u,
                bodies: &self.bodies,
                node_sdf: &self.statics.node_sdf,
                margin: self.push_margin(),
                density: self.density_inputs(geometry, &self.bodies),
                step,
            };
            let substeps = stage.substeps(self.settings.solver.particle_substeps);
            let start = taped.then(|| particles.clone());
            let moved = stage.advect(&mut particles, substeps, taped);
            timed.lap(Stage::AdvectParticles);
            (substeps, start, moved, stage.settle(&mut particles, potential))
        };
        self.particles = particles;
        let settled = settled?;
        if let (Pressures::Record(solves), true) = (&mut *pressures, density_on) {
            for (q, iterations) in &settled.passes {
                solves.push_density(q.clone(), *iterations);
            }
        }
        timed.lap(Stage::Density);
        let stats = settled.stats;
        let record = start.zip(moved).map(|(start, moved)| ParticleRecord {
            start,
            substeps,
            moved,
            density: settled.into_potentials(),
            nearest: Vec::new(),
            pockets: Pockets::default(),
            change,
            deep: self.band.as_ref().map(|b| b.deep.clone()),
        });
        Ok((record, stats))
    }

    /// [`Stage::Surface`]: φ_L where the particles are now (with a frozen surface: where it
    /// was at the start). Taped, the record keeps the particle each cell's φ is the distance
    /// to.
    fn surface(
        &mut self,
        mut record: Option<&mut ParticleRecord>,
        geometry: &Geometry,
    ) -> Vec<f64> {
        let weights = &geometry.weights;
        // Where the step reads φ's value (the soft minimum's sum is made there only).
        let near_solids = self.value_reads(geometry);
        let reads = near_solids.as_deref().map(|near_solids| surface::Reads { near_solids });
        let mut phi = match record.as_deref_mut() {
            Some(r) => {
                let bins = Bins::new(&self.particles, &self.grid);
                let deep = self.band.as_deref().map(Band::deep);
                let model = self.surface_model();
                let ghosts = self.ghosts_at(&self.bodies);
                let (phi, nearest) = surface::liquid_sdf_nearest(
                    &self.particles,
                    &bins,
                    &ghosts,
                    &self.grid,
                    &model,
                    deep,
                    reads,
                );
                r.nearest = nearest;
                phi
            }
            // Nothing reads the last step's φ_L after the band's update: its memory takes
            // this step's, which the step's system holds until the step ends (a failed step
            // gives it back, see `Simulation::step_inner`).
            None => {
                let mut phi = std::mem::take(&mut self.phi);
                self.particle_phi_into(&mut phi, reads);
                phi
            }
        };
        // A frozen surface keeps the φ_L it was frozen with.
        let close = self.settings.solver.close_pockets.filter(|k| *k > 0.0);
        if let (Some(k), None) = (close, &self.frozen_phi) {
            let pockets = surface::close_pockets(&mut phi, &self.grid, weights, k);
            if let Some(r) = record {
                r.pockets = pockets;
            }
        }
        phi
    }

    /// With volume control (`solver.volume_control`) and the surface moving, the marker
    /// particles' density per cell (in cells) where the particle stages left them (the
    /// [`Stage::Surface`] stage measures it); None otherwise.
    fn controlled_density(&self) -> Option<Vec<f64>> {
        let on = self.settings.solver.volume_rate() > 0.0 && self.frozen_phi.is_none();
        on.then(|| {
            let base = self.band.as_ref().map(|b| b.density.as_slice());
            let ppc = self.settings.solver.particles_per_cell;
            surface::particle_density(&self.particles, &self.grid, ppc, base)
        })
    }

    /// [`Stage::Pressure`]: the projection, with contact held inside it when contact is
    /// possible for the bodies moving at their velocities `v_hat` before the pressure acts;
    /// sets the coupled bodies' velocities and fluid forces. Returns the projection, the
    /// updated field and whether contact was held.
    fn pressure_stage(
        &mut self,
        sys: &StepSystem,
        u_hat: Mac,
        v_hat: &[Twist],
        dt: f64,
        pressures: &mut Pressures,
    ) -> Result<(Projection, Mac, bool)> {
        let contact = self.settings.contact.enabled && {
            let mut moving = self.bodies.clone();
            for (&i, v) in sys.coupled.iter().zip(v_hat) {
                (moving[i].v, moving[i].w) = (v.linear(), v.angular());
            }
            contact_possible(&moving, self.grid.size(), dt)
        };
        let held = contact.then(|| HeldContact {
            bodies: &self.bodies,
            size: self.grid.size(),
            settings: &self.settings.contact,
            tolerance: contact_tolerance(self.settings.fluid.gravity, dt),
        });
        let mut solve = |u_hat: &Mac, vel_e: &[Twist], warm: Option<Vec<f64>>| {
            self.solve_pressure(sys, u_hat, vel_e, warm, pressures)
        };
        let (proj, u) = project(sys, u_hat, v_hat, dt, held, &mut solve)?;
        for ((&i, v), f) in sys.coupled.iter().zip(&proj.v_after).zip(&proj.forces) {
            let b = &mut self.bodies[i];
            (b.v, b.w) = (v.linear(), v.angular());
            self.fluid_forces[i] = *f;
        }
        // A kinematic body's force is what its motion costs: J·p.
        for (i, c, _) in &sys.kinematic {
            self.fluid_forces[*i] = c.force(&proj.p);
        }
        Ok((proj, u, contact))
    }

    /// One pressure solve of the step's projection, as `pressures` says: solved from `warm`
    /// (or the last step's pressure), and kept when recording; or taken from the record.
    fn solve_pressure(
        &self,
        sys: &StepSystem,
        u_hat: &Mac,
        vel_e: &[Twist],
        warm: Option<Vec<f64>>,
        pressures: &mut Pressures,
    ) -> Result<(Vec<f64>, CgStats)> {
        let step = self.step + 1;
        let how = self.settings.solver.linear();
        let (p, stats) = match pressures {
            Pressures::Replay(replay) => replay.next(sys.pressure.len(), step)?,
            _ => {
                let b = sys.rhs(u_hat, vel_e);
                // Warm start: the last solve's pressure (this step's previous contact
                // iteration, or the last step's).
                let guess = warm.unwrap_or_else(|| {
                    let cells = &sys.pressure.cell_of_row;
                    let min = crate::math::par::MIN_LEN;
                    let gather = |&c: &u32| self.pressure[c as usize];
                    cells.par_iter().with_min_len(min).map(gather).collect()
                });
                sys.pressure.solve_from(&b, guess, &how)
            }
        };
        if let Pressures::Record(solves) = pressures {
            solves.push(p.clone(), stats);
        }
        if !stats.relative_residual.is_finite() {
            return Err(Error::NonFinite {
                step,
                what: "the pressure solve's residual is not finite".into(),
            });
        }
        if !stats.converged {
            return Err(Error::NotConverged {
                solve: crate::error::Solve::Pressure,
                step,
                iterations: stats.iterations,
                residual: stats.relative_residual,
                tolerance: how.tolerance,
            });
        }
        Ok((p, stats))
    }

    /// What only the report reads of the projection (the largest divergence left, the
    /// liquid's kinetic energy); NaN when not `report` (a gradient's forward pass and a
    /// replayed re-run drop their reports).
    fn projected_measures(
        &self,
        sys: &StepSystem,
        u: &Mac,
        proj: &Projection,
        report: bool,
    ) -> (f64, f64) {
        if !report {
            return (f64::NAN, f64::NAN);
        }
        let mut flux = sys.flux(u, &proj.v_after);
        // The divergence volume control asked for is not an error of the solve.
        for (f, q) in flux.iter_mut().zip(&sys.volume_source) {
            *f -= q;
        }
        let rho = self.settings.fluid.density;
        let dx3 = self.grid.dx.powi(3);
        (
            flux.iter().fold(0.0f64, |m, f| m.max(f.abs())) / dx3,
            kinetic_energy(u, &sys.pressure, &sys.geometry.weights, rho),
        )
    }

    /// The end of a step: the state it leaves is checked (finite, and below [`LARGEST`]: a
    /// larger one only overflows a step later), then kept, and reported.
    #[allow(clippy::too_many_arguments)]
    fn finish(
        &mut self,
        dt: f64,
        u: Mac,
        sys: StepSystem,
        proj: Projection,
        measured: Measured,
        stage_seconds: StageSeconds,
        report: bool,
    ) -> Result<StepReport> {
        let step = self.step + 1;
        let fluid = largest_magnitude(&u);
        if fluid.is_nan() || fluid >= LARGEST {
            let what = format!("the fluid velocity is not finite (up to {fluid:.3e} m/s)");
            return Err(Error::NonFinite { step, what });
        }
        for b in &self.bodies {
            let state = [b.x, b.v, b.w].map(|v| v.abs().max_element());
            if !(state.iter().all(|x| *x < LARGEST) && b.q.is_finite()) {
                return Err(Error::NonFinite {
                    step,
                    what: format!(
                        "body {}'s state is not finite (x up to {:.3e} m, v {:.3e} m/s, ω {:.3e} \
                         rad/s)",
                        b.name, state[0], state[1], state[2]
                    ),
                });
            }
        }
        self.step = step;
        self.time += dt;
        self.spare.keep_velocity(std::mem::replace(&mut self.u, u));
        self.largest_u = Some(fluid);
        sys.pressure.scatter_into(&proj.p, &mut self.pressure);
        self.phi = sys.phi;
        let bodies = sys
            .coupled
            .iter()
            .zip(&proj.forces)
            .map(|(&i, f)| BodyForce {
                name: self.bodies[i].name.clone(),
                force: [f[0], f[1], f[2]],
                torque: [f[3], f[4], f[5]],
                volume_error: measured.volume_errors[i],
            })
            .collect();
        let liquid_cells = sys.pressure.len();
        let (max_speed, liquid_volume) = if report {
            (self.max_liquid_speed(&sys.pressure.cell_of_row), self.liquid_volume())
        } else {
            (f64::NAN, f64::NAN)
        };
        self.spare.keep_system(sys.geometry, sys.pressure);
        let energy = if report { self.energy() } else { Energy::default() };
        Ok(StepReport {
            step: self.step,
            time: self.time,
            liquid_cells,
            cg_iterations: proj.stats.iterations,
            cg_relative_residual: proj.stats.relative_residual,
            density_cg_iterations: measured.density.cg_iterations,
            max_divergence: measured.max_divergence,
            liquid_volume,
            max_speed,
            kinetic_energy: measured.kinetic_energy,
            energy,
            bodies,
            contact_iterations: proj.hold.iterations,
            contact_residual: proj.hold.residual,
            stage_seconds,
            warnings: measured.warnings,
        })
    }
}

/// What the stages before [`Stage::Rigid`] leave for a taped step's record.
struct Taped {
    phi: Vec<f64>,
    air_body_faces: AirBodyFaces,
    particles: Option<ParticleRecord>,
    held: Vec<HeldSolve>,
}

/// What a step measured along the way for its report.
struct Measured {
    volume_errors: Vec<f64>,
    warnings: Vec<String>,
    density: DensityStats,
    max_divergence: f64,
    kinetic_energy: f64,
}
