//! A running simulation: the liquid on a MAC grid, its marker particles, and the rigid bodies
//! coupled to it, named by handles. Split by concern: the world and its handles here, its
//! builder and the checks it makes in `builder.rs`, the memory estimate in `memory.rs`, and
//! the step, a pipeline of named stages (the paper's Algorithm 2), in `stepping.rs`.

use super::settings::{check_finite, WorldSettings};
use super::step::{body_faces, Energy, Geometry, Spare, StaticGeometry};
use crate::error::{Error, Result};
use crate::geometry::body::{BodyState, RigidBody};
use crate::geometry::fractions;
use crate::geometry::grid::{Grid, Mac};
use crate::math::par::MIN_LEN;
use crate::math::{v3, Vec3};
use crate::stages::band::{self, Band, BandChange};
use crate::stages::surface::{self, Bins};
use rayon::prelude::*;
use std::sync::Arc;

mod builder;
mod memory;
mod stepping;

use builder::check_body;
pub use builder::SimulationBuilder;

/// A body's name in a [`Simulation`], stable while other bodies come and go.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BodyHandle(u32);

impl BodyHandle {
    /// The handle's number (handles are never reused).
    pub fn id(self) -> u32 {
        self.0
    }
}

/// A running simulation.
#[derive(Clone, Debug)]
pub struct Simulation {
    grid: Grid,
    settings: WorldSettings,
    /// Shared between clones (checkpoint snapshots, finite differences): it never changes.
    statics: Arc<StaticGeometry>,
    radius: f64,
    /// Fluid velocity on faces.
    pub u: Mac,
    /// Marker particle positions.
    pub particles: Vec<Vec3>,
    /// The narrow band's deep cells (`solver.narrow_band`), shared between clones until the
    /// next update.
    band: Option<Arc<Band>>,
    bodies: Vec<RigidBody>,
    handles: Vec<BodyHandle>,
    next_handle: u32,
    /// Per body, the pressure force and torque of the last step's solve.
    fluid_forces: Vec<[f64; 6]>,
    pressure: Vec<f64>,
    phi: Vec<f64>,
    /// φ_L of the initial particles, when the surface is frozen.
    frozen_phi: Option<Arc<Vec<f64>>>,
    /// Liquid volume of the frozen particles.
    frozen_volume: f64,
    step: usize,
    time: f64,
    /// What the builder chose from the scene where a setting was left to it, in words.
    model: String,
    /// Every warning so far (each once).
    warnings: Vec<String>,
    /// The warnings given once a body: of which kind, about which body.
    warned: Vec<(&'static str, BodyHandle)>,
    /// The last step's whole-grid arrays, for the next step (or step adjoint) to build into;
    /// shared between clones.
    spare: Arc<Spare>,
    /// Whether a step that fails is rolled back ([`Simulation::set_rollback`]).
    rollback: bool,
}

/// A body's face fractions may miss its volume by this much (relative) before a step warns.
const VOLUME_TOLERANCE: f64 = 1e-3;

impl Simulation {
    /// A builder for a tank of `size` metres (x, y up, z) cut into cubes of side `dx`.
    pub fn builder(size: [f64; 3], dx: f64) -> SimulationBuilder {
        SimulationBuilder {
            size,
            dx,
            settings: WorldSettings::default(),
            liquid: Vec::new(),
            obstacles: Vec::new(),
            bodies: Vec::new(),
            notes: Vec::new(),
        }
    }

    /// What was chosen from the scene where a setting was left to `auto`, in words, for a
    /// run to print once at its start (`narrow band 3 (auto: 62% of the liquid's cells
    /// deep)`); the settings themselves, resolved, are [`Simulation::settings`].
    pub fn model(&self) -> &str {
        &self.model
    }

    /// Every warning so far, each once: what a user should know that is not an error (a body
    /// too thin or small for the grid).
    pub fn warnings(&self) -> &[String] {
        &self.warnings
    }

    /// Records `w` unless it was already given, and adds it to this step's `new` ones.
    fn warn(&mut self, new: &mut Vec<String>, w: String) {
        if !self.warnings.contains(&w) {
            self.warnings.push(w.clone());
            new.push(w);
        }
    }

    /// [`Simulation::warn`] once for each body and `kind`: the first such warning about the
    /// body stands for the ones after it (a thin body's missing volume changes as it moves:
    /// a resting box warned 24 times in 300 steps).
    fn warn_about(&mut self, new: &mut Vec<String>, kind: &'static str, h: BodyHandle, w: String) {
        if !self.warned.contains(&(kind, h)) {
            self.warned.push((kind, h));
            self.warn(new, w);
        }
    }

