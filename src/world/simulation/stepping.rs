//! The step: a pipeline of named stages (the paper's Algorithm 2):
//!
//! 3a. where the solids are: the bodies' face fractions, J, the combined weights;
//! 0. advect the marker particles through uₜ (RK2), pushed out of solids;
//! 3. rebuild the liquid signed distance φ_L from the particles, and assemble the step's
//!    system ([`StepSystem::assemble`]);
//! 1. advect the velocity semi-Lagrangianly, on the faces the step reads;
//! 2. add gravity (and the bodies' external forces);
//! 4. project: solve the coupled pressure system (with contact held inside it), update the
//!    velocity and the bodies;
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

use super::{volume_warning, BodyHandle, Simulation, EXTERNAL_REACH};
use crate::error::{Error, Result};
use crate::geometry::body::{BodyState, Motion, RigidBody};
use crate::geometry::grid::Mac;
use crate::math::pool::{run_spread, Spread, SERIAL_BELOW};
use crate::math::{v3, Vec3};
use crate::stages::band::Band;
use crate::stages::contact::{contact_possible, hold_contact, ContactChange, ContactHold};
use crate::stages::density::{self, DensityInputs, DensityStats};
use crate::stages::extrapolate::correct_with_bodies;
use crate::stages::forces::body_velocity;
use crate::stages::pressure::PressureParams;
use crate::stages::surface::{self, Bins, SurfaceModel};
use crate::world::step::{
    generalized_velocity, kinetic_energy, predicted_velocity, BodyForce, Energy, Geometry,
    StageSeconds, StepParams, StepReport, StepSystem,
};
use crate::world::tape::{ParticleRecord, Replay, Solves, StepRecord, Tape};
use rayon::prelude::*;
use std::ops::ControlFlow;
use std::sync::Arc;
use std::time::Instant;

/// A contact velocity change below this (a thousandth of what gravity adds in a step) is
/// taken as none.
fn contact_tolerance(gravity: [f64; 3], dt: f64) -> f64 {
    1e-3 * v3(gravity).length().max(1.0) * dt
}

/// The largest speed (m/s, rad/s) or coordinate (m) a step takes: beyond it the state is
/// taken as blown up. Far above anything physical, and far enough below f64's range that the
/// solve's sums of squares over a grid of 512³ cells cannot overflow (1e100² · 1.3e8 < 1e308).
const LARGEST: f64 = 1e100;

/// The largest |u| over every face, NaN if one is NaN: one parallel pass for both checks.
fn largest_magnitude(u: &Mac) -> f64 {
    u.max_abs_or_nan()
}

/// What every failed step puts back (see [`Simulation::step_inner`]), rollback or not: the
/// bodies, their fluid forces, the step count and the time. The marker particles and the
/// narrow band are [`Undo`]'s, kept only when [`Simulation::rollback`] is on (their copy costs
/// 24 bytes a particle and 21 a cell every step).
struct BodyUndo {
    bodies: Vec<RigidBody>,
    fluid_forces: Vec<[f64; 6]>,
    step: usize,
    time: f64,
}

impl BodyUndo {
    fn of(sim: &Simulation) -> BodyUndo {
        BodyUndo {
            bodies: sim.bodies.clone(),
            fluid_forces: sim.fluid_forces.clone(),
            step: sim.step,
            time: sim.time,
        }
    }

    fn restore(self, sim: &mut Simulation) {
        sim.bodies = self.bodies;
        sim.fluid_forces = self.fluid_forces;
        sim.step = self.step;
        sim.time = self.time;
    }
}

