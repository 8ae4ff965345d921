//! A running simulation: the liquid on a MAC grid, its marker particles, and the rigid bodies
//! coupled to it, with the step as a pipeline of named stages (the paper's Algorithm 2):
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

use super::settings::{check_finite, check_positive, SettingError, SolverSettings, WorldSettings};
use super::step::{
    body_faces, generalized_velocity, kinetic_energy, predicted_velocity, BodyForce, Energy,
    Geometry, Spare, StageSeconds, StaticGeometry, StepParams, StepReport, StepSystem, NEAR_SOLID,
};
use super::tape::{ParticleRecord, Replay, Solves, StepRecord, Tape};
use crate::error::{Error, Result};
use crate::geometry::body::{BodyState, RigidBody};
use crate::geometry::fractions;
use crate::geometry::grid::{Grid, Mac};
use crate::math::pool::on_pool_spinning;
use crate::geometry::shape::Solid;
use crate::geometry::weights::FaceWeights;
use crate::math::par::MIN_LEN;
use crate::math::{v3, Vec3};
use crate::stages::band::{self, Band, BandChange};
use crate::stages::contact::{contact_possible, hold_contact, ContactChange, ContactHold};
use crate::stages::density::{self, DensityInputs, DensityStats};
use crate::stages::extrapolate::correct_with_bodies;
use crate::stages::forces::body_velocity;
use crate::stages::pressure::PressureParams;
use crate::stages::surface::{self, Bins, SurfaceModel};
use rayon::prelude::*;
use std::sync::Arc;
use std::time::Instant;

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
    /// Every warning so far (each once).
    warnings: Vec<String>,
    /// The last step's whole-grid arrays, for the next step (or step adjoint) to build into;
    /// shared between clones.
    spare: Arc<Spare>,
}

/// A body's face fractions may miss its volume by this much (relative) before a step warns.
const VOLUME_TOLERANCE: f64 = 1e-3;

/// Builds a [`Simulation`] from plain parts: the tank, the settings, the liquid's initial
/// regions, static obstacles and bodies. Everything has a default but the tank.
///
/// ```
/// use diffluid::geometry::body::RigidBody;
/// use diffluid::geometry::shape::Solid;
/// use diffluid::math::{Pose, SharedShape, Vec3};
/// use diffluid::world::Simulation;
///
/// let pool = Solid::aabb(Vec3::ZERO, Vec3::new(0.6, 0.2, 0.4));
/// let ball = RigidBody::new(
///     "ball".into(),
///     SharedShape::ball(0.06),
///     Pose::from_translation(Vec3::new(0.3, 0.3, 0.2)),
///     500.0,
/// );
/// let mut sim = Simulation::builder([0.6, 0.4, 0.4], 0.05).dt(0.01).liquid(pool).body(ball).build()?;
/// let ball = sim.handles()[0];
/// for _ in 0..5 {
///     sim.step()?;
/// }
/// assert!(sim.body(ball).unwrap().v.y < 0.0, "the ball falls toward the water");
/// # Ok::<(), diffluid::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct SimulationBuilder {
    size: [f64; 3],
    dx: f64,
    settings: WorldSettings,
    liquid: Vec<Solid>,
    obstacles: Vec<Solid>,
    bodies: Vec<RigidBody>,
    notes: Vec<String>,
}

impl SimulationBuilder {
    /// A warning the simulation starts with (what its maker repaired or approximated: a
    /// scene file's mesh replaced by its convex hull).
    pub fn warning(mut self, w: String) -> Self {
        self.notes.push(w);
        self
    }

    /// All settings at once.
    pub fn settings(mut self, settings: WorldSettings) -> Self {
        self.settings = settings;
        self
    }

    /// The fixed step, s (default 0.01).
    pub fn dt(mut self, dt: f64) -> Self {
        self.settings.dt = dt;
        self
    }

    /// The liquid's density and gravity (default water, g = 9.81 m/s² down y).
    pub fn fluid(mut self, fluid: super::settings::Fluid) -> Self {
        self.settings.fluid = fluid;
        self
    }

    /// Solver settings.
    pub fn solver(mut self, solver: SolverSettings) -> Self {
        self.settings.solver = solver;
        self
    }