    /// The settings.
    pub fn settings(&self) -> &WorldSettings {
        &self.settings
    }

    /// The fixed step of [`Simulation::step`], s.
    pub fn dt(&self) -> f64 {
        self.settings.dt
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

    /// Simulated time, s.
    pub fn time(&self) -> f64 {
        self.time
    }

    /// Pressure at cell centres from the last solve (Pa, zero outside the liquid).
    pub fn pressure(&self) -> &[f64] {
        &self.pressure
    }

    /// Liquid signed distance at cell centres from the last step.
    pub fn liquid_phi(&self) -> &[f64] {
        &self.phi
    }

    /// Cells that are liquid in the last step's φ_L.
    pub fn liquid_cells(&self) -> impl Iterator<Item = usize> + '_ {
        self.phi.iter().enumerate().filter(|(_, p)| **p < 0.0).map(|(c, _)| c)
    }

    /// Liquid volume of the current particles, m³.
    pub fn liquid_volume(&self) -> f64 {
        if self.frozen_phi.is_some() {
            return self.frozen_volume;
        }
        let base = self.band.as_ref().map(|b| b.density.as_slice());
        surface::liquid_volume(
            &self.particles,
            &self.grid,
            self.settings.solver.particles_per_cell,
            base,
        )
    }

    /// The narrow band's deep cells, when the liquid has a band (`solver.narrow_band`).
    pub fn band(&self) -> Option<&Band> {
        self.band.as_deref()
    }

    /// Brings the narrow band up to date for a step of `dt` with the solids of `geometry`
    /// (see `band.rs`): from the last step's φ_L (the particles' before the first step),
    /// with the band widened by the cells the fastest velocity crosses in `dt`. None
    /// without a band or with the surface frozen.
    fn update_band(&mut self, geometry: &Geometry, dt: f64) -> Option<BandChange> {
        if self.band.is_none() || (self.frozen_phi.is_some() && self.step > 0) {
            return None;
        }
        let fresh = (self.step == 0).then(|| self.particle_phi());
        let phi = fresh.as_deref().unwrap_or(&self.phi);
        let outside: Vec<bool> = phi
            .par_iter()
            .zip(geometry.centre_in_solid.par_iter())
            .map(|(p, s)| *p >= 0.0 || *s)
            .collect();
        let grid = self.grid;
        // A trilinear sample is at most √3 times the largest face velocity.
        let reach = (3f64.sqrt() * self.u.max_abs() * dt / grid.dx).ceil() as usize;
        let width = self.settings.solver.narrow_band.width() + reach;
        let m = surface::per_axis(self.settings.solver.particles_per_cell);
        let node_sdf = &self.statics.node_sdf;
        let bodies = &self.bodies;
        let margin = self.push_margin();
        let admit =
            |x: Vec3| node_sdf.sample(&grid, x) > 0.0 && bodies.iter().all(|b| b.sdf(x) > margin);
        let band = Arc::make_mut(self.band.as_mut()?);
        let u = &self.u;
        Some(band::update(&mut self.particles, band, &outside, width, u, dt, &grid, m, admit))
    }

    /// The bodies, in the order they were added.
    pub fn bodies(&self) -> &[RigidBody] {
        &self.bodies
    }

    /// The bodies, to change their state in place (their number and order stay).
    pub fn bodies_mut(&mut self) -> &mut [RigidBody] {
        &mut self.bodies
    }

    /// Each body's handle, in the order of [`Simulation::bodies`].
    pub fn handles(&self) -> &[BodyHandle] {
        &self.handles
    }

    /// Where body `h` is in [`Simulation::bodies`].
    pub fn index_of(&self, h: BodyHandle) -> Option<usize> {
        self.handles.iter().position(|&x| x == h)
    }

    fn index(&self, h: BodyHandle) -> Result<usize> {
        self.index_of(h).ok_or(Error::UnknownBody { handle: h.0 })
    }

    /// Body `h`.
    pub fn body(&self, h: BodyHandle) -> Option<&RigidBody> {
        self.index_of(h).map(|i| &self.bodies[i])
    }

    /// Body `h`, to change it.
    pub fn body_mut(&mut self, h: BodyHandle) -> Option<&mut RigidBody> {
        self.index_of(h).map(|i| &mut self.bodies[i])
    }

