//! Stepping a simulation: a fixed step, a frame of steps ([`Simulation::advance`]), the
//! checks before a step changes anything, and what a failed step puts back. The step itself
//! is the recipe of `recipe.rs`, its stages [`crate::stages::Stage::ALL`].

use super::Simulation;
use crate::error::{Error, Result};
use crate::geometry::body::{BodyState, RigidBody};
use crate::geometry::grid::Mac;
use crate::math::pool::{run_spread, Spread, SERIAL_BELOW};
use crate::math::Twist;
use crate::math::{v3, Vec3};
use crate::stages::band::Band;
use crate::stages::density::DensityInputs;
use crate::stages::pressure::PressureParams;
use crate::stages::solid_phi;
use crate::stages::surface::SurfaceModel;
use crate::world::step::{Geometry, StepParams, StepReport};
use crate::world::tape::{Replay, Solves, Tape};
use std::ops::ControlFlow;
use std::sync::Arc;

/// The largest speed (m/s, rad/s) or coordinate (m) a step takes: beyond it the state is
/// taken as blown up. Far above anything physical, and far enough below f64's range that the
/// solve's sums of squares over a grid of 512³ cells cannot overflow (1e100² · 1.3e8 < 1e308).
pub(super) const LARGEST: f64 = 1e100;

/// The largest |u| over every face, NaN if one is NaN: one parallel pass for both checks.
pub(super) fn largest_magnitude(u: &Mac) -> f64 {
    u.max_abs_or_nan()
}

impl Simulation {
    /// The largest |u| over the faces of the fluid velocity (NaN ignored): kept from the
    /// step that made it ([`Mac::max_abs_or_nan`] there, which is this for a field without
    /// NaN, the only kind a step leaves), else measured.
    pub(super) fn largest_face_speed(&self) -> f64 {
        self.largest_u.unwrap_or_else(|| self.u.max_abs())
    }
}

