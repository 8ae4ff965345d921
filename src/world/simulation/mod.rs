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
use crate::math::Twist;
use crate::math::{v3, TwistParts, Vec3};
use crate::stages::band::{self, Band, BandChange};
use crate::stages::surface::{self, Bins};
use rayon::prelude::*;
use std::sync::Arc;

mod builder;
mod memory;
mod recipe;
mod stepping;

pub use builder::SimulationBuilder;
use builder::{check_body, overlap, overlap_message, thin_body_warning, volume_warning};

/// A body's name in a [`Simulation`], stable while other bodies come and go. It carries the
/// identity of the simulation that gave it out (shared by that simulation's clones), so a
/// handle from another simulation names no body there: [`Error::UnknownBody`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BodyHandle {
    /// The simulation (and its clones) that gave the handle out.
    world: u32,
    /// The body's number in it.
    id: u32,
}

impl BodyHandle {
    /// The handle's number (handles are never reused within a simulation).
    pub fn id(self) -> u32 {
        self.id
    }
}

/// The identity of the next simulation built (see [`BodyHandle`]).
static NEXT_WORLD: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);

/// A fresh simulation identity.
fn next_world() -> u32 {
    NEXT_WORLD.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
}

/// A running simulation.
///
/// Bodies are named by [`BodyHandle`]s. Every method that takes a handle returns
/// [`Error::UnknownBody`] for one that names no body here (removed, or given out by another
/// simulation); `sim[h]` panics on one, as a slice does on an index out of range, and
/// [`Simulation::index_of`] asks without failing. The state changes only through setters that
/// check what they are given ([`Simulation::set_body_state`], [`Simulation::set_mass`],
/// [`Simulation::set_motion`], [`Simulation::set_velocity_field`],
/// [`Simulation::set_particles`]).
#[derive(Clone, Debug)]
pub struct Simulation {
    grid: Grid,
    settings: WorldSettings,
    /// Shared between clones (checkpoint snapshots, finite differences): it never changes.
    statics: Arc<StaticGeometry>,
    radius: f64,
    /// Fluid velocity on faces ([`Simulation::velocity_field`],
    /// [`Simulation::set_velocity_field`]).
    pub(crate) u: Mac,
    /// Marker particle positions ([`Simulation::particles`], [`Simulation::set_particles`]).
    pub(crate) particles: Vec<Vec3>,
    /// The narrow band's deep cells (`solver.narrow_band`), shared between clones until the
    /// next update.
    band: Option<Arc<Band>>,
    bodies: Vec<RigidBody>,
    /// Per body, the seeding sites it displaced when placed (see
    /// `stages/surface/ghosts.rs`).
    displaced: Vec<surface::Displaced>,
    handles: Vec<BodyHandle>,
    /// This simulation's identity in its handles (its clones share it).
    world: u32,
    next_handle: u32,
    /// Per body, the pressure force and torque of the last step's solve.
    fluid_forces: Vec<Twist>,
    pressure: Vec<f64>,
    phi: Vec<f64>,
    /// φ_L of the initial particles, when the surface is frozen.
    frozen_phi: Option<Arc<Vec<f64>>>,
    /// The liquid volume the particles held at the start ([`Simulation::start_volume`]).
    start_volume: f64,
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
    /// Whether a step's report measures the liquid ([`Simulation::set_report_measures`]).
    measures: bool,
    /// The particles' bins that a step's φ_L was made with, for the next step's band update.
    surface_bins: KeptBins,
    /// The largest |u| over the faces of `u`, when the step that made `u` measured it (its
    /// end checks it): what the next step's checks and its band read, without two more
    /// passes over the field. None once `u` is set from outside.
    largest_u: Option<f64>,
}

/// The bins of the particles as a step's surface stage (stage 3) left them, tagged with the
/// step count before that step: the next step's narrow-band update bins the very same
/// particles (nothing moves them in between), so it takes these instead of binning them
/// again (1.5 ms of a 70 ms step of the 64×32×64 pool, one thread). Taken once; a clone
/// starts without.
#[derive(Default)]
struct KeptBins(std::sync::Mutex<Option<(Bins, usize)>>);

impl KeptBins {
    /// Keeps `bins`, made in the step after `step` steps.
    fn keep(&self, bins: Bins, step: usize) {
        if let Ok(mut slot) = self.0.lock() {
            *slot = Some((bins, step));
        }
    }

    /// The bins of `particles` kept by the step before the `step`-th (one that failed or was
    /// rolled back keeps none that count: the step count went back); None when there are
    /// none.
    fn take(&self, particles: &[Vec3], step: usize) -> Option<Bins> {
        let (bins, made) = self.0.lock().ok()?.take()?;
        (made + 1 == step && bins.items.len() == particles.len()).then_some(bins)
    }
}