/// Where a step's pressure solves (and density projection potentials) come from.
enum Pressures<'a, 'b> {
    /// Solved.
    Solve,
    /// Solved, and kept in order (a checkpointed forward pass).
    Record(&'a mut Solves),
    /// Taken in order from the record of the same steps from the same state (their re-run).
    Replay(&'a mut Replay<'b>),
}

/// What the projection (stage 4) leaves.
struct Projection {
    p: Vec<f64>,
    stats: crate::solvers::cg::CgStats,
    /// Per coupled body: [v; ω] the solve started from (with the contact kick) and after it,
    /// and the pressure force and torque J·p.
    v_hat: Vec<[f64; 6]>,
    v_after: Vec<[f64; 6]>,
    forces: Vec<[f64; 6]>,
    hold: ContactHold,
}

/// What a step changes before it can fail, kept so that a step that fails leaves the
/// simulation as it was (see [`Simulation::set_rollback`]): the marker particles and the
/// narrow band (stage 0; neither with a frozen surface), φ_L (whose memory the step builds
/// into), the bodies (stages 4 and 6), their fluid forces, the step count and the time. The
/// fluid velocity and the pressure are replaced only once the step has succeeded.
struct Undo {
    particles: Option<Vec<Vec3>>,
    band: Option<Arc<Band>>,
    phi: Vec<f64>,
    bodies: Vec<BodyState>,
    fluid_forces: Vec<[f64; 6]>,
    step: usize,
    time: f64,
}

impl Undo {
    /// What `sim`'s next step may change.
    fn take(sim: &Simulation) -> Undo {
        let moving = sim.frozen_phi.is_none();
        Undo {
            particles: moving.then(|| sim.particles.clone()),
            // Shared until the band's update changes it, which then copies it.
            band: if moving { sim.band.clone() } else { None },
            phi: sim.phi.clone(),
            bodies: sim.bodies.iter().map(RigidBody::state).collect(),
            fluid_forces: sim.fluid_forces.clone(),
            step: sim.step,
            time: sim.time,
        }
    }

    /// Puts `sim` back as it was.
    fn restore(self, sim: &mut Simulation) {
        if let Some(p) = self.particles {
            sim.particles = p;
            sim.band = self.band;
        }
        sim.phi = self.phi;
        for (b, s) in sim.bodies.iter_mut().zip(&self.bodies) {
            b.set_state(s);
        }
        sim.fluid_forces = self.fluid_forces;
        sim.step = self.step;
        sim.time = self.time;
    }
}

impl Simulation {
    /// The largest step [`Simulation::advance`] takes now: the fixed step, or less where the
    /// fastest liquid face or body point, plus what gravity can add within a cell
    /// (√(dx·|g|), after Bridson), would cross more than `solver.cfl` cells. The liquid's
    /// faces are those next to a cell the last step counted as liquid: the extrapolated air
    /// beyond them moves nothing (it read 7.4 m/s where the liquid moved at 2 m/s, and
    /// halved the step for nothing).
    pub fn stable_dt(&self) -> f64 {
        let dx = self.grid.dx;
        let body_speed = self
            .bodies
            .iter()
            .map(|b| {
                let (lo, hi) = b.bounds();
                b.v.length() + b.w.length() * 0.5 * (hi - lo).length()
            })
            .fold(0.0, f64::max);
        // Sizes as the largest component (a length would overflow first).
        let size = |v: Vec3| v.abs().max_element();
        let g = size(v3(self.settings.fluid.gravity));
        let speed = self.max_liquid_face_speed().max(body_speed) + (dx * g).sqrt();
        let limit = self.settings.solver.cfl * dx / speed;
        if limit.is_finite() {
            self.settings.dt.min(limit)
        } else {
            self.settings.dt
        }
    }

    /// Advances by `frame_dt` seconds in as many steps as [`Simulation::stable_dt`] asks for
    /// (a game or robot loop's frame). Each step is a step of the same map as
    /// [`Simulation::step`] with a shorter Δt; gradients use the fixed-Δt path. A step that
    /// fails is rolled back (see [`Simulation::step`]); the frame's steps before it stay.
    pub fn advance(&mut self, frame_dt: f64) -> Result<Vec<StepReport>> {
        self.advance_while(frame_dt, |_| ControlFlow::Continue(()))
    }

    /// [`Simulation::advance`], asking `between` after each step whether to go on: a
    /// [`ControlFlow::Break`] ends the frame there, with the steps taken so far (an
    /// interrupted frame, for a caller that watches for a signal between steps).
    pub fn advance_while(
        &mut self,
        frame_dt: f64,
        mut between: impl FnMut(&StepReport) -> ControlFlow<()>,
    ) -> Result<Vec<StepReport>> {
        if !(frame_dt.is_finite() && frame_dt > 0.0) {
            return Err(Error::InvalidSettings {
                key: "frame_dt".into(),
                message: format!("must be a positive number, got {frame_dt}"),
            });
        }
        let mut left = frame_dt;
        let mut reports = Vec::new();
        while left > 1e-12 * frame_dt {
            let n = (left / self.stable_dt()).ceil().max(1.0);
            let h = left / n;
            let report = self.step_undoable(h)?;
            left -= h;
            let flow = between(&report);
            reports.push(report);
            if flow.is_break() {
                break;
            }
        }
        Ok(reports)
    }