/// What every failed step puts back (see [`Simulation::step_inner`]), rollback or not: the
/// bodies, their fluid forces, the step count and the time. The marker particles and the
/// narrow band are [`Undo`]'s, kept only when [`Simulation::rollback`] is on (their copy costs
/// 24 bytes a particle and 21 a cell every step).
struct BodyUndo {
    bodies: Vec<RigidBody>,
    fluid_forces: Vec<Twist>,
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
pub(super) enum Pressures<'a, 'b> {
    /// Solved.
    Solve,
    /// Solved, and kept in order (a checkpointed forward pass).
    Record(&'a mut Solves),
    /// Taken in order from the record of the same steps from the same state (their re-run).
    Replay(&'a mut Replay<'b>),
}

/// What a step changes before it can fail, kept so that a step that fails leaves the
/// simulation as it was (see [`Simulation::set_rollback`]): the marker particles and the
/// narrow band (the particle stages; neither with a frozen surface), φ_L (whose memory the step builds
/// into), the bodies (stages `pressure` and `rigid`), their fluid forces, the step count and the time. The
/// fluid velocity and the pressure are replaced only once the step has succeeded.
struct Undo {
    particles: Option<Vec<Vec3>>,
    band: Option<Arc<Band>>,
    phi: Vec<f64>,
    bodies: Vec<BodyState>,
    fluid_forces: Vec<Twist>,
    step: usize,
    time: f64,
}

impl Undo {
    /// What `sim`'s next step may change. The two large copies side by side, each in
    /// parallel pieces (run on the step's pool).
    fn take(sim: &Simulation) -> Undo {
        let moving = sim.frozen_phi.is_none();
        let (particles, phi) = rayon::join(
            || moving.then(|| crate::math::par::copied(&sim.particles)),
            || crate::math::par::copied(&sim.phi),
        );
        Undo {
            particles,
            // Shared until the band's update changes it, which then copies it.
            band: if moving { sim.band.clone() } else { None },
            phi,
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
        self.step_inner(dt, None, Pressures::Solve, self.measures, self.rollback)
    }

    /// Advances one step and records on `tape` what the backward pass needs.
    pub fn step_taped(&mut self, tape: &mut Tape) -> Result<StepReport> {
        let dt = self.settings.dt;
        self.step_inner(dt, Some(tape), Pressures::Solve, true, false)
    }

    /// A step for a gradient's forward pass, recorded on `tape` when there is one. Its report
    /// would be dropped, so the liquid's volume, speeds and energy are not measured (on
    /// `block_drop` the particles' energy alone was 13% of an optimisation's time), and a
    /// failed step is not rolled back (the gradient fails with it).
    pub(crate) fn step_unreported(&mut self, tape: Option<&mut Tape>) -> Result<()> {
        let dt = self.settings.dt;
        self.step_inner(dt, tape, Pressures::Solve, false, false).map(drop)
    }

    /// [`Simulation::step_unreported`] that keeps its pressure solves in `solves` (see
    /// [`Solves`]).
    pub(crate) fn step_recording(&mut self, solves: &mut Solves) -> Result<()> {
        let dt = self.settings.dt;
        self.step_inner(dt, None, Pressures::Record(solves), false, false).map(drop)
    }

    /// [`Simulation::step_taped`] that takes its pressures from `replay` instead of solving:
    /// the re-run of a step [`Simulation::step_recording`] made from the same state.
    /// It makes no report: what only a report reads (the divergence, the kinetic energy, the
    /// fastest speed, the liquid volume) is not computed.
    pub(crate) fn step_replayed(&mut self, tape: &mut Tape, replay: &mut Replay) -> Result<()> {
        let dt = self.settings.dt;
        self.step_inner(dt, Some(tape), Pressures::Replay(replay), false, false).map(drop)
    }

    /// What the step's system is assembled with for a step of `dt`.
    pub(crate) fn step_params(&self, dt: f64) -> StepParams {
        let s = &self.settings;
        StepParams {
            pressure: PressureParams {
                dt,
                density: s.fluid.density,
                ghost: s.solver.ghost_fluid(),
            },
            coupling: s.solver.coupling,
            gravity: s.fluid.gravity,
            solves: true,
        }
    }

    /// One step of `dt`, taped on `tape` when given, its pressures as `pressures` says, run
    /// on the pool (its other workers spinning when [`Simulation::spins`]).
    ///
    /// A step whose state or predicted velocities are not finite (or beyond [`LARGEST`])
    /// fails before it changes anything ([`Simulation::check_state`]). A step that fails
    /// later (a solve that does not converge, a body leaving the tank) puts back the bodies,
    /// their fluid forces, the time, the step count and the tape; the velocity and pressure
    /// are only ever replaced by a step that succeeds. The marker particles (and a narrow
    /// band) stay where the step's particle stages moved them, and φ_L follows them, unless
    /// `rollback` puts them back too: see [`BodyUndo`] and [`Undo`] (taken on the step's
    /// pool, whose threads its copies use). The warnings the step found are kept.
    fn step_inner(
        &mut self,
        dt: f64,
        mut tape: Option<&mut Tape>,
        pressures: Pressures,
        report: bool,
        rollback: bool,
    ) -> Result<StepReport> {
        run_spread(self.spread(), || {
            let full = rollback.then(|| Undo::take(self));
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
                if let Some(full) = full {
                    full.restore(self);
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
        let fluid = self.largest_u.unwrap_or_else(|| largest_magnitude(&self.u)) + dt * g;
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

    /// How far out of a body a particle is pushed.
    pub(crate) fn push_margin(&self) -> f64 {
        1e-3 * self.grid.dx
    }

    /// [`solid_phi::value_reads`] for a step with `geometry` (None with the surface frozen,
    /// whose φ_L is not made again).
    pub(crate) fn value_reads(&self, geometry: &Geometry) -> Option<Vec<bool>> {
        if self.frozen_phi.is_some() {
            return None;
        }
        let everywhere = self.settings.solver.surface_interior_values;
        let (centre_in_solid, partial) = (&geometry.centre_in_solid, &geometry.partial);
        let model = self.surface_model();
        solid_phi::value_reads(&self.grid, centre_in_solid, partial, &model, everywhere)
    }

    /// How φ_L is made from the particles.
    pub(crate) fn surface_model(&self) -> SurfaceModel {
        self.settings.solver.surface_model(self.grid.dx, self.radius)
    }

    /// The sites each body displaced when it was placed, in its frame (see
    /// `stages/surface/ghosts.rs`), body by body.
    pub(crate) fn displaced(&self) -> &[crate::stages::surface::Displaced] {
        &self.displaced
    }

    /// The bodies' ghosts where `bodies` (this simulation's, or a step's record of them)
    /// are: what the soft minimum of φ_L counts besides the particles; none for the nearest
    /// particle's distance.
    pub(crate) fn ghosts_at(&self, bodies: &[RigidBody]) -> Vec<Vec3> {
        crate::stages::surface::counted_ghosts(&self.surface_model(), bodies, &self.displaced)
    }

    /// What the density projection of a step with `geometry` and `bodies` reads (None when
    /// it is off).
    pub(crate) fn density_inputs<'a>(
        &'a self,
        geometry: &'a Geometry,
        bodies: &'a [RigidBody],
    ) -> Option<DensityInputs<'a>> {
        let solver = &self.settings.solver;
        solver.density_correction.then(|| DensityInputs {
            grid: &self.grid,
            weights: &geometry.weights,
            node_sdf: &self.statics.node_sdf,
            centre_in_solid: &geometry.centre_in_solid,
            partial: &geometry.partial,
            near_solid: &self.statics.near_solid,
            bodies,
            displaced: &self.displaced,
            gravity: self.settings.fluid.gravity,
            surface: self.surface_model(),
            interior_values: solver.surface_interior_values,
            particles_per_cell: solver.particles_per_cell,
            gain: solver.density_gain,
            passes: solver.density_passes,
            face_ramp: solver.density_face_ramp,
            ghost: solver.ghost_fluid(),
            blend: solver.blend(),
            solve: solver.density_linear(),
            band: self.band.as_deref(),
            systems: Some(self.spare.systems()),
        })
    }
}
