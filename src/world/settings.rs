//! What a world is set up with: plain structs with documented defaults. A scene file's
//! `[solver]` and `[contact]` tables deserialise into [`SolverSettings`] and
//! [`ContactSettings`] directly; a program fills them in code.

use crate::solvers::{LinearSolve, Preconditioner};
pub use crate::stages::contact::ContactSettings;
use crate::stages::extrapolate::SurfaceBlend;
use crate::stages::pressure::{Coupling, GhostFluid};
use crate::stages::surface::{self, SurfaceModel};
use serde::{Deserialize, Serialize};

/// A setting that fails its check: the key (as a scene file names it, `solver.theta_min`)
/// and what is wrong.
#[derive(Clone, Debug, PartialEq)]
pub struct SettingError {
    /// The key.
    pub key: String,
    /// What is wrong.
    pub message: String,
}

impl SettingError {
    /// A failure of `key`.
    pub fn new(key: impl Into<String>, message: impl Into<String>) -> SettingError {
        SettingError { key: key.into(), message: message.into() }
    }
}

/// Checks that `x` is a finite positive number.
pub fn check_positive(key: &str, x: f64) -> Result<(), SettingError> {
    if x.is_finite() && x > 0.0 {
        Ok(())
    } else {
        Err(SettingError::new(key, format!("must be a positive number, got {x}")))
    }
}

/// Checks that every value is finite.
pub fn check_finite(key: &str, xs: &[f64]) -> Result<(), SettingError> {
    if xs.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(SettingError::new(key, format!("must be finite, got {xs:?}")))
    }
}

/// The liquid.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Fluid {
    /// Density in kg/m³.
    pub density: f64,
    /// Gravity in m/s² (on the liquid and on the bodies).
    pub gravity: [f64; 3],
}

impl Default for Fluid {
    /// Water under Earth's gravity, y up.
    fn default() -> Self {
        Fluid { density: 1000.0, gravity: [0.0, -9.81, 0.0] }
    }
}

impl Fluid {
    /// The checks of `fluid.*`.
    pub fn validate(&self) -> Result<(), SettingError> {
        check_positive("fluid.density", self.density)?;
        check_finite("fluid.gravity", &self.gravity)
    }
}

/// Writes an optional setting whose absence is not its default as 0 when it is `None` (the
/// setting's off).
fn off_as_zero<S: serde::Serializer>(value: &Option<f64>, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_f64(value.unwrap_or(0.0))
}

/// The most extrapolation layers a scene may ask for: far more than advection ever reads
/// (Δt·|u|/dx cells), and below what the layer counter of `extrapolate.rs` holds (253).
pub const MAX_EXTRAPOLATION_LAYERS: usize = 64;

/// The largest `solver.density_gain`: the surge lost 7% of its volume at 2.5, the
/// displacement overshooting its cells' excess.
pub const MAX_DENSITY_GAIN: f64 = 2.0;

/// The most density projection passes a step may ask for (`solver.density_passes`): each
/// leaves about a third of what it was given, so a fourth has little left to take.
pub const MAX_DENSITY_PASSES: usize = 4;