    /// Adds a body at runtime. It must lie inside the tank, with a finite state and a
    /// positive mass; marker particles inside it are removed (the body displaces that
    /// liquid).
    pub fn add_body(&mut self, body: RigidBody) -> Result<BodyHandle> {
        check_body(&body, self.grid.size(), 0.0).map_err(|message| Error::InvalidSettings {
            key: format!("body {:?}", body.name),
            message,
        })?;
        let margin = 1e-3 * self.grid.dx;
        self.particles.retain(|x| body.sdf(*x) > margin);
        let h = BodyHandle(self.next_handle);
        self.next_handle += 1;
        self.bodies.push(body);
        self.handles.push(h);
        self.fluid_forces.push([0.0; 6]);
        Ok(h)
    }

    /// Removes body `h` and returns it. The space it held is left to the liquid and air.
    pub fn remove_body(&mut self, h: BodyHandle) -> Result<RigidBody> {
        let i = self.index(h)?;
        self.handles.remove(i);
        self.fluid_forces.remove(i);
        Ok(self.bodies.remove(i))
    }

    /// Sets the external force (N, on the centre of mass) and torque (N·m) on body `h`, both
    /// in the world frame; they act every step, with gravity, until changed.
    pub fn set_external_force(&mut self, h: BodyHandle, force: Vec3, torque: Vec3) -> Result<()> {
        let i = self.index(h)?;
        check_finite("force", &force.to_array())
            .and_then(|()| check_finite("torque", &torque.to_array()))
            .map_err(|e| Error::InvalidSettings { key: e.key, message: e.message })?;
        self.bodies[i].force = force;
        self.bodies[i].torque = torque;
        Ok(())
    }

    /// Sets body `h`'s pose and velocity: how a program whose own rigid-body engine moves an
    /// [`crate::geometry::body::Motion::External`] body hands it over each step. The body
    /// must lie inside the tank, up to a quarter of a cell into a wall (contact resolved by
    /// the caller's engine allows a little penetration).
    pub fn set_body_state(&mut self, h: BodyHandle, state: &BodyState) -> Result<()> {
        let i = self.index(h)?;
        let mut b = self.bodies[i].clone();
        b.set_state(state);
        check_body(&b, self.grid.size(), 0.25 * self.grid.dx).map_err(|message| {
            Error::InvalidSettings { key: format!("body {:?}", b.name), message }
        })?;
        self.bodies[i] = b;
        Ok(())
    }

    /// The pressure force (N) and torque (N·m, about the centre of mass) of the last step's
    /// solve on body `h` (zero before the first step and for bodies held still; for a
    /// kinematic body, what driving it along its motion meets).
    pub fn fluid_force(&self, h: BodyHandle) -> Option<(Vec3, Vec3)> {
        let f = self.fluid_forces[self.index_of(h)?];
        Some((Vec3::new(f[0], f[1], f[2]), Vec3::new(f[3], f[4], f[5])))
    }

    /// A copy to re-run steps from (a gradient's checkpoint snapshot): with the surface
    /// frozen, without the marker particles, which its steps never read (on a large tank
    /// they are half of a copy; they are set aside for the clone, not copied); otherwise a
    /// clone.
    pub(crate) fn replay_copy(&mut self) -> Simulation {
        if self.frozen_phi.is_none() {
            return self.clone();
        }
        let particles = std::mem::take(&mut self.particles);
        let copy = self.clone();
        self.particles = particles;
        copy
    }

    /// The liquid signed distance from the particles (before extension into solids): the
    /// frozen one, or the current particles'.
    pub fn particle_phi(&self) -> Vec<f64> {
        let mut phi = Vec::new();
        self.particle_phi_into(&mut phi);
        phi
    }

    /// [`Simulation::particle_phi`] written into the memory of `phi`.
    fn particle_phi_into(&self, phi: &mut Vec<f64>) {
        match &self.frozen_phi {
            Some(frozen) => {
                phi.clear();
                phi.extend_from_slice(frozen);
            }
            None => surface::liquid_sdf_into(
                phi,
                &self.particles,
                &Bins::new(&self.particles, &self.grid),
                &self.grid,
                &self.surface_model(),
                self.band.as_deref().map(Band::deep),
            ),
        }
    }

    /// Where the solids are now.
    pub fn geometry(&self) -> Geometry {
        self.geometry_with(&self.bodies, body_faces(&self.grid, &self.bodies))
    }

    /// Where the solids are with `bodies` in place of this simulation's, whose face fractions
    /// are `faces` (the backward pass has them on its tape).
    pub fn geometry_with(
        &self,
        bodies: &[RigidBody],
        faces: Vec<fractions::BodyFaces>,
    ) -> Geometry {
        Geometry::new_in(self.spare.geometry(), &self.grid, &self.statics, bodies, faces)
    }