    /// Contact settings.
    pub fn contact(mut self, contact: super::settings::ContactSettings) -> Self {
        self.settings.contact = contact;
        self
    }

    /// A region that starts full of liquid (the liquid is the union of all of them).
    pub fn liquid(mut self, region: Solid) -> Self {
        self.liquid.push(region);
        self
    }

    /// A static obstacle.
    pub fn obstacle(mut self, solid: Solid) -> Self {
        self.obstacles.push(solid);
        self
    }

    /// A rigid body in its initial state.
    pub fn body(mut self, body: RigidBody) -> Self {
        self.bodies.push(body);
        self
    }

    /// The checks of [`SimulationBuilder::build`], without building: the grid the tank is cut
    /// into, or the first setting that fails.
    pub fn check(&self) -> std::result::Result<Grid, SettingError> {
        let grid = tank_grid(self.size, self.dx)?;
        self.settings.validate()?;
        let size = grid.size();
        let tol = 1e-9 * size.max_element();
        for (i, l) in self.liquid.iter().enumerate() {
            let (lo, hi) = l.bounds();
            if !(lo.is_finite() && hi.is_finite()) {
                return Err(SettingError::new(
                    format!("liquid[{i}]"),
                    "liquid region bounds must be finite",
                ));
            }
            if lo.min_element() < -tol || (hi - size).max_element() > tol {
                return Err(SettingError::new(
                    format!("liquid[{i}]"),
                    format!(
                        "liquid region spans {:?}..{:?}, outside the domain [0, 0, 0]..{:?}",
                        round6(lo.to_array()),
                        round6(hi.to_array()),
                        round6(size.to_array())
                    ),
                ));
            }
        }
        for (i, b) in self.bodies.iter().enumerate() {
            check_body(b, size, 0.0).map_err(|m| SettingError::new(format!("body[{i}]"), m))?;
        }
        let (bytes, particles) = self.memory_estimate(&grid);
        if particles > u32::MAX as f64 {
            return Err(SettingError::new(
                "solver.particles_per_cell",
                format!(
                    "about {particles:.3e} marker particles: more than the 2³² a bin can index"
                ),
            ));
        }
        let limit = match self.settings.solver.memory_limit_gb {
            Some(gb) => Some(gb * 1e9),
            None => available_memory(),
        };
        if let Some(limit) = limit {
            if bytes > limit {
                let how = if self.settings.solver.memory_limit_gb.is_some() {
                    "the limit solver.memory_limit_gb sets"
                } else {
                    "available; set solver.memory_limit_gb to run it anyway"
                };
                return Err(SettingError::new(
                    "domain",
                    format!(
                        "the scene needs about {:.1} GB ({} cells, {particles:.3e} particles) and \
                         {:.1} GB is {how}",
                        bytes / 1e9,
                        grid.num_cells(),
                        limit / 1e9
                    ),
                ));
            }
        }
        Ok(grid)
    }

    /// Bytes a forward run of this world takes at its peak, roughly, and the marker
    /// particles it seeds: 250 bytes per grid cell (the velocity and its advected copy, the
    /// face weights, φ_L, the pressure and density systems and their multigrids; `large_tank`
    /// measured 222 bytes a cell at 1 M cells and 230 at 8.4 M, its particles aside) and 56
    /// per particle (positions, their copies and bins). Particles are counted over the
    /// liquid regions' bounds; with `solver.narrow_band` only over the band: each region's
    /// bounds less the bounds shrunk by the band and two cells on every side off the tank's
    /// walls, and each body's bounds grown by as much. That counts at least the particles
    /// seeded (the regions' overlaps and the bodies' corners count twice), so a scene the
    /// machine can hold is not refused for particles the band never seeds.
    pub fn memory_estimate(&self, grid: &Grid) -> (f64, f64) {
        let cell = grid.dx.powi(3);
        let size = grid.size();
        let clip = |(lo, hi): (Vec3, Vec3)| (lo.max(Vec3::ZERO), hi.min(size));
        let volume =
            |(lo, hi): (Vec3, Vec3)| (hi - lo).max(Vec3::ZERO).to_array().iter().product::<f64>();
        let width = self.settings.solver.narrow_band;
        let margin = (width + 2) as f64 * grid.dx;
        let tol = 1e-9 * grid.dx;
        let liquid: f64 = self
            .liquid
            .iter()
            .map(|l| {
                let (lo, hi) = clip(l.bounds());
                if width == 0 {
                    return volume((lo, hi));
                }
                // The band runs along the region's faces that are not against a wall.
                let inner_lo = Vec3::select(lo.cmpgt(Vec3::splat(tol)), lo + margin, lo);
                let inner_hi = Vec3::select(hi.cmplt(size - tol), hi - margin, hi);
                volume((lo, hi)) - volume((inner_lo, inner_hi))
            })
            .sum();
        let near_bodies: f64 = if width == 0 {
            0.0
        } else {
            self.bodies
                .iter()
                .map(|b| {
                    let (lo, hi) = b.bounds();
                    volume(clip((lo - margin, hi + margin)))
                })
                .sum()
        };
        let everywhere = size.to_array().iter().product::<f64>();
        let ppc = self.settings.solver.particles_per_cell as f64;
        // Up to a whole particle: a region's cells in f64 come out a hair under a whole count.
        let particles = ((liquid + near_bodies).min(everywhere) / cell * ppc).ceil();
        (250.0 * grid.num_cells() as f64 + 56.0 * particles, particles)
    }