/// Solver settings (a scene's `[solver]` table). Every field has a default, given with its
/// reason.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SolverSettings {
    /// CG stops when ‖r‖₂ ≤ tolerance·‖b‖₂. Default 1e-8: the still-water and Archimedes
    /// checks need pressure to well under 1%, and MIC(0) reaches 1e-8 in a few dozen
    /// iterations on the shipped grids.
    pub tolerance: f64,
    /// CG iteration cap; reaching it is an error, never a silent answer. Default 2000.
    pub max_iterations: usize,
    /// Preconditioner: `mic0`, `multigrid`, `none` or `auto`. Default `auto`: whichever of
    /// MIC(0) and multigrid solves faster for the number of unknowns (measured crossover in
    /// [`Preconditioner::AUTO_CROSSOVER`]).
    pub preconditioner: Preconditioner,
    /// Layers of velocity extrapolated into air after projection. Default 3 (the paper's
    /// choice; advection reads at most Δt·|u|/dx cells beyond the surface).
    pub extrapolation_layers: usize,
    /// Marker particles seeded per liquid cell, on a regular sub-lattice: 1, 8, 27 or 64.
    /// Default 8.
    pub particles_per_cell: usize,
    /// Smallest ghost-fluid fraction θ at a liquid–air face. Default 1e-5: the clamp is a
    /// kink of the step where a face's θ crosses it, and with the blended faces
    /// (`surface_blend`) a face of small θ carries little of its projected velocity. 0.01
    /// (Gibou et al.'s, bounding the diagonal at 100× a full face) was the default before
    /// 6 December 2026; `large_tank` costs 1.08× as much in the smooth defaults.
    pub theta_min: f64,
    /// Ramp φ_L into the moving bodies over half a cell outside them instead of switching a
    /// cell from the particles' φ to the extension's as a body's surface crosses its centre
    /// (`stages/solid_phi.rs`). Default true (false before 6 December 2026). It makes the
    /// map continuous in the bodies' poses (a box under a moving surface: central
    /// differences at 1e-4 and 1e-6 within 2.6% instead of 17%; docs/gradients.md, "Bodies
    /// crossing cell centres").
    pub body_ramp: bool,
    /// Blend each liquid–air face from its projected velocity into the extrapolation's as
    /// the ghost-fluid fraction θ of its liquid side falls below `surface_blend` (the face's
    /// share of the projected velocity is min(1, θ/surface_blend)), start a face a body
    /// covers in part with the body's part known and its fluid part by that part's share,
    /// and let the extrapolation's layers weigh what they read by those shares, so the
    /// velocity changes continuously as a cell turns from liquid to air or a body comes to
    /// cover a face (`stages/extrapolate/blend.rs`); the density projection's displacement
    /// is blended the same way in its one layer. Default 0.5 (0, the yes/no rule, before
    /// 6 December 2026): with the other smooth defaults central differences at 1e-4 and 1e-6
    /// agree within 0.7% on a box under a moving surface (15% with the yes/no rules) and
    /// within 2.1% on the surge's velocities at 50 steps (27 to 350-fold). The blended faces
    /// no longer hold their liquid cells' flux at zero; the dam break's worst volume error
    /// over 100 steps is 0.60% with them, 0.52% without (docs/gradients.md, "Liquid–air
    /// faces blended into the extrapolation", "The smooth defaults"). 0 to 1, 0.5 being the
    /// surface at the face.
    pub surface_blend: f64,
    /// Push marker particles out of over-full cells after advecting them (particle density
    /// projection, see `density.rs`). Default true: without it the dam break loses about
    /// 10% of its volume to particles bunching at the floor.
    pub density_correction: bool,
    /// How many times its excess the density projection asks of an over-full cell's
    /// displacement in a step. The particles' density is read through the trilinear
    /// deposit, which sees a displacement only in part: a one-cell excess is (3/4)³ ≈ 0.42
    /// of its own cell's reading, and a particle in the half cell next to a wall deposits
    /// on the wall's cell wherever it is there. With a gain of 1 (Kugelstadt et al.'s
    /// projection) a step took out 41% of the dam break's excess and the particles ended
    /// its landing 1.39% short of its volume. Default 1.75; (0, 2].
    pub density_gain: f64,
    /// How many times a step runs the density projection, each on the particles the last
    /// one left (each pass solves again, so the stage costs that many times as much; a pass
    /// that finds no over-full cell ends them). What one pass leaves sits in the cells along
    /// the walls, where the deposit sees least of a displacement. Default 1; 1 to 4. Two
    /// take the dam break's worst volume error over 100 steps from 0.60% to 0.42% (the
    /// defaults), but make the map rougher at the scale an optimiser steps
    /// (docs/gradients.md, "The density projection's gain").
    pub density_passes: usize,
    /// A face of the density projection's operator whose weight w (its open fraction) is
    /// under `density_face_ramp` carries w/`density_face_ramp` of its displacement: as a
    /// body covers a face it fades to the zero of a closed face. Without it a face opens with
    /// a weight of 1e-9 and takes its full displacement at once, which the particles beside
    /// it read (a jump of the forward map). Default 0.2 (0, off, before 7 December 2026); 0
    /// to under 1.
    pub density_face_ramp: f64,
    /// Volume control without the density projection: each step's pressure solve gives
    /// every liquid cell whose marker particles hold more than a full cell a divergence that
    /// spreads `volume_control` times the excess in a step (Kim et al. 2007, "Volume control
    /// for simulation of liquid", with the error measured per cell). Particles that bunch are
    /// how a marker-particle liquid loses volume; the density projection moves them apart
    /// directly, through its classification of over-full cells (a jump of the forward map),
    /// while this moves them through the velocity, a continuously differentiable function of
    /// their positions, which the gradient follows. With `density_correction = false`, 4
    /// keeps the dam break's volume within 1% but for a transient of 1.9% as the column
    /// lands, over 100 steps, against 10.8% lost without it. Default: off (none given, or 0);
    /// 0 to 8. Not for a tank the liquid nearly fills: the excess, taken one-sided, has
    /// little air to go to there, and a closed, nearly full tank blew up with it.
    pub volume_control: Option<f64>,
    /// Close the air pockets of φ_L (see `stages/surface/pockets.rs`): air that reaches no
    /// point `close_pockets`·dx from the particles through air (a gap in the particles
    /// inside the liquid) is liquid, by a continuous function of φ_L. Such a pocket is a
    /// zero-pressure sink inside the liquid, and as it opens and closes the step jumps.
    /// Default 0.5 (off before 6 December 2026); 0 (off) to 0.6 cells. Written as 0 when
    /// off (`None`), so that a written scene reads back off, not as the default.
    #[serde(serialize_with = "off_as_zero")]
    pub close_pockets: Option<f64>,
    /// The density projection's CG stops when ‖r‖₂ ≤ density_tolerance·‖b‖₂ (b: the excess
    /// volume of the over-full cells). What is left is that fraction of the volume the
    /// projection moves, and the next step's projection takes it with what advection bunches
    /// up again, so the pressure's 1e-8 is more than it needs. Default 1e-6: measured against
    /// 1e-8, the dam break's worst volume error over 50 steps (1/40 m cells, full volume and
    /// a band of 3), `large_tank`'s over 20 steps, the live-surface gradient check of
    /// `gradcheck_live` and the surface meshes of `dam_break_ball` are the same to every
    /// printed digit, in 7–9 iterations instead of 9–13 on `large_tank`. At 1e-4 (5–6
    /// iterations) the volumes still agree to four digits and the gradient check to 2%, but a
    /// splash of `dam_break_ball` takes another path (see `large_tank.toml`, which uses it).
    pub density_tolerance: f64,
    /// A cell that holds a marker particle is liquid even where the particles' distance says
    /// air (thin sheets and splashes stay in the projection instead of drifting on
    /// extrapolated velocities, which loses volume). Default false (true before 6 December
    /// 2026): as the rule was (and is with `sparse_depth = 0`), it makes φ_L jump when a
    /// particle crosses a cell face, a kink of the forward map that gradients cannot see, and
    /// the density projection keeps the volume without it (the dam break's worst over 100
    /// steps 0.60% in the smooth defaults).
    pub sparse_cells: bool,
    /// With `sparse_cells`, how deep (cells) a particle must be inside its cell to make it
    /// liquid, φ_L falling continuously with the particle's depth up to there (see
    /// `stages/surface/distance.rs`, `sparse_phi`), its derivative followed by the gradient.
    /// Default 0: the rule as it was, a cell liquid the moment it holds a particle (the
    /// continuous rule moved the dam break's volume checks, see docs/gradients.md,
    /// "Sparse cells"). 0 to 0.5 cells; 0.05 is what was measured.
    pub sparse_depth: f64,
    /// Make φ_L a soft minimum of the particles' distances, of this softness τ (cells;
    /// `stages/surface/softmin.rs`), instead of the nearest particle's distance. The nearest
    /// particle's distance has a kink wherever another particle becomes a cell's nearest,
    /// which a surface's cells pass through all the time; the soft minimum is infinitely
    /// differentiable in the particles' positions. Default 0.35 (0, the nearest particle,
    /// before 7 December 2026); 0 or 0.01 to 0.5 cells.
    pub surface_softness: f64,
    /// With the soft minimum, make φ_L's value in every cell. By default a step makes it
    /// only where it reads a value, not just a sign, and gives the liquid's interior (cells
    /// more than a tenth of a cell deep with no air beside them, away from the solids) the
    /// deep value a narrow band's deep cells hold: the step's results are the same bits,
    /// and its φ costs about half (see `surface::Reads`). For output that reads φ_L's
    /// values deep in the liquid ([`crate::Simulation::liquid_phi`], the VTK files).
    pub surface_interior_values: bool,
    /// Sub-steps of the marker particles' advection per step. Default 0: as many as keep
    /// every particle within half a cell per sub-step, from the step's largest velocity
    /// (cheap, but the count changes as the flow speeds up, a jump of the forward map). A
    /// fixed count (at least that many, up to 64) makes the map smooth there.
    pub particle_substeps: usize,
    /// Marker particles only in a band this many cells wide (L∞) around the air and the
    /// solids; the liquid beyond is carried by the grid as full cells (see `stages/band.rs`).
    /// 0 fills the whole liquid; 2 to 32 is a band. The band is cheaper wherever the liquid
    /// is deeper than a few cells, and it adds to its width the cells a step's fastest
    /// velocity crosses. Default `"auto"`: a band of [`NarrowBand::AUTO_WIDTH`] where the
    /// scene starts with deep cells, none where it does not (see [`NarrowBand::Auto`]).
    pub narrow_band: NarrowBand,
    /// The most memory a simulation may take, GB. Default: none given, so the memory the
    /// machine has available (its free memory, or the cgroup limit) is the limit. Before
    /// anything is allocated, a scene's needs are estimated (see
    /// [`crate::world::SimulationBuilder::memory_estimate`]) and a scene over the limit is
    /// refused; a larger value here lets it run anyway.
    pub memory_limit_gb: Option<f64>,
    /// Hold the free surface fixed: the marker particles do not move and the liquid signed
    /// distance keeps its initial value (extended into the solids where they are now). The
    /// backward pass always holds the surface fixed (as the paper does); with this switch the
    /// forward pass is exactly the map the adjoint differentiates, which gradient checks need.
    /// It also skips all particle work. Default false.
    pub freeze_surface: bool,
    /// Keep the pool's other workers spinning through a step (and a backward pass), taking
    /// the step's parallel work as soon as it is split off, instead of sleeping between its
    /// loops and being woken for each (a step of `large_tank` runs about 375 loops, each
    /// wake a context switch; docs/performance.md, "Spinning workers", has the gain). The
    /// other workers then spend their idle moments spinning, not sleeping. Default:
    /// none given, so on for grids of 262,144 cells (64³) and more, where a step is long
    /// enough for it to pay; off below. The results are the same bits either way.
    pub spin_workers: Option<bool>,
    /// Liquid–body coupling. Default `monolithic`; `weak` is the partitioned baseline the
    /// stability map compares against (no gradients through it).
    pub coupling: Coupling,
    /// The most cells a liquid sample or body point may cross in one of the steps
    /// [`crate::world::Simulation::advance`] takes. Default 1 (semi-Lagrangian advection is
    /// stable at any CFL number, but the explicit free surface and the bodies' geometry,
    /// taken where it is at the start of a step, are accurate up to about one cell). The
    /// fixed-Δt [`crate::world::Simulation::step`] does not read it.
    pub cfl: f64,
}