impl Clone for KeptBins {
    fn clone(&self) -> Self {
        KeptBins::default()
    }
}

impl std::fmt::Debug for KeptBins {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("KeptBins")
    }
}

/// How far (in cells) an [`Motion::External`](crate::geometry::body::Motion::External)
/// body may reach into a wall: the caller's engine resolves its contact, which leaves a
/// little penetration (rapier's is a few micrometres at rest); a quarter cell keeps the
/// body's face fractions and the liquid it displaces well defined.
const EXTERNAL_REACH: f64 = 0.25;

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

    /// Liquid signed distance at cell centres from the last step. Its sign is exact
    /// everywhere; its value is a distance within a cell or two of the surface. Deep in the
    /// liquid it holds the deep value [`crate::stages::surface::SurfaceModel::full_phi`]
    /// where a narrow band leaves no particles, and with the soft minimum
    /// (`solver.surface_softness`) wherever the step read only its sign, unless
    /// `solver.surface_interior_values` (see [`crate::stages::surface::Reads`]).
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
            return self.start_volume;
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
        let reach = (3f64.sqrt() * self.largest_face_speed() * dt / grid.dx).ceil() as usize;
        let width = self.settings.solver.narrow_band.width() + reach;
        let m = surface::per_axis(self.settings.solver.particles_per_cell);
        let node_sdf = &self.statics.node_sdf;
        let bodies = &self.bodies;
        let margin = self.push_margin();
        let admit =
            |x: Vec3| node_sdf.sample(&grid, x) > 0.0 && bodies.iter().all(|b| b.sdf(x) > margin);
        // Shared with a step's undo: the update changes a copy (`Arc::make_mut` without
        // copying the density the update makes anew).
        let shared = self.band.as_mut()?;
        if Arc::get_mut(shared).is_none() {
            *shared = Arc::new(shared.for_update());
        }
        let band = Arc::get_mut(shared).expect("the band is not shared now");
        let u = &self.u;
        // Those the last step's φ_L was made of (when nothing else moved them since).
        let bins = self.surface_bins.take(&self.particles, self.step);
        let particles = &mut self.particles;
        Some(band::update(particles, bins, band, &outside, width, u, dt, &grid, m, admit))
    }

    /// The bodies, in the order they were added.
    pub fn bodies(&self) -> &[RigidBody] {
        &self.bodies
    }

    /// The bodies, to change their state in place, unchecked (their number and order stay).
    pub(crate) fn bodies_mut(&mut self) -> &mut [RigidBody] {
        &mut self.bodies
    }

    /// Fluid velocity on the grid's faces, m/s.
    pub fn velocity_field(&self) -> &Mac {
        &self.u
    }

    /// Replaces the fluid velocity on the faces. Errors: a field of another grid's shape, or
    /// a velocity that is not finite.
    pub fn set_velocity_field(&mut self, u: Mac) -> Result<()> {
        for a in 0..3 {
            let want = self.grid.faces(a).len();
            if u.c[a].len() != want {
                return Err(Error::InvalidSettings {
                    key: "velocity field".into(),
                    message: format!("has {} faces along axis {a}, the grid {want}", u.c[a].len()),
                });
            }
            if let Some(f) = u.c[a].iter().position(|x| !x.is_finite()) {
                return Err(Error::InvalidSettings {
                    key: "velocity field".into(),
                    message: format!("face {f} along axis {a} is {}, not finite", u.c[a][f]),
                });
            }
        }
        self.u = u;
        self.largest_u = None;
        Ok(())
    }

    /// Marker particle positions, m.
    pub fn particles(&self) -> &[Vec3] {
        &self.particles
    }

    /// Replaces the marker particles (with the surface frozen, φ_L stays the initial
    /// particles'). Errors: a position that is not finite or outside the tank, and a
    /// simulation with a narrow band (`solver.narrow_band`), whose deep cells stand for
    /// particles it does not hold.
    pub fn set_particles(&mut self, particles: Vec<Vec3>) -> Result<()> {
        if self.band.is_some() {
            return Err(Error::InvalidSettings {
                key: "solver.narrow_band".into(),
                message: "the particles of a simulation with a narrow band cannot be replaced \
                          (its deep cells stand for particles it does not hold)"
                    .into(),
            });
        }
        let size = self.grid.size();
        if let Some(i) = particles
            .iter()
            .position(|p| !(p.is_finite() && p.cmpge(Vec3::ZERO).all() && p.cmple(size).all()))
        {
            return Err(Error::InvalidSettings {
                key: format!("particles[{i}]"),
                message: format!(
                    "{:?} must be finite and inside the tank [0, 0, 0]..{:?}",
                    particles[i].to_array(),
                    size.to_array()
                ),
            });
        }
        self.particles = particles;
        self.start_volume = self.liquid_volume();
        Ok(())
    }

    /// The liquid volume the particles held at the start (or when last set), m³: what
    /// `solver.volume_control` keeps.
    pub fn start_volume(&self) -> f64 {
        self.start_volume
    }

    /// Each body's handle, in the order of [`Simulation::bodies`].
    pub fn handles(&self) -> &[BodyHandle] {
        &self.handles
    }

    /// Where body `h` is in [`Simulation::bodies`] (None for a removed body or a handle of
    /// another simulation).
    pub fn index_of(&self, h: BodyHandle) -> Option<usize> {
        if h.world != self.world {
            return None;
        }
        self.handles.iter().position(|&x| x == h)
    }

    fn index(&self, h: BodyHandle) -> Result<usize> {
        self.index_of(h).ok_or(Error::UnknownBody { handle: h.id })
    }

    /// Body `h` (also `sim[h]`).
    pub fn body(&self, h: BodyHandle) -> Result<&RigidBody> {
        Ok(&self.bodies[self.index(h)?])
    }

    /// Scales body `h`'s mass to `kg`, its inertia with it (its density changes, not its
    /// shape). Errors: an unknown handle, a mass that is not a positive finite number.
    pub fn set_mass(&mut self, h: BodyHandle, kg: f64) -> Result<()> {
        let i = self.index(h)?;
        if !(kg.is_finite() && kg > 0.0) {
            return Err(Error::InvalidSettings {
                key: format!("body {:?}", self.bodies[i].name),
                message: format!("mass must be a positive number, got {kg}"),
            });
        }
        self.bodies[i].set_mass(kg);
        Ok(())
    }

    /// Sets who moves body `h` (see [`Motion`](crate::geometry::body::Motion)); its state
    /// stays. Errors: an unknown handle.
    pub fn set_motion(
        &mut self,
        h: BodyHandle,
        motion: crate::geometry::body::Motion,
    ) -> Result<()> {
        let i = self.index(h)?;
        self.bodies[i].motion = motion;
        Ok(())
    }

    /// Adds a body at runtime. It must lie inside the tank, with a finite state and a
    /// positive mass; marker particles inside it are removed (the body displaces that
    /// liquid).
    ///
    /// Refused with [`Error::InvalidSettings`] naming the body: a mass or inertia that is
    /// not a positive finite number, a pose or velocity that is not finite, an orientation
    /// further than 10⁻⁶ from a unit quaternion (one that close is used as it is), a body
    /// not strictly inside the tank, and, with contact off, a body that overlaps another
    /// where one of the two is dynamic (nothing would keep them apart). A body thinner or
    /// smaller than the grid resolves gets its warning ([`Simulation::warnings`]) here.
    pub fn add_body(&mut self, body: RigidBody) -> Result<BodyHandle> {
        let invalid =
            |message| Error::InvalidSettings { key: format!("body {:?}", body.name), message };
        check_body(&body, self.grid.size(), 0.0).map_err(invalid)?;
        if !self.settings.contact.enabled {
            if let Some(other) = self.bodies.iter().find(|b| overlap(b, &body)) {
                return Err(invalid(overlap_message(&other.name)));
            }
        }
        let margin = 1e-3 * self.grid.dx;
        let displaced = surface::Displaced::of(&body, &self.particles, margin);
        self.particles.retain(|x| body.sdf(*x) > margin);
        let h = BodyHandle { world: self.world, id: self.next_handle };
        self.next_handle += 1;
        let mut warnings = Vec::new();
        if let Some(w) = thin_body_warning(&body, self.grid.dx) {
            self.warn(&mut warnings, w);
        }
        if !self.settings.contact.enabled
            && body.motion == crate::geometry::body::Motion::Dynamic
            && body.mass > self.settings.fluid.density * body.volume()
        {
            let w = format!(
                "body {} is denser than the liquid and contact is off: when it reaches the \
                 floor the step fails with BodyLeftTank (turn contact on with \
                 SimulationBuilder::contact(ContactSettings::on()))",
                body.name
            );
            self.warn(&mut warnings, w);
        }
        let faces = body.face_fractions(&self.grid);
        if let Some(w) =
            volume_warning(&body, faces.volume_error(&self.grid, body.volume()), self.grid.dx)
        {
            self.warn_about(&mut warnings, "volume", h, w);
        }
        self.bodies.push(body);
        self.displaced.push(displaced);
        self.handles.push(h);
        self.fluid_forces.push([0.0; 6]);
        Ok(h)
    }

    /// Removes body `h` and returns it. The space it held is left to the liquid and air.
    pub fn remove_body(&mut self, h: BodyHandle) -> Result<RigidBody> {
        let i = self.index(h)?;
        self.handles.remove(i);
        self.fluid_forces.remove(i);
        self.displaced.remove(i);
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
        check_body(&b, self.grid.size(), EXTERNAL_REACH * self.grid.dx).map_err(|message| {
            Error::InvalidSettings { key: format!("body {:?}", b.name), message }
        })?;
        self.bodies[i] = b;
        Ok(())
    }

    /// The pressure force (N) and torque (N·m, about the centre of mass) of the last step's
    /// solve on body `h` (zero before the first step and for bodies held still; for a
    /// kinematic body, what driving it along its motion meets).
    ///
    /// With contact on ([`crate::world::ContactSettings`]), the force includes what holds a
    /// body up against the floor or a wall: contact is held inside the pressure solve, so a
    /// body resting on the floor shows its weight less its buoyancy there as well. For a
    /// [`Motion::External`](crate::geometry::body::Motion::External) body, hand the caller's
    /// engine this force and leave contact off here (its engine resolves it).
    pub fn fluid_force(&self, h: BodyHandle) -> Result<(Vec3, Vec3)> {
        let f = self.fluid_forces[self.index(h)?];
        Ok((f.linear(), f.angular()))
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
        self.particle_phi_into(&mut phi, None);
        phi
    }

    /// With `reads`, where a step reads φ's value (see [`surface::Reads`]): the φ a step
    /// makes, its value only there. Without, [`Simulation::particle_phi`].
    pub(crate) fn particle_phi_into(&self, phi: &mut Vec<f64>, reads: Option<surface::Reads<'_>>) {
        match &self.frozen_phi {
            Some(frozen) => {
                phi.clear();
                phi.extend_from_slice(frozen);
            }
            None => {
                let bins = Bins::new(&self.particles, &self.grid);
                surface::liquid_sdf_into(
                    phi,
                    &self.particles,
                    &bins,
                    &self.ghosts_at(&self.bodies),
                    &self.grid,
                    &self.surface_model(),
                    self.band.as_deref().map(Band::deep),
                    reads,
                );
                // The next step's band update bins these same particles.
                if self.band.is_some() {
                    self.surface_bins.keep(bins, self.step);
                }
            }
        }
    }

    /// Where the solids are now.
    pub fn geometry(&self) -> Geometry {
        self.geometry_with(&self.bodies, body_faces(&self.grid, &self.bodies))
    }

    /// Where the solids are with `bodies` in place of this simulation's, whose face fractions
    /// are `faces` (the backward pass has them on its tape).
    pub(crate) fn geometry_with(
        &self,
        bodies: &[RigidBody],
        faces: Vec<fractions::BodyFaces>,
    ) -> Geometry {
        let ramp = self.settings.solver.body_ramp;
        Geometry::new_in(self.spare.geometry(), &self.grid, &self.statics, bodies, faces, ramp)
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

    /// Whether [`Simulation::step`] and [`Simulation::advance`] measure the liquid for their
    /// reports (on unless [`Simulation::set_report_measures`] turned it off).
    pub fn report_measures(&self) -> bool {
        self.measures
    }

    /// Whether the reports of [`Simulation::step`] and [`Simulation::advance`] measure the
    /// liquid: its mechanical energy ([`Simulation::energy`], a velocity sample at every
    /// marker particle), its volume ([`Simulation::liquid_volume`], a deposit of every
    /// particle), its fastest speed, its face-weighted kinetic energy and its largest
    /// divergence. On by default: a run's summary and the physics checks read them. Off,
    /// those fields are NaN (the energy zero) and the step is otherwise the same, bit for
    /// bit: for a game or control loop that reads none of them (on the 64×32×64 pool of
    /// `examples/realtime_pool.rs`, a sixth of a frame). [`Simulation::energy`] and
    /// [`Simulation::liquid_volume`] still measure when called.
    pub fn set_report_measures(&mut self, on: bool) {
        self.measures = on;
    }

    /// Make φ_L's value in every cell from here on (`solver.surface_interior_values`), for
    /// output that reads it deep in the liquid: [`Simulation::liquid_phi`], the VTK frames,
    /// the surface mesh (which interpolates it within two cells of the surface). The step's
    /// results are the same bits either way; off, the soft surface's φ costs about half.
    /// The CLI turns it on for a run that writes VTK frames or surface meshes.
    pub fn set_interior_values(&mut self, on: bool) {
        self.settings.solver.surface_interior_values = on;
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

impl std::ops::Index<BodyHandle> for Simulation {
    type Output = RigidBody;

    /// Body `h`. Panics for a handle that names no body here; [`Simulation::body`] returns
    /// [`Error::UnknownBody`] instead.
    fn index(&self, h: BodyHandle) -> &RigidBody {
        match self.index_of(h) {
            Some(i) => &self.bodies[i],
            None => panic!("no body with handle {} in this simulation", h.id),
        }
    }
}