    /// With `solver.narrow_band`, the band before any particle is seeded: deep cells where
    /// the liquid regions (their signed distance at the cell centres) are more than the band
    /// and two cells from their surface, the static solids and the bodies, so a large tank
    /// never holds its full-volume particles. The first step's update starts from them.
    fn initial_band(&self, grid: &Grid, centre_in_solid: &[bool], radius: f64) -> Option<Band> {
        let width = self.settings.solver.narrow_band;
        if width == 0 {
            return None;
        }
        let cells = grid.cells();
        let liquid = surface::Regions::new(&self.liquid);
        let bodies: Vec<(Vec3, Vec3)> = self.bodies.iter().map(RigidBody::bounds).collect();
        let inside = |x: Vec3, (lo, hi): (Vec3, Vec3)| x.cmpge(lo).all() && x.cmple(hi).all();
        let outside: Vec<bool> = (0..grid.num_cells())
            .into_par_iter()
            .map(|c| {
                let [i, j, k] = cells.ijk(c);
                let x = cells.position(i, j, k);
                let wet = liquid.contain(x);
                let solid = centre_in_solid[c]
                    || self
                        .bodies
                        .iter()
                        .zip(&bodies)
                        .any(|(b, bb)| inside(x, *bb) && b.sdf(x) <= 0.0);
                !wet || solid
            })
            .collect();
        let deep = band::deep_cells(grid, &outside, width, None);
        let m = surface::per_axis(self.settings.solver.particles_per_cell);
        Some(Band::with_deep(grid, deep, radius, m))
    }