impl Default for SolverSettings {
    fn default() -> Self {
        SolverSettings {
            tolerance: 1e-8,
            max_iterations: 2000,
            preconditioner: Preconditioner::Auto,
            extrapolation_layers: 3,
            particles_per_cell: 8,
            theta_min: 1e-5,
            body_ramp: true,
            surface_blend: 0.5,
            density_correction: true,
            density_gain: 1.75,
            density_passes: 1,
            density_face_ramp: 0.2,
            volume_control: None,
            close_pockets: Some(0.5),
            density_tolerance: 1e-6,
            sparse_cells: false,
            sparse_depth: 0.0,
            surface_softness: 0.35,
            surface_interior_values: false,
            particle_substeps: 0,
            narrow_band: NarrowBand::Auto,
            memory_limit_gb: None,
            freeze_surface: false,
            spin_workers: None,
            coupling: Coupling::Monolithic,
            cfl: 1.0,
        }
    }
}

impl SolverSettings {
    /// The surface rules of the defaults (since 6 December 2026, the smooth ones:
    /// `surface_blend`, `body_ramp`, `close_pockets`, `sparse_cells`, `theta_min`), the other
    /// settings left as they are.
    pub fn use_smooth_surface_rules(&mut self) {
        let d = SolverSettings::default();
        self.surface_blend = d.surface_blend;
        self.body_ramp = d.body_ramp;
        self.close_pockets = d.close_pockets;
        self.sparse_cells = d.sparse_cells;
        self.theta_min = d.theta_min;
    }