    /// The arrays the last step (or step adjoint) left to build into.
    pub(crate) fn spare(&self) -> &Spare {
        &self.spare
    }

    /// Gives back the whole-grid arrays this simulation keeps between steps for the next step
    /// to build into (about 200 bytes a liquid cell; shared with its clones, which keep
    /// theirs). The next step allocates them again; no result changes. For a simulation kept
    /// idle beside others.
    pub fn release_spare(&mut self) {
        self.spare = Arc::default();
    }

    /// The mechanical energy of the liquid and the bodies now: the liquid's as the marker
    /// particles carry it (each its share ρ·dx³/particles-per-cell of mass, moving with the
    /// grid velocity where it is), the cells of a narrow band's deep region as full cells at
    /// their centre. Kinetic and potential energy of the liquid are then measured on the same
    /// mass, which the face-weighted sum of the step report is not.
    pub fn energy(&self) -> Energy {
        let g = v3(self.settings.fluid.gravity);
        let rho = self.settings.fluid.density;
        let cell = self.grid.dx.powi(3);
        let grid = &self.grid;
        let per_particle = rho * cell / self.settings.solver.particles_per_cell as f64;
        let kinetic = crate::math::par::sum_by(&self.particles, |x| {
            0.5 * self.u.velocity(grid, *x).length_squared()
        });
        let potential = crate::math::par::sum_by(&self.particles, |x| -g.dot(*x));
        let (deep_kinetic, deep_potential) = self.band.as_ref().map_or((0.0, 0.0), |b| {
            let cells = grid.cells();
            (0..b.deep.len()).filter(|&c| b.deep[c]).fold((0.0, 0.0), |(k, p), c| {
                let [i, j, k3] = cells.ijk(c);
                let x = cells.position(i, j, k3);
                (k + 0.5 * self.u.velocity(grid, x).length_squared(), p - g.dot(x))
            })
        });
        let (mut body_kinetic, mut body_potential) = (0.0, 0.0);
        for b in &self.bodies {
            body_kinetic +=
                0.5 * b.mass * b.v.length_squared() + 0.5 * b.w.dot(b.world_inertia() * b.w);
            body_potential -= b.mass * g.dot(b.x);
        }
        Energy {
            liquid_kinetic: per_particle * kinetic + rho * cell * deep_kinetic,
            liquid_potential: per_particle * potential + rho * cell * deep_potential,
            body_kinetic,
            body_potential,
        }
    }

    /// The largest velocity component on a face of a cell the last step counted as liquid
    /// (its φ_L, extended into the solids); before the first step, on any face.
    fn max_liquid_face_speed(&self) -> f64 {
        let cells = self.grid.cells().len();
        if self.step == 0 || self.phi.len() != cells {
            return self.u.max_abs();
        }
        let [n0, n1, _] = self.grid.n;
        let u = &self.u.c;
        (0..cells)
            .into_par_iter()
            .with_min_len(MIN_LEN)
            .filter(|&c| self.phi[c] < 0.0)
            .map(|c| {
                // Cell c's −side faces (see `max_liquid_speed`), and the +side ones a row, a
                // slab or a face further on.
                let (row, slab) = (c / n0, c / (n0 * n1));
                let most =
                    |a: usize, lo: usize, step: usize| u[a][lo].abs().max(u[a][lo + step].abs());
                most(0, c + row, 1).max(most(1, c + n0 * slab, n0)).max(most(2, c, n0 * n1))
            })
            .reduce(|| 0.0, f64::max)
    }

    /// Largest speed at the centre of a liquid cell (faces averaged per axis).
    fn max_liquid_speed(&self, cell_of_row: &[u32]) -> f64 {
        let [n0, n1, _] = self.grid.n;
        let u = &self.u.c;
        // The largest square, then its root: the same bits, since a correctly rounded
        // square root never decreases.
        let squared = cell_of_row
            .par_iter()
            .with_min_len(MIN_LEN)
            .map(|&c| {
                // Cell (i, j, k)'s −side faces: along x (one more face a row) at
                // c + (j + n1·k), along y (one more row a slab) at c + n0·k, along z at c;
                // the +side faces one row, slab or face further on.
                let c = c as usize;
                let (row, slab) = (c / n0, c / (n0 * n1));
                let mean = |a: usize, lo: usize, step: usize| 0.5 * (u[a][lo] + u[a][lo + step]);
                let v = [mean(0, c + row, 1), mean(1, c + n0 * slab, n0), mean(2, c, n0 * n1)];
                v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
            })
            .reduce(|| 0.0, f64::max);
        squared.sqrt()
    }
}