    /// Checks everything and sets up the simulation: static geometry, particles seeded in
    /// the liquid regions (outside obstacles and bodies), fluid at rest. A failed check is
    /// [`Error::InvalidSettings`] naming the key as a scene file would (`domain.dx`,
    /// `liquid[0]`, `body[1]`, `solver.theta_min`).
    pub fn build(self) -> Result<Simulation> {
        let grid =
            self.check().map_err(|e| Error::InvalidSettings { key: e.key, message: e.message })?;
        let node_sdf = fractions::NodeSdf::new(&grid, &self.obstacles);
        let weights = fractions::face_weights(&grid, &self.obstacles);
        let centre_in_solid = fractions::cell_centre_in_solid(&grid, &node_sdf);
        let ppc = self.settings.solver.particles_per_cell;
        let radius = surface::particle_radius(grid.dx, surface::per_axis(ppc));
        let band = self.initial_band(&grid, &centre_in_solid, radius);
        let deep = band.as_ref().map(|b| b.deep.as_slice());
        let mut particles = surface::seed(&grid, &self.liquid, ppc, &node_sdf, deep);
        let margin = 1e-3 * grid.dx;
        particles.retain(|x| self.bodies.iter().all(|b| b.sdf(*x) > margin));
        let (frozen_phi, frozen_volume) = if self.settings.solver.freeze_surface {
            let bins = Bins::new(&particles, &grid);
            let base = band.as_ref().map(|b| b.density.as_slice());
            let vol = surface::liquid_volume(&particles, &grid, ppc, base);
            let model = SurfaceModel { radius, sparse_cells: self.settings.solver.sparse_cells };
            let deep = band.as_ref().map(Band::deep);
            (Some(Arc::new(surface::liquid_sdf(&particles, &bins, &grid, &model, deep))), vol)
        } else {
            (None, 0.0)
        };
        let n = self.bodies.len();
        let mut warnings = self.notes.clone();
        warnings.extend(self.bodies.iter().filter_map(|b| thin_body_warning(b, grid.dx)));
        let band = band.map(Arc::new);
        let mut sim = Simulation {
            band,
            frozen_phi,
            frozen_volume,
            handles: (0..n as u32).map(BodyHandle).collect(),
            next_handle: n as u32,
            fluid_forces: vec![[0.0; 6]; n],
            bodies: self.bodies,
            u: Mac::zeros(&grid),
            particles,
            pressure: vec![0.0; grid.num_cells()],
            phi: vec![0.0; grid.num_cells()],
            statics: Arc::new(StaticGeometry {
                near_solid: fractions::cells_within(&grid, &node_sdf, NEAR_SOLID * grid.dx),
                node_sdf,
                weights: FaceWeights::new(&weights),
                centre_in_solid,
            }),
            radius,
            grid,
            settings: self.settings,
            step: 0,
            time: 0.0,
            warnings,
            spare: Arc::default(),
        };
        // The particles the band does not need go before the first step.
        let geometry = sim.geometry();
        sim.update_band(&geometry, 0.0);
        Ok(sim)
    }
}