    /// The yes/no surface rules that were the defaults before 6 December 2026: no blend, no
    /// ramp, air pockets open, the sparse-cell rule, θ clamped at 0.01 (docs/gradients.md,
    /// "The smooth defaults"); the other settings left as they are.
    pub fn use_yes_no_surface_rules(&mut self) {
        self.surface_blend = 0.0;
        self.body_ramp = false;
        self.close_pockets = None;
        self.sparse_cells = true;
        self.theta_min = 0.01;
    }

    /// The pressure solve these settings ask for.
    pub fn linear(&self) -> LinearSolve {
        LinearSolve {
            preconditioner: self.preconditioner,
            tolerance: self.tolerance,
            max_iterations: self.max_iterations,
        }
    }

    /// The share of a cell's excess a step's solve spreads ([`Self::volume_control`]
    /// resolved): 0 when off.
    pub fn volume_rate(&self) -> f64 {
        match self.volume_control {
            Some(k) if !self.freeze_surface => k,
            _ => 0.0,
        }
    }

    /// The density projection's solve.
    pub fn density_linear(&self) -> LinearSolve {
        LinearSolve { tolerance: self.density_tolerance, ..self.linear() }
    }

    /// The marker particles' radius on cells of size `dx`, for the nearest particle's
    /// distance or their soft minimum ([`Self::surface_softness`]).
    pub fn particle_radius(&self, dx: f64) -> f64 {
        let m = surface::per_axis(self.particles_per_cell);
        match self.surface_softness {
            tau if tau > 0.0 => surface::soft_particle_radius(dx, m, tau),
            _ => surface::particle_radius(dx, m),
        }
    }