    /// Whether a step keeps the pool's other workers spinning (`solver.spin_workers`; by
    /// default for grids of 64³ cells and more).
    pub(crate) fn spins(&self) -> bool {
        self.settings.solver.spin_workers.unwrap_or(self.grid.num_cells() >= 1 << 18)
    }

    /// How a step's work is spread over the threads: on one thread below
    /// [`SERIAL_BELOW`] cells (unless `solver.spin_workers` asks for spinning), spinning
    /// where [`Simulation::spins`], on rayon's pool otherwise.
    pub(crate) fn spread(&self) -> Spread {
        match self.settings.solver.spin_workers {
            _ if self.spins() => Spread::Spinning,
            None if self.grid.num_cells() < SERIAL_BELOW => Spread::Serial,
            _ => Spread::Parallel,
        }
    }

    /// Advances one step of the fixed Δt. A step that fails is rolled back (see
    /// [`Simulation::set_rollback`]).
    pub fn step(&mut self) -> Result<StepReport> {
        let dt = self.settings.dt;
        self.step_undoable(dt)
    }

    /// Whether [`Simulation::step`] and [`Simulation::advance`] roll back a step that fails
    /// (on unless [`Simulation::set_rollback`] turned it off).
    pub fn rollback(&self) -> bool {
        self.rollback
    }

    /// Whether a step that fails (a solve that does not converge, a body that leaves the
    /// tank, a state that is not finite) is rolled back: the simulation is then left as it
    /// was before the step (its particles, narrow band, φ_L, bodies, fluid forces, time and
    /// step count; the velocity and the pressure change only once a step has succeeded), so
    /// that the same step can be tried again after a change; only its warnings stay. On by
    /// default. It keeps a copy of the particles, the narrow band and φ_L through every step
    /// (on `large_tank`, a fifth more peak memory: docs/performance.md): a caller that stops
    /// at the first error (the CLI's `run`) turns it off, and a step that fails then leaves
    /// the particles (and the narrow band) where it had moved them; the bodies, their forces,
    /// the time and the step count are put back either way. The gradients' taped steps never roll back (a failure ends their run).
    pub fn set_rollback(&mut self, on: bool) {
        self.rollback = on;
    }

    /// A step of `dt` that [`Simulation::rollback`] rolls back if it fails.
    fn step_undoable(&mut self, dt: f64) -> Result<StepReport> {
        let undo = self.rollback.then(|| Undo::take(self));
        let report = self.step_inner(dt, None, Pressures::Solve, self.measures);
        if let (Err(_), Some(undo)) = (&report, undo) {
            undo.restore(self);
        }
        report
    }

    /// Advances one step and records on `tape` what the backward pass needs.
    pub fn step_taped(&mut self, tape: &mut Tape) -> Result<StepReport> {
        let dt = self.settings.dt;
        self.step_inner(dt, Some(tape), Pressures::Solve, true)
    }

    /// A step for a gradient's forward pass, recorded on `tape` when there is one. Its report
    /// would be dropped, so the liquid's volume, speeds and energy are not measured (on
    /// `block_drop` the particles' energy alone was 13% of an optimisation's time), and a
    /// failed step is not rolled back (the gradient fails with it).
    pub(crate) fn step_unreported(&mut self, tape: Option<&mut Tape>) -> Result<()> {
        let dt = self.settings.dt;
        self.step_inner(dt, tape, Pressures::Solve, false).map(drop)
    }

    /// [`Simulation::step_unreported`] that keeps its pressure solves in `solves` (see
    /// [`Solves`]).
    pub(crate) fn step_recording(&mut self, solves: &mut Solves) -> Result<()> {
        let dt = self.settings.dt;
        self.step_inner(dt, None, Pressures::Record(solves), false).map(drop)
    }

    /// [`Simulation::step_taped`] that takes its pressures from `replay` instead of solving:
    /// the re-run of a step [`Simulation::step_recording`] made from the same state.
    /// It makes no report: what only a report reads (the divergence, the kinetic energy, the
    /// fastest speed, the liquid volume) is not computed.
    pub(crate) fn step_replayed(&mut self, tape: &mut Tape, replay: &mut Replay) -> Result<()> {
        let dt = self.settings.dt;
        self.step_inner(dt, Some(tape), Pressures::Replay(replay), false).map(drop)
    }