/// Bytes of memory this process may still take: the smaller of the machine's available
/// memory and the cgroup's limit, when they can be read (Linux); None elsewhere.
fn available_memory() -> Option<f64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok()?;
    let avail = meminfo
        .lines()
        .find_map(|l| l.strip_prefix("MemAvailable:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map(|kb| kb * 1024.0)?;
    let cgroup = std::fs::read_to_string("/sys/fs/cgroup/memory.max")
        .ok()
        .and_then(|s| s.trim().parse::<f64>().ok());
    Some(cgroup.map_or(avail, |c| c.min(avail)))
}

/// The grid of a tank of `size` metres cut into cells of `dx`.
fn tank_grid(size: [f64; 3], dx: f64) -> std::result::Result<Grid, SettingError> {
    check_positive("domain.dx", dx)?;
    for (a, s) in size.iter().enumerate() {
        check_positive(&format!("domain.size[{a}]"), *s)?;
        let n = (s / dx).round();
        if n < 1.0 || (n * dx - s).abs() > 1e-6 * s {
            return Err(SettingError::new(
                "domain.size",
                format!("size {s} along axis {a} is not a whole number of cells of dx = {dx}"),
            ));
        }
    }
    let cells: f64 = size.iter().map(|s| (s / dx).round()).product();
    if cells > 512.0f64.powi(3) {
        return Err(SettingError::new(
            "domain",
            format!("{cells} cells is more than 512³; raise dx"),
        ));
    }
    Ok(Grid { n: size.map(|s| (s / dx).round() as usize), dx })
}

/// Bounds for messages, without floating-point noise (3.5999999999999996 → 3.6).
pub(crate) fn round6(a: [f64; 3]) -> [f64; 3] {
    a.map(|x| (x * 1e6).round() / 1e6)
}

/// A body a simulation can take: a positive finite mass, a finite state, and bounds inside
/// the tank: strictly inside for a body added (`reach` 0), within `reach` of the walls for one
/// whose caller's engine moved it (resting on the floor, a little into it).
fn check_body(b: &RigidBody, size: Vec3, reach: f64) -> std::result::Result<(), String> {
    if !(b.mass.is_finite() && b.mass > 0.0) {
        return Err(format!("mass must be a positive number, got {}", b.mass));
    }
    let finite = |key: &str, v: Vec3| {
        check_finite(key, &v.to_array()).map_err(|e| format!("{} {}", e.key, e.message))
    };
    finite("velocity", b.v)?;
    finite("angular_velocity", b.w)?;
    finite("force", b.force)?;
    finite("torque", b.torque)?;
    finite("position", b.x)?;
    let (lo, hi) = b.bounds();
    let inside = if reach == 0.0 {
        lo.min_element() > 0.0 && (hi - size).max_element() < 0.0
    } else {
        lo.min_element() >= -reach && (hi - size).max_element() <= reach
    };
    if !inside {
        let how = if reach == 0.0 {
            "it must start inside the tank".to_string()
        } else {
            format!("it must stay within {reach} m of the tank")
        };
        return Err(format!(
            "body spans {:?}..{:?}: {how} [0, 0, 0]..{:?}{}",
            round6(lo.to_array()),
            round6(hi.to_array()),
            round6(size.to_array()),
            if reach == 0.0 { " without touching a wall" } else { "" }
        ));
    }
    Ok(())
}

/// A warning when a body is thinner than half a cell (its thickness taken as 2·V/S, exact
/// for a plate). Its face fractions are then sampled more finely
/// ([`RigidBody::samples_per_cell`]) and keep its whole volume, so its buoyancy, down to the
/// finest sampling; but a body's faces stay open by 1 − β, so the liquid passes through it
/// (a body seals by its fractions alone from 2 cells up). Below the finest sampling it also
/// loses part of its buoyancy, as every thin body did before the finer sampling (a quarter-cell
/// plate sampled every dx/2 lost 75%).
fn thin_body_warning(b: &RigidBody, dx: f64) -> Option<String> {
    let t = b.thickness;
    if t >= 0.5 * dx {
        return None;
    }
    let r = b.samples_per_cell(dx);
    Some(if dx / r as f64 > t {
        format!(
            "body {} is about {:.3} cells thick, thinner than the 1/{r} cell its face fractions \
             are sampled at: it will feel only part of its buoyancy and let liquid through \
             (refine dx below {:.4} m)",
            b.name,
            t / dx,
            r as f64 * t
        )
    } else {
        format!(
            "body {} is about {:.2} cells thick, less than half a cell: its face fractions are \
             sampled every dx/{r} and keep its buoyancy, but liquid passes through it (a body's \
             faces stay open by 1 - β; refine dx below {:.4} m to seal it)",
            b.name,
            t / dx,
            0.5 * t
        )
    })
}

/// A contact velocity change below this (a thousandth of what gravity adds in a step) is
/// taken as none.
fn contact_tolerance(gravity: [f64; 3], dt: f64) -> f64 {
    1e-3 * v3(gravity).length().max(1.0) * dt
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
        let width = self.settings.solver.narrow_band + reach;
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
    /// solve on body `h` (zero before the first step and for fixed bodies).
    pub fn fluid_force(&self, h: BodyHandle) -> Option<(Vec3, Vec3)> {
        let f = self.fluid_forces[self.index_of(h)?];
        Some((Vec3::new(f[0], f[1], f[2]), Vec3::new(f[3], f[4], f[5])))
    }

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
        let g = v3(self.settings.fluid.gravity).length();
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
    /// [`Simulation::step`] with a shorter Δt; gradients use the fixed-Δt path.
    pub fn advance(&mut self, frame_dt: f64) -> Result<Vec<StepReport>> {
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
            reports.push(self.step_inner(h, None, Pressures::Solve)?);
            left -= h;
        }
        Ok(reports)
    }

    /// Whether a step keeps the pool's other workers spinning (`solver.spin_workers`; by
    /// default for grids of 64³ cells and more).
    pub fn spins(&self) -> bool {
        self.settings.solver.spin_workers.unwrap_or(self.grid.num_cells() >= 1 << 18)
    }

    /// Advances one step of the fixed Δt.
    pub fn step(&mut self) -> Result<StepReport> {
        let dt = self.settings.dt;
        self.step_inner(dt, None, Pressures::Solve)
    }

    /// Advances one step and records on `tape` what the backward pass needs.
    pub fn step_taped(&mut self, tape: &mut Tape) -> Result<StepReport> {
        let dt = self.settings.dt;
        self.step_inner(dt, Some(tape), Pressures::Solve)
    }

    /// Advances one step and keeps its pressure solves in `solves` (see [`Solves`]).
    pub(crate) fn step_recording(&mut self, solves: &mut Solves) -> Result<StepReport> {
        let dt = self.settings.dt;
        self.step_inner(dt, None, Pressures::Record(solves))
    }

    /// [`Simulation::step_taped`] that takes its pressures from `replay` instead of solving:
    /// the re-run of a step [`Simulation::step_recording`] made from the same state.
    /// It makes no report: what only a report reads (the divergence, the kinetic energy, the
    /// fastest speed, the liquid volume) is not computed.
    pub(crate) fn step_replayed(&mut self, tape: &mut Tape, replay: &mut Replay) -> Result<()> {
        let dt = self.settings.dt;
        self.step_inner(dt, Some(tape), Pressures::Replay(replay)).map(drop)
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

    /// What the step's system is assembled with for a step of `dt`.
    pub fn step_params(&self, dt: f64) -> StepParams {
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
    /// on the pool (its other workers spinning when [`Simulation::spins`]). A step that fails
    /// leaves φ_L that of the particles where they are.
    fn step_inner(
        &mut self,
        dt: f64,
        tape: Option<&mut Tape>,
        pressures: Pressures,
    ) -> Result<StepReport> {
        on_pool_spinning(self.spins(), || {
            let report = self.step_stages(dt, tape, pressures);
            if report.is_err() && self.phi.len() != self.grid.num_cells() {
                // The step failed while its system held φ_L's memory.
                self.phi = self.particle_phi();
            }
            report
        })
    }

    /// [`Simulation::step_inner`]'s stages.
    fn step_stages(
        &mut self,
        dt: f64,
        tape: Option<&mut Tape>,
        mut pressures: Pressures,
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
        let found: Vec<String> = self
            .bodies
            .iter()
            .zip(&volume_errors)
            .filter(|(_, e)| **e > VOLUME_TOLERANCE)
            .map(|(b, e)| {
                format!(
                    "body {}: its face fractions miss {:.1}% of its volume, so its buoyancy \
                     is off by as much (it is too small or thin for cells of {} m)",
                    b.name,
                    100.0 * e,
                    grid.dx
                )
            })
            .collect();
        for w in found {
            self.warn(&mut warnings, w);
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
        // What only the report reads: a replayed re-run's report is dropped, so it skips them.
        let report = !matches!(pressures, Pressures::Replay(_));
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
                air_body_faces,
                contact: contact || contact_moves,
                particles: particle_record,
            });
        }

        // 6. Rigid integration (or contact).
        self.move_bodies(dt, contact_moves)?;
        lap(&mut times.rigid);

        self.step += 1;
        self.time += dt;
        if !u.is_finite() {
            return Err(Error::NonFinite { step: self.step, what: "the fluid velocity".into() });
        }
        for b in &self.bodies {
            if !(b.x.is_finite() && b.v.is_finite() && b.w.is_finite() && b.q.is_finite()) {
                return Err(Error::NonFinite { step: self.step, what: format!("body {}", b.name) });
            }
        }
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
    pub fn push_margin(&self) -> f64 {
        1e-3 * self.grid.dx
    }

    /// How φ_L is made from the particles.
    pub fn surface_model(&self) -> SurfaceModel {
        SurfaceModel { radius: self.radius, sparse_cells: self.settings.solver.sparse_cells }
    }

    /// What the density projection of a step with `geometry` reads (None when it is off).
    pub fn density_inputs<'a>(&'a self, geometry: &'a Geometry) -> Option<DensityInputs<'a>> {
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
            let (p, stats) = match pressures {
                Pressures::Replay(replay) => replay.next(sys.pressure.len(), self.step + 1)?,
                _ => {
                    let b = sys.rhs(&u_hat, &vel);
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
            if !stats.converged {
                return Err(Error::NotConverged {
                    solve: crate::error::Solve::Pressure,
                    step: self.step + 1,
                    iterations: stats.iterations,
                    residual: stats.relative_residual,
                    tolerance: how.tolerance,
                });
            }
            let forces: Vec<[f64; 6]> = sys.couplings().iter().map(|c| c.force(&p)).collect();
            let after: Vec<[f64; 6]> = sys
                .couplings()
                .iter()
                .zip(&vel)
                .zip(&forces)
                .map(|((c, v), f)| {
                    let dv = c.dt_minv_times(f);
                    std::array::from_fn(|d| v[d] + dv[d])
                })
                .collect();
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