    /// How φ_L is made from the particles of radius `radius` (see
    /// [`Self::particle_radius`]) on cells of size `dx`: the nearest particle's distance or
    /// their soft minimum, and the sparse-cell rule.
    pub fn surface_model(&self, dx: f64, radius: f64) -> SurfaceModel {
        SurfaceModel {
            radius,
            sparse_cells: self.sparse_cells,
            sparse_depth: self.sparse_depth,
            softness: self.surface_softness * dx,
            per_axis: surface::per_axis(self.particles_per_cell),
        }
    }

    /// How liquid–air faces blend into the extrapolation ([`Self::surface_blend`]).
    pub fn blend(&self) -> SurfaceBlend {
        SurfaceBlend { theta: self.surface_blend }
    }

    /// The ghost-fluid θ.
    pub fn ghost_fluid(&self) -> GhostFluid {
        GhostFluid::clamped(self.theta_min)
    }

    /// The checks of `solver.*`.
    pub fn validate(&self) -> Result<(), SettingError> {
        for (key, t) in [
            ("solver.tolerance", self.tolerance),
            ("solver.density_tolerance", self.density_tolerance),
        ] {
            if !(t.is_finite() && t > 0.0 && t < 1.0) {
                return Err(SettingError::new(key, format!("must be in (0, 1), got {t}")));
            }
        }
        if self.max_iterations == 0 {
            return Err(SettingError::new("solver.max_iterations", "must be at least 1"));
        }
        if self.extrapolation_layers > MAX_EXTRAPOLATION_LAYERS {
            return Err(SettingError::new(
                "solver.extrapolation_layers",
                format!(
                    "must be at most {MAX_EXTRAPOLATION_LAYERS} (advection reads a few cells \
                     beyond the surface), got {}",
                    self.extrapolation_layers
                ),
            ));
        }
        let m = (self.particles_per_cell as f64).cbrt().round() as usize;
        if !(1..=4).contains(&m) || m * m * m != self.particles_per_cell {
            return Err(SettingError::new(
                "solver.particles_per_cell",
                format!(
                    "must be 1, 8, 27 or 64 (a regular sub-lattice), got {}",
                    self.particles_per_cell
                ),
            ));
        }
        if !(self.theta_min.is_finite() && self.theta_min > 0.0 && self.theta_min <= 0.5) {
            return Err(SettingError::new(
                "solver.theta_min",
                format!("must be in (0, 0.5], got {}", self.theta_min),
            ));
        }
        check_positive("solver.cfl", self.cfl)?;
        if !(self.surface_blend.is_finite() && (0.0..=1.0).contains(&self.surface_blend)) {
            return Err(SettingError::new(
                "solver.surface_blend",
                format!("must be in [0, 1] (a ghost-fluid fraction), got {}", self.surface_blend),
            ));
        }
        if !(self.density_gain.is_finite()
            && self.density_gain > 0.0
            && self.density_gain <= MAX_DENSITY_GAIN)
        {
            return Err(SettingError::new(
                "solver.density_gain",
                format!("must be in (0, {MAX_DENSITY_GAIN}], got {}", self.density_gain),
            ));
        }
        if !(1..=MAX_DENSITY_PASSES).contains(&self.density_passes) {
            return Err(SettingError::new(
                "solver.density_passes",
                format!("must be 1 to {MAX_DENSITY_PASSES}, got {}", self.density_passes),
            ));
        }
        if !(self.density_face_ramp.is_finite() && (0.0..1.0).contains(&self.density_face_ramp)) {
            return Err(SettingError::new(
                "solver.density_face_ramp",
                format!("must be in [0, 1), got {}", self.density_face_ramp),
            ));
        }
        if let Some(k) = self.volume_control {
            if !(k.is_finite() && (0.0..=8.0).contains(&k)) {
                return Err(SettingError::new(
                    "solver.volume_control",
                    format!("must be in [0, 8] (the share of a cell's excess spread in a step), got {k}"),
                ));
            }
        }
        if !(self.sparse_depth.is_finite() && (0.0..=0.5).contains(&self.sparse_depth)) {
            return Err(SettingError::new(
                "solver.sparse_depth",
                format!("must be in [0, 0.5] (cells), got {}", self.sparse_depth),
            ));
        }
        // Below 0.01 cells the far value e^{−R/τ} (R = 2 cells) and a cell's terms underflow
        // and φ would come out infinite in the air.
        let tau = self.surface_softness;
        if !(tau == 0.0 || (0.01..=0.5).contains(&tau)) {
            return Err(SettingError::new(
                "solver.surface_softness",
                format!("must be 0 (the nearest particle) or in [0.01, 0.5] (cells), got {tau}"),
            ));
        }
        if let Some(k) = self.close_pockets {
            if !(k.is_finite() && (0.0..=0.6).contains(&k)) {
                return Err(SettingError::new(
                    "solver.close_pockets",
                    format!("must be in [0, 0.6] (cells), got {k}"),
                ));
            }
        }
        if let Some(gb) = self.memory_limit_gb {
            check_positive("solver.memory_limit_gb", gb)?;
        }
        if self.particle_substeps > 64 {
            return Err(SettingError::new(
                "solver.particle_substeps",
                format!("must be 0 (adaptive) to 64, got {}", self.particle_substeps),
            ));
        }
        if let NarrowBand::Cells(w @ (1 | 33..)) = self.narrow_band {
            return Err(SettingError::new(
                "solver.narrow_band",
                format!(
                    "must be \"auto\", 0 (particles fill the liquid) or a band of 2 to 32 cells \
                     (φ_L reads particles up to 2 cells away), got {w}"
                ),
            ));
        }
        Ok(())
    }
}