    /// What the step's system is assembled with for a step of `dt`.
    pub(crate) fn step_params(&self, dt: f64) -> StepParams {
        let s = &self.settings;
        StepParams {
            pressure: PressureParams {
                dt,
                density: s.fluid.density,
                theta_min: s.solver.theta_min,
            },
            coupling: s.solver.coupling,
            gravity: s.fluid.gravity,
            solves: true,
        }
    }

    /// Whether rapier contact is on and could act this step (see [`contact_possible`]).
    fn contact_on(&self, dt: f64) -> bool {
        self.settings.contact.enabled && contact_possible(&self.bodies, self.grid.size(), dt)
    }

    /// One step of `dt`, taped on `tape` when given, its pressures as `pressures` says, run
    /// on the pool (its other workers spinning when [`Simulation::spins`]).
    ///
    /// A step whose state or predicted velocities are not finite (or beyond [`LARGEST`])
    /// fails before it changes anything ([`Simulation::check_state`]). A step that fails
    /// later (a solve that does not converge, a body leaving the tank) puts back the bodies,
    /// their fluid forces, the time, the step count and the tape; the velocity and pressure
    /// are only ever replaced by a step that succeeds. The marker particles (and a narrow
    /// band) stay where the step's stage 0 moved them, and φ_L follows them, unless the
    /// caller's [`Simulation::rollback`] puts them back too: see [`BodyUndo`] and [`Undo`].
    /// The warnings the step found are kept.
    fn step_inner(
        &mut self,
        dt: f64,
        mut tape: Option<&mut Tape>,
        pressures: Pressures,
        report: bool,
    ) -> Result<StepReport> {
        run_spread(self.spread(), || {
            self.check_state(dt)?;
            let undo = BodyUndo::of(self);
            let taped = tape.as_ref().map(|t| t.steps.len());
            let report = self.step_stages(dt, tape.as_deref_mut(), pressures, report);
            if report.is_err() {
                undo.restore(self);
                // φ_L of the particles where they are (the step's system may have held its
                // memory), and no record of the step on the tape.
                self.phi = self.particle_phi();
                if let (Some(t), Some(n)) = (tape, taped) {
                    t.steps.truncate(n);
                }
            }
            report
        })
    }

    /// The checks before a step changes anything: the state is finite, and the velocities
    /// the step starts its solve from (with gravity and the bodies' loads for `dt`) are below
    /// [`LARGEST`], so the solve's sums of squares cannot overflow (`gravity = [0, -1e160,
    /// 0]` gave an infinite right-hand side, a NaN residual that counted as converged, and
    /// `max speed inf`).
    fn check_state(&self, dt: f64) -> Result<()> {
        let step = self.step + 1;
        let blew = |what: String| Err(Error::NonFinite { step, what });
        // Sizes as the largest component (a length would overflow first).
        let size = |v: Vec3| v.abs().max_element();
        let g = size(v3(self.settings.fluid.gravity));
        let fluid = largest_magnitude(&self.u) + dt * g;
        if fluid.is_nan() {
            return blew("the fluid velocity is not finite".into());
        }
        if fluid >= LARGEST {
            return blew(format!(
                "the fluid velocity would reach {fluid:.3e} m/s with gravity, beyond {LARGEST:e} \
                 (is gravity too large?)"
            ));
        }
        for b in &self.bodies {
            let pose = b.x.is_finite() && b.q.is_finite() && b.x.abs().max_element() < LARGEST;
            if !pose {
                return blew(format!("body {}'s position or orientation is not finite", b.name));
            }
            let (v, w) = (size(b.v), size(b.w));
            let (f, t) = (size(b.force), size(b.torque));
            // What gravity and the loads add in a step (at most: ‖I⁻¹‖ bounded by the sum of
            // its entries' magnitudes).
            let inverse = b.local_inertia.inverse().to_cols_array();
            let inverse = inverse.iter().map(|x| x.abs()).sum::<f64>();
            let pushed = if b.moves() { dt * (g + f / b.mass) } else { 0.0 };
            let spun = if b.moves() { dt * t * inverse } else { 0.0 };
            if !(v + pushed < LARGEST && w + spun < LARGEST) {
                return blew(format!(
                    "body {}'s velocity would reach {:.3e} m/s and {:.3e} rad/s (largest \
                     components), beyond {LARGEST:e}",
                    b.name,
                    v + pushed,
                    w + spun
                ));
            }
        }
        Ok(())
    }

