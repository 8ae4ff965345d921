//! Building a [`Simulation`]: the builder, the checks it makes on every part, and the
//! initial state (particles seeded, the narrow band, the bodies' handles).

use super::memory::available_memory;
use super::{BodyHandle, Simulation};
use crate::error::{Error, Result};
use crate::geometry::body::RigidBody;
use crate::geometry::fractions;
use crate::geometry::grid::{Grid, Mac};
use crate::geometry::shape::Solid;
use crate::geometry::weights::FaceWeights;
use crate::math::Vec3;
use crate::stages::band::{self, Band};
use crate::stages::surface::{self, Bins};
use crate::world::settings::{
    check_finite, check_positive, NarrowBand, SettingError, SolverSettings, WorldSettings,
};
use crate::world::step::{StaticGeometry, NEAR_SOLID};
use rayon::prelude::*;
use std::sync::Arc;

/// Builds a [`Simulation`] from plain parts: the tank, the settings, the liquid's initial
/// regions, static obstacles and bodies. Everything has a default but the tank.
///
/// ```
/// use diffluid::prelude::*;
///
/// let pool = Solid::aabb(Vec3::ZERO, Vec3::new(0.6, 0.2, 0.4));
/// let ball = RigidBody::builder("ball", SharedShape::ball(0.06))
///     .density(500.0)
///     .pose(Pose::from_translation(Vec3::new(0.3, 0.3, 0.2)))
///     .build()?;
/// let mut sim = Simulation::builder([0.6, 0.4, 0.4], 0.05).dt(0.01).liquid(pool).body(ball).build()?;
/// let ball = sim.handles()[0];
/// for _ in 0..5 {
///     sim.step()?;
/// }
/// assert!(sim[ball].v.y < 0.0, "the ball falls toward the water");
/// # Ok::<(), diffluid::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct SimulationBuilder {
    pub(super) size: [f64; 3],
    pub(super) dx: f64,
    pub(super) settings: WorldSettings,
    pub(super) liquid: Vec<Solid>,
    pub(super) obstacles: Vec<Solid>,
    pub(super) bodies: Vec<RigidBody>,
    pub(super) notes: Vec<String>,
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
    pub fn fluid(mut self, fluid: crate::world::settings::Fluid) -> Self {
        self.settings.fluid = fluid;
        self
    }

    /// Solver settings.
    pub fn solver(mut self, solver: SolverSettings) -> Self {
        self.settings.solver = solver;
        self
    }

    /// Contact settings (default off, as in a scene file): `.contact(ContactSettings::on())`
    /// lets rapier hold bodies against the walls, the floor and each other (needs the
    /// `contact` feature). Off, a body that reaches a wall stops the step with
    /// [`Error::BodyLeftTank`], and [`Simulation::add_body`] warns about a dynamic body
    /// denser than the liquid.
    ///
    /// Why off by default: a world built in code gives the same numbers as the scene file
    /// that describes it (contact is off there too), and the gradient through a step in which
    /// contact acted costs more (see `gradients::GradientOptions::through_contact`). A program
    /// that only steps forward (a game loop) wants it on.
    pub fn contact(mut self, contact: crate::world::settings::ContactSettings) -> Self {
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
            if !self.settings.contact.enabled {
                if let Some(other) = self.bodies[..i].iter().find(|o| overlap(o, b)) {
                    return Err(SettingError::new(
                        format!("body[{i}]"),
                        format!("body {}: {}", b.name, overlap_message(&other.name)),
                    ));
                }
            }
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

    /// With `solver.narrow_band`, the band before any particle is seeded: deep cells where
    /// the liquid regions (their signed distance at the cell centres) are more than the band
    /// and two cells from their surface, the static solids and the bodies, so a large tank
    /// never holds its full-volume particles. The first step's update starts from them.
    /// `auto` takes the band when enough of the liquid is deep
    /// ([`NarrowBand::AUTO_DEEP_SHARE`]). Returns the band, the width chosen (0 for none)
    /// and what was chosen, in words.
    fn initial_band(
        &self,
        grid: &Grid,
        centre_in_solid: &[bool],
        radius: f64,
    ) -> (Option<Band>, usize, String) {
        let setting = self.settings.solver.narrow_band;
        let width = setting.width();
        if width == 0 {
            return (None, 0, "particles fill the liquid (narrow_band = 0)".into());
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
        let wet = outside.iter().filter(|&&o| !o).count();
        let share = deep.iter().filter(|&&d| d).count() as f64 / wet.max(1) as f64;
        let percent = (100.0 * share).round();
        if setting == NarrowBand::Auto && share < NarrowBand::AUTO_DEEP_SHARE {
            let why = format!(
                "particles fill the liquid (auto: {percent}% of its cells deep at a band of \
                 {width}, under {:.0}%)",
                100.0 * NarrowBand::AUTO_DEEP_SHARE
            );
            return (None, 0, why);
        }
        let how = if setting == NarrowBand::Auto { "auto" } else { "narrow_band" };
        let why = format!("narrow band {width} ({how}: {percent}% of the liquid's cells deep)");
        let model = self.settings.solver.surface_model(grid.dx, radius);
        (Some(Band::with_deep(grid, deep, &model)), width, why)
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
        let radius = self.settings.solver.particle_radius(grid.dx);
        let (band, width, model) = self.initial_band(&grid, &centre_in_solid, radius);
        let mut settings = self.settings;
        settings.solver.narrow_band = NarrowBand::Cells(width);
        let deep = band.as_ref().map(|b| b.deep.as_slice());
        let mut particles = surface::seed(&grid, &self.liquid, ppc, &node_sdf, deep);
        let margin = 1e-3 * grid.dx;
        let displaced: Vec<surface::Displaced> =
            self.bodies.iter().map(|b| surface::Displaced::of(b, &particles, margin)).collect();
        particles.retain(|x| self.bodies.iter().all(|b| b.sdf(*x) > margin));
        let start_volume = {
            let base = band.as_ref().map(|b| b.density.as_slice());
            surface::liquid_volume(&particles, &grid, ppc, base)
        };
        let frozen_phi = settings.solver.freeze_surface.then(|| {
            let bins = Bins::new(&particles, &grid);
            let surface = settings.solver.surface_model(grid.dx, radius);
            let deep = band.as_ref().map(Band::deep);
            let ghosts = surface::counted_ghosts(&surface, &self.bodies, &displaced);
            Arc::new(surface::liquid_sdf(&particles, &bins, &ghosts, &grid, &surface, deep, None))
        });
        let n = self.bodies.len();
        let mut warnings = self.notes.clone();
        warnings.extend(self.bodies.iter().filter_map(|b| thin_body_warning(b, grid.dx)));
        let band = band.map(Arc::new);
        let world = super::next_world();
        let mut sim = Simulation {
            band,
            frozen_phi,
            start_volume,
            handles: (0..n as u32).map(|id| BodyHandle { world, id }).collect(),
            world,
            next_handle: n as u32,
            fluid_forces: vec![[0.0; 6]; n],
            bodies: self.bodies,
            displaced,
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
            settings,
            model,
            step: 0,
            time: 0.0,
            warnings,
            warned: Vec::new(),
            spare: Arc::default(),
            rollback: true,
            measures: true,
            surface_bins: Default::default(),
            largest_u: None,
        };
        // The particles the band does not need go before the first step.
        let geometry = sim.geometry();
        sim.update_band(&geometry, 0.0);
        Ok(sim)
    }
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
/// the tank: strictly inside for a body added (`reach` 0: more than 1e-9 of the tank's size
/// from every wall), within `reach` of the walls for one
/// whose caller's engine moved it (resting on the floor, a little into it).
pub(super) fn check_body(b: &RigidBody, size: Vec3, reach: f64) -> std::result::Result<(), String> {
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
    let norm = b.q.length();
    if !norm.is_finite() {
        return Err(format!("orientation must be finite, got {:?}", b.q.to_array()));
    }
    if (norm - 1.0).abs() > QUATERNION_TOLERANCE {
        return Err(format!(
            "orientation {:?} has length {norm}: it must be a unit quaternion (normalise it)",
            b.q.to_array()
        ));
    }
    if !b.local_inertia.is_finite() || !b.local_com.is_finite() {
        return Err("inertia and centre of mass must be finite (a shape too large?)".into());
    }
    let (lo, hi) = b.bounds();
    let inside = if reach == 0.0 {
        // Within round-off of a wall is touching it, at the floor (0) and at the lid (n·dx,
        // which is 0.6000000000000001 for 6 cells of 0.1) alike.
        let tol = 1e-9 * size.max_element();
        lo.min_element() > tol && (hi - size).max_element() < -tol
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

/// How far from unit length a body's orientation quaternion may be: rapier's and glam's
/// normalised quaternions are within a few ulps; one further off is not a rotation (it scales
/// the shape's samples: 0.046 N of force where 6.52 N was right).
const QUATERNION_TOLERANCE: f64 = 1e-6;

/// Whether bodies `a` and `b` overlap where one of them is dynamic: with contact off nothing
/// keeps them apart (an external body's engine keeps its own apart; fixed and kinematic
/// bodies go where they are told). Shapes parry cannot test against each other count as
/// apart.
pub(super) fn overlap(a: &RigidBody, b: &RigidBody) -> bool {
    use crate::geometry::body::Motion;
    if a.motion != Motion::Dynamic && b.motion != Motion::Dynamic {
        return false;
    }
    parry3d_f64::query::intersection_test(&a.pose(), &*a.shape.0, &b.pose(), &*b.shape.0)
        .is_ok_and(|i| i.intersecting)
}

/// The message of a body that overlaps body `other` with contact off.
pub(super) fn overlap_message(other: &str) -> String {
    format!(
        "overlaps body {other}, and with contact off nothing keeps them apart: move it, or \
         turn contact on (SimulationBuilder::contact, or [contact] enabled = true in a scene)"
    )
}

/// A body's face fractions may miss its volume by this much (relative) before a step warns.
const VOLUME_TOLERANCE: f64 = 1e-3;

/// The warning about a body whose face fractions miss the fraction `error` of its volume,
/// if that is more than [`VOLUME_TOLERANCE`].
pub(super) fn volume_warning(b: &RigidBody, error: f64, dx: f64) -> Option<String> {
    (error > VOLUME_TOLERANCE).then(|| {
        format!(
            "body {}: its face fractions miss {:.1}% of its volume, so its buoyancy is off by \
             as much (it is too small or thin for cells of {} m; each step's report has its \
             volume_error)",
            b.name,
            100.0 * error,
            dx
        )
    })
}

/// A warning when a body is thinner than the finest sampling of its face fractions
/// ([`RigidBody::samples_per_cell`], down to dx/16; its thickness taken as 2·V/S, exact for a
/// plate): it falls between the samples and loses part of its buoyancy (a quarter-cell plate
/// sampled every dx/2 lost 75%). A thinner body down to that sampling keeps its volume, and
/// seals the liquid on its two sides as it moves ([`crate::geometry::seal`]).
pub(super) fn thin_body_warning(b: &RigidBody, dx: f64) -> Option<String> {
    let t = b.thickness;
    let r = b.samples_per_cell(dx);
    (t < 0.5 * dx && dx / r as f64 > t).then(|| {
        format!(
            "body {} is about {:.3} cells thick, thinner than the 1/{r} cell its face fractions \
             are sampled at: it will feel only part of its buoyancy (refine dx below {:.4} m)",
            b.name,
            t / dx,
            r as f64 * t
        )
    })
}