/// The narrow band of marker particles a world runs with (`solver.narrow_band`): `"auto"`,
/// or a width in cells (0: particles fill the liquid).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum NarrowBand {
    /// A band of [`NarrowBand::AUTO_WIDTH`] cells when at least
    /// [`NarrowBand::AUTO_DEEP_SHARE`] of the liquid's cells would be deep at the start (more
    /// than the band and two cells from the air, the walls' solids and the bodies), no band
    /// otherwise: a shallow scene has nothing for a band to save and keeps every particle.
    /// [`crate::world::Simulation::model`] says which was chosen and why.
    #[default]
    Auto,
    /// A band this many cells wide; 0 fills the whole liquid with particles.
    Cells(usize),
}

impl NarrowBand {
    /// The width `auto` picks: the narrowest band the surface's distance reads (2 cells) and
    /// one more, as `large_tank` ran before `auto` (its accuracy figures in
    /// docs/performance.md, "The narrow band").
    pub const AUTO_WIDTH: usize = 3;

    /// The share of the liquid's cells that must be deep for `auto` to take a band. A band
    /// costs its update every step and saves the deep cells' particles; on the shipped scenes
    /// it paid for itself from about half of the cells deep, and not below a third
    /// (docs/performance.md, "Defaults chosen from the scene", has the CPU times).
    pub const AUTO_DEEP_SHARE: f64 = 0.5;