    /// [`Simulation::step_inner`]'s stages.
    fn step_stages(
        &mut self,
        dt: f64,
        tape: Option<&mut Tape>,
        mut pressures: Pressures,
        report: bool,
    ) -> Result<StepReport> {
        let start = tape
            .as_ref()
            .map(|_| (self.u.clone(), self.bodies.iter().map(RigidBody::state).collect()));
        let grid = self.grid;
        let mut times = StageSeconds::default();
        let mut clock = Instant::now();
        let mut lap = |slot: &mut f64| {
            let now = Instant::now();
            *slot = (now - clock).as_secs_f64();
            clock = now;
        };

        // 3a. The solids where they are at the start of the step (bodies move in stage 6).
        let geometry = self.geometry();
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
        lap(&mut times.geometry);

        // 0. Marker particles ride the current (divergence-free, extrapolated) field.
        let (particle_record, density_stats) =
            self.advect_particles(&geometry, dt, start.is_some(), &mut times, &mut pressures)?;
        let density_cg_iterations = density_stats.cg_iterations;
        lap(&mut 0.0);

        // 3. Where the liquid is now (with a frozen surface: where it was at the start). It
        // depends on the particles only, and tells advection which faces the step reads.
        let mut particle_record = particle_record;
        let particle_phi = match particle_record.as_mut() {
            // Taped: the particle each cell's φ is the distance to, for the backward pass.
            Some(r) => {
                let bins = Bins::new(&self.particles, &grid);
                let (phi, nearest) = surface::liquid_sdf_nearest(
                    &self.particles,
                    &bins,
                    &grid,
                    &self.surface_model(),
                    self.band.as_deref().map(Band::deep),
                );
                r.nearest = nearest;
                phi
            }
            // Nothing reads the last step's φ_L after the band's update: its memory takes
            // this step's, which the step's system holds until the step ends (a failed step
            // gives it back, see `Simulation::step_inner`).
            None => {
                let mut phi = std::mem::take(&mut self.phi);
                self.particle_phi_into(&mut phi);
                phi
            }
        };
        lap(&mut times.surface);
        let taped_phi = match (&start, &self.frozen_phi) {
            (Some(_), None) => particle_phi.clone(),
            _ => Vec::new(),
        };
        let memory = self.spare.systems().take();
        // A replayed step is given its pressures: its system needs no operator.
        let solves = !matches!(pressures, Pressures::Replay(_));
        let params = StepParams { solves, ..self.step_params(dt) };
        let sys = StepSystem::assemble(&grid, &self.bodies, geometry, particle_phi, params, memory);
        lap(&mut times.assemble);

        // 1–2. Self-advection of the velocity on the faces the rest of the step reads, and
        // gravity; gravity and the external forces on the bodies.
        let gravity = self.settings.fluid.gravity;
        let out = self.spare.velocity(&grid);
        let u_hat = predicted_velocity(&self.u, &grid, dt, gravity, &sys.needed, out);
        lap(&mut times.advect_velocity);
        let v_hat: Vec<[f64; 6]> =
            sys.coupled.iter().map(|&i| body_velocity(&self.bodies[i], v3(gravity), dt)).collect();
        lap(&mut times.forces);

        // 4. Projection, coupled with the bodies, contact held inside it (when contact is
        // possible for the bodies moving at their velocities before the pressure acts).
        let contact = self.settings.contact.enabled && {
            let mut moving = self.bodies.clone();
            for (&i, v) in sys.coupled.iter().zip(&v_hat) {
                moving[i].v = Vec3::new(v[0], v[1], v[2]);
                moving[i].w = Vec3::new(v[3], v[4], v[5]);
            }
            contact_possible(&moving, grid.size(), dt)
        };
        let (proj, u) = self.project(&sys, u_hat, &v_hat, dt, contact, &mut pressures)?;
        for ((&i, v), f) in sys.coupled.iter().zip(&proj.v_after).zip(&proj.forces) {
            let b = &mut self.bodies[i];
            b.v = Vec3::new(v[0], v[1], v[2]);
            b.w = Vec3::new(v[3], v[4], v[5]);
            self.fluid_forces[i] = *f;
        }
        // A kinematic body's force is what its motion costs: J·p.
        for (i, c, _) in &sys.kinematic {
            self.fluid_forces[*i] = c.force(&proj.p);
        }
        // What only the report reads: a gradient's forward pass and a replayed re-run drop
        // their reports, so they skip them.
        let report = report && !matches!(pressures, Pressures::Replay(_));
        let (max_divergence, kinetic_energy) = if report {
            let flux = sys.flux(&u, &proj.v_after);
            let rho = self.settings.fluid.density;
            (
                flux.iter().fold(0.0f64, |m, f| m.max(f.abs())) / grid.dx.powi(3),
                kinetic_energy(&u, &sys.pressure, &sys.geometry.weights, rho),
            )
        } else {
            (f64::NAN, f64::NAN)
        };
        lap(&mut times.pressure);

        // 5. Velocity correction: the bodies' velocity on the faces they cover (which then
        // count as known), extrapolation into air, zero in static solids and walls.
        let mut u = u;
        let air_body_faces = correct_with_bodies(
            &mut u,
            &sys.projected_mask(),
            &self.bodies,
            &sys.geometry.body_faces,
            &sys.geometry.weights,
            &self.statics.weights,
            &grid,
            self.settings.solver.extrapolation_layers,
        );
        lap(&mut times.correct_velocity);

        // Whether rapier integrates the bodies: contact possible at their new velocities.
        let contact_moves = self.contact_on(dt);
        if let Pressures::Record(solves) = &mut pressures {
            solves.contact |= contact || contact_moves;
        }
        if let (Some(t), Some((u0, bodies))) = (tape, start) {
            t.steps.push(StepRecord {
                u: u0,
                bodies,
                v_hat: proj.v_hat,
                v_after: self.bodies.iter().map(generalized_velocity).collect(),
                p: proj.p.clone(),
                phi: taped_phi,
                body_faces: sys.geometry.body_faces.clone(),
                loads: self.bodies.iter().map(RigidBody::load).collect(),
                air_body_faces,
                contact: contact || contact_moves,
                particles: particle_record,
            });
        }

        // 6. Rigid integration (or contact).
        self.move_bodies(dt, contact_moves)?;
        lap(&mut times.rigid);

        // The state the step leaves: finite, and below LARGEST (a larger one only overflows
        // a step later).
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
                volume_error: volume_errors[i],
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
            density_cg_iterations,
            max_divergence,
            liquid_volume,
            max_speed,
            kinetic_energy,
            energy,
            bodies,
            contact_iterations: proj.hold.iterations,
            contact_residual: proj.hold.residual,
            stage_seconds: times,
            warnings,
        })
    }

    /// Stage 0: the marker particles through the current field, pushed out of the solids,
    /// and the density projection (nothing with a frozen surface).
    /// Times its three parts into `times` (`band`, `advect_particles`, `density`).
    fn advect_particles(
        &mut self,
        geometry: &Geometry,
        dt: f64,
        taped: bool,
        times: &mut StageSeconds,
        pressures: &mut Pressures,
    ) -> Result<(Option<ParticleRecord>, DensityStats)> {
        if self.frozen_phi.is_some() {
            return Ok((None, DensityStats::default()));
        }
        let clock = Instant::now();
        let change = self.update_band(geometry, dt);
        times.band = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let start = taped.then(|| self.particles.clone());
        let margin = self.push_margin();
        let substeps = match self.settings.solver.particle_substeps {
            0 => surface::advect_substeps(&self.u, &self.grid, dt),
            n => n.max(surface::advect_substeps(&self.u, &self.grid, dt)),
        };
        let node_sdf = &self.statics.node_sdf;
        surface::advect_substepped(
            &mut self.particles,
            &self.u,
            &self.grid,
            dt,
            substeps,
            node_sdf,
        );
        let moved = taped.then(|| self.particles.clone());
        surface::push_out_of_bodies(&mut self.particles, &self.bodies, margin);
        times.advect_particles = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let mut density = None;
        let mut stats = DensityStats::default();
        let mut particles = std::mem::take(&mut self.particles);
        if let Some(inputs) = self.density_inputs(geometry) {
            let step = self.step + 1;
            let corrected = match pressures {
                Pressures::Replay(replay) => replay
                    .next_density(step)
                    .and_then(|q| density::correct_replayed(&mut particles, &inputs, q, step)),
                _ => density::correct(&mut particles, &inputs, step),
            };
            if let (Pressures::Record(solves), Ok((s, q))) = (&mut *pressures, &corrected) {
                solves.push_density(q.clone(), s.cg_iterations);
            }
            match corrected {
                Ok((s, q)) => (stats, density) = (s, q),
                Err(e) => {
                    self.particles = particles;
                    return Err(e);
                }
            }
            surface::push_out_of_bodies(&mut particles, &self.bodies, margin);
        }
        self.particles = particles;
        times.density = clock.elapsed().as_secs_f64();
        let record = start.zip(moved).map(|(start, moved)| ParticleRecord {
            start,
            substeps,
            moved,
            density,
            nearest: Vec::new(),
            change,
            deep: self.band.as_ref().map(|b| b.deep.clone()),
        });
        Ok((record, stats))
    }

    /// How far out of a body a particle is pushed.
    pub(crate) fn push_margin(&self) -> f64 {
        1e-3 * self.grid.dx
    }

    /// How φ_L is made from the particles.
    pub(crate) fn surface_model(&self) -> SurfaceModel {
        SurfaceModel { radius: self.radius, sparse_cells: self.settings.solver.sparse_cells }
    }

    /// What the density projection of a step with `geometry` reads (None when it is off).
    pub(crate) fn density_inputs<'a>(
        &'a self,
        geometry: &'a Geometry,
    ) -> Option<DensityInputs<'a>> {
        let solver = &self.settings.solver;
        solver.density_correction.then(|| DensityInputs {
            grid: &self.grid,
            weights: &geometry.weights,
            node_sdf: &self.statics.node_sdf,
            centre_in_solid: &geometry.centre_in_solid,
            near_solid: &geometry.near_solid,
            gravity: self.settings.fluid.gravity,
            surface: self.surface_model(),
            particles_per_cell: solver.particles_per_cell,
            theta_min: solver.theta_min,
            solve: solver.density_linear(),
            band: self.band.as_deref(),
            systems: Some(self.spare.systems()),
        })
    }

    /// Stage 4: the coupled solve from the fluid velocity `u_hat` and the coupled bodies'
    /// velocities `v_hat`, warm-started from the last pressure, with contact held inside it
    /// when `contact` (see [`hold_contact`]). Returns the solve and `u_hat` updated by its
    /// pressure.
    fn project(
        &self,
        sys: &StepSystem,
        u_hat: Mac,
        v_hat: &[[f64; 6]],
        dt: f64,
        contact: bool,
        pressures: &mut Pressures,
    ) -> Result<(Projection, Mac)> {
        let how = self.settings.solver.linear();
        let mut last_p: Option<Vec<f64>> = None;
        let solve = |kick: &[[f64; 6]]| {
            let vel: Vec<[f64; 6]> =
                v_hat.iter().zip(kick).map(|(v, k)| std::array::from_fn(|d| v[d] + k[d])).collect();
            // With the liquid the thin bodies carry (`vel` where they carry none).
            let vel_e = sys.entrained_velocities(&vel, &u_hat);
            let (p, stats) = match pressures {
                Pressures::Replay(replay) => replay.next(sys.pressure.len(), self.step + 1)?,
                _ => {
                    let b = sys.rhs(&u_hat, &vel_e);
                    // Warm start: the last solve's pressure (this step's previous contact
                    // iteration, or the last step's).
                    let guess = match last_p.take() {
                        Some(p) => p,
                        None => {
                            let cells = &sys.pressure.cell_of_row;
                            let min = crate::math::par::MIN_LEN;
                            let gather = |&c: &u32| self.pressure[c as usize];
                            cells.par_iter().with_min_len(min).map(gather).collect()
                        }
                    };
                    sys.pressure.solve_from(&b, guess, &how)
                }
            };
            if let Pressures::Record(solves) = pressures {
                solves.push(p.clone(), stats);
            }
            if !stats.relative_residual.is_finite() {
                return Err(Error::NonFinite {
                    step: self.step + 1,
                    what: "the pressure solve's residual is not finite".into(),
                });
            }
            if !stats.converged {
                return Err(Error::NotConverged {
                    solve: crate::error::Solve::Pressure,
                    step: self.step + 1,
                    iterations: stats.iterations,
                    residual: stats.relative_residual,
                    tolerance: how.tolerance,
                });
            }
            let mut forces: Vec<[f64; 6]> = sys.couplings().iter().map(|c| c.force(&p)).collect();
            let after: Vec<[f64; 6]> = sys
                .couplings()
                .iter()
                .zip(&vel_e)
                .zip(&forces)
                .map(|((c, v), f)| {
                    let dv = c.dt_minv_times(f);
                    std::array::from_fn(|d| v[d] + dv[d])
                })
                .collect();
            // A body carrying liquid feels M·(V' − V̂)/Δt of it: J·p less the weight and the
            // momentum of the liquid it carries.
            for (k, ent) in sys.entrained.iter().enumerate().filter(|(_, e)| !e.is_empty()) {
                let dv: [f64; 6] = std::array::from_fn(|d| (after[k][d] - vel[k][d]) / dt);
                forces[k] = std::array::from_fn(|r| (0..6).map(|c| ent.mass[r][c] * dv[c]).sum());
            }
            last_p = Some(p.clone());
            let proj = Projection {
                p,
                stats,
                v_hat: vel,
                v_after: after.clone(),
                forces,
                hold: ContactHold::default(),
            };
            Ok((proj, after))
        };
        let change = |after: &[[f64; 6]]| self.contact_change(&sys.coupled, after, dt);
        let change: Option<ContactChange<'_>> = if contact { Some(&change) } else { None };
        let tolerance = contact_tolerance(self.settings.fluid.gravity, dt);
        let (mut proj, hold) = hold_contact(sys.coupled.len(), solve, change, tolerance)?;
        proj.hold = hold;
        // The velocity update of the solve that stands (the field is not copied per contact
        // iteration).
        let mut u = u_hat;
        sys.pressure.update_velocity(&proj.p, &mut u);
        Ok((proj, u))
    }

    /// What rapier's contact step would do to each coupled body's [v; ω] if the bodies had
    /// the velocities `after`: its velocity after the step minus before.
    fn contact_change(&self, coupled: &[usize], after: &[[f64; 6]], dt: f64) -> Vec<[f64; 6]> {
        #[cfg(feature = "contact")]
        {
            let mut bodies = self.bodies.clone();
            for (&i, v) in coupled.iter().zip(after) {
                bodies[i].v = Vec3::new(v[0], v[1], v[2]);
                bodies[i].w = Vec3::new(v[3], v[4], v[5]);
            }
            let before = bodies.clone();
            crate::stages::contact::ContactWorld::new(
                self.grid.size(),
                &bodies,
                &self.settings.contact,
            )
            .step(&mut bodies, dt);
            coupled
                .iter()
                .map(|&i| {
                    let (a, b) =
                        (generalized_velocity(&bodies[i]), generalized_velocity(&before[i]));
                    std::array::from_fn(|d| a[d] - b[d])
                })
                .collect()
        }
        #[cfg(not(feature = "contact"))]
        {
            let _ = (after, dt);
            vec![[0.0; 6]; coupled.len()]
        }
    }

    /// Stage 6: integrate the bodies, through rapier when contact is on and possible; a body
    /// that leaves the tank is an error.
    fn move_bodies(&mut self, dt: f64, contact: bool) -> Result<()> {
        #[cfg(feature = "contact")]
        if contact {
            // A fresh world per step: the fluid step changed every velocity, and rebuilding
            // a handful of colliders costs microseconds.
            let before: Vec<_> = self.bodies.iter().map(|b| b.q).collect();
            crate::stages::contact::ContactWorld::new(
                self.grid.size(),
                &self.bodies,
                &self.settings.contact,
            )
            .step(&mut self.bodies, dt);
            // rapier's step keeps ω (its gyroscopic forces are off, see contact.rs): carry
            // the dynamic bodies' angular momentum to their new orientation, as our integrator
            // does.
            for (b, q0) in self.bodies.iter_mut().zip(&before) {
                if b.motion == crate::geometry::body::Motion::Dynamic {
                    b.w = crate::geometry::body::carry_angular_momentum(
                        &b.local_inertia,
                        *q0,
                        b.q,
                        b.w,
                    );
                }
            }
            // rapier holds kinematic bodies fixed at their pose; they move along their own
            // velocity.
            for b in self
                .bodies
                .iter_mut()
                .filter(|b| b.motion == crate::geometry::body::Motion::Kinematic)
            {
                b.integrate(dt);
            }
            return Ok(());
        }
        let _ = contact;
        let size = self.grid.size();
        // An external body is where the caller's engine put it, and may sit as far into a
        // wall as [`Simulation::set_body_state`] allows (rapier's contact leaves a few
        // micrometres of overlap with the floor it rests on).
        let external_reach = EXTERNAL_REACH * self.grid.dx;
        for b in self.bodies.iter_mut() {
            b.integrate(dt);
            let reach = if b.motion == Motion::External { external_reach } else { 0.0 };
            let (lo, hi) = b.bounds();
            if lo.min_element() < -reach || (hi - size).max_element() > reach {
                return Err(Error::BodyLeftTank {
                    step: self.step + 1,
                    body: b.name.clone(),
                    bounds: (lo.to_array(), hi.to_array()),
                });
            }
        }
        Ok(())
    }
}