    /// The width in cells, with `auto` read as the band it would be
    /// ([`NarrowBand::AUTO_WIDTH`]); 0 for none.
    pub fn width(self) -> usize {
        match self {
            NarrowBand::Auto => Self::AUTO_WIDTH,
            NarrowBand::Cells(w) => w,
        }
    }
}

impl From<usize> for NarrowBand {
    fn from(w: usize) -> NarrowBand {
        NarrowBand::Cells(w)
    }
}

impl Serialize for NarrowBand {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            NarrowBand::Auto => s.serialize_str("auto"),
            NarrowBand::Cells(w) => s.serialize_u64(*w as u64),
        }
    }
}

impl<'de> Deserialize<'de> for NarrowBand {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<NarrowBand, D::Error> {
        struct Visitor;
        impl serde::de::Visitor<'_> for Visitor {
            type Value = NarrowBand;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("\"auto\" or a width in cells (0, or 2 to 32)")
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<NarrowBand, E> {
                match v {
                    "auto" => Ok(NarrowBand::Auto),
                    _ => Err(E::invalid_value(serde::de::Unexpected::Str(v), &self)),
                }
            }
            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<NarrowBand, E> {
                usize::try_from(v)
                    .map(NarrowBand::Cells)
                    .map_err(|_| E::invalid_value(serde::de::Unexpected::Unsigned(v), &self))
            }
            fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<NarrowBand, E> {
                u64::try_from(v)
                    .map_err(|_| E::invalid_value(serde::de::Unexpected::Signed(v), &self))
                    .and_then(|v| self.visit_u64(v))
            }
        }
        d.deserialize_any(Visitor)
    }
}

/// Everything a world is set up with besides its geometry.
#[derive(Clone, Debug, PartialEq)]
pub struct WorldSettings {
    /// The fixed step of [`crate::world::Simulation::step`], s. A fixed Δt keeps the step a
    /// differentiable map; [`crate::world::Simulation::advance`] takes shorter steps where
    /// the CFL condition asks for them.
    pub dt: f64,
    /// The liquid.
    pub fluid: Fluid,
    /// The solver.
    pub solver: SolverSettings,
    /// Rigid contact.
    pub contact: ContactSettings,
}

impl Default for WorldSettings {
    /// A 0.01 s step, water, the default solver, no contact.
    fn default() -> Self {
        WorldSettings {
            dt: 0.01,
            fluid: Fluid::default(),
            solver: SolverSettings::default(),
            contact: ContactSettings::default(),
        }
    }
}

impl WorldSettings {
    /// Every check, with the key a scene file gives the setting.
    pub fn validate(&self) -> Result<(), SettingError> {
        check_positive("time.dt", self.dt)?;
        self.fluid.validate()?;
        self.solver.validate()?;
        self.contact.validate().map_err(|(key, message)| SettingError { key, message })
    }
}

#[cfg(test)]
mod tests {
    use super::SolverSettings;

    /// The softness is 0 or in [0.01, 0.5] cells; anything else names the key.
    #[test]
    fn surface_softness_is_checked() {
        let with = |tau: f64| SolverSettings { surface_softness: tau, ..Default::default() };
        for tau in [0.0, 0.01, 0.35, 0.5] {
            assert!(with(tau).validate().is_ok(), "{tau}");
        }
        for tau in [1e-3, 0.009, 0.51, -0.1, f64::NAN, f64::INFINITY] {
            let err = with(tau).validate().unwrap_err();
            assert_eq!(err.key, "solver.surface_softness", "{tau}");
        }
    }

    /// Pockets left open (`None`, not the default) are written so that they read back open,
    /// and the default reads back as itself.
    #[test]
    fn open_pockets_round_trip() {
        for close_pockets in [None, Some(0.5), Some(0.25)] {
            let settings = SolverSettings { close_pockets, ..Default::default() };
            let text = toml::to_string(&settings).unwrap();
            let back: SolverSettings = toml::from_str(&text).unwrap();
            let effective = |s: &SolverSettings| s.close_pockets.filter(|k| *k > 0.0);
            assert_eq!(effective(&back), effective(&settings), "{text}");
        }
    }
}
