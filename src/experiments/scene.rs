//! Scene files: TOML read with serde (an unknown key is an error), validated into values a
//! simulation can trust, with errors that name the key and, where there is one, the line.

use crate::error::{Error, Result};
use crate::geometry::body::RigidBody;
use crate::geometry::grid::Grid;
use crate::geometry::shape::{AxisAngle, Placed, ShapeSpec, Solid};
use crate::math::{v3, Arr3};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The scene `cargo run --release` runs when no scene is given.
pub const DEFAULT_SCENE: &str = include_str!("../../assets/scenes/block_drop.toml");

/// Scenes shipped with diffluid, by name, so tests and the CLI can load them anywhere.
pub const BUILTIN_SCENES: &[(&str, &str)] = &[
    ("dam_break", include_str!("../../assets/scenes/dam_break.toml")),
    ("still_water", include_str!("../../assets/scenes/still_water.toml")),
    ("block_drop", include_str!("../../assets/scenes/block_drop.toml")),
    ("dam_break_ball", include_str!("../../assets/scenes/dam_break_ball.toml")),
    ("floating_box", include_str!("../../assets/scenes/floating_box.toml")),
    ("gradcheck_box", include_str!("../../assets/scenes/gradcheck_box.toml")),
    ("recover_box", include_str!("../../assets/scenes/recover_box.toml")),
];

/// A whole scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Short name, used for output folders.
    pub name: String,
    /// Free text.
    #[serde(default)]
    pub description: String,
    /// The tank.
    pub domain: Domain,
    /// Time stepping.
    pub time: Time,
    /// Liquid properties.
    pub fluid: Fluid,
    /// Regions that start full of liquid (their union).
    #[serde(default)]
    pub liquid: Vec<Placed>,
    /// Static solid obstacles.
    #[serde(default)]
    pub obstacle: Vec<Placed>,
    /// Solver settings.
    #[serde(default)]
    pub solver: Solver,
    /// Rigid bodies coupled to the liquid.
    #[serde(default)]
    pub body: Vec<BodySpec>,
    /// Rigid contact (body–wall, body–body), resolved after the fluid step.
    #[serde(default)]
    pub contact: Contact,
    /// What to optimise and how (for `diffluid optimize`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub optimize: Option<OptimizeSpec>,
    /// A loss on the final state (for gradients and optimisation).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss: Option<LossSpec>,
    /// What to write out.
    #[serde(default)]
    pub output: Output,
    /// Folder that relative mesh paths start from (the scene file's folder).
    #[serde(skip)]
    pub base_dir: Option<PathBuf>,
}

/// A rigid body as written in a scene file: a shape with a pose, a density or a mass, and
/// an initial velocity. `position` places the shape's local origin (the centre for
/// primitives).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BodySpec {
    /// Name used in outputs (default `body<i>`).
    #[serde(default)]
    pub name: String,
    /// The shape.
    pub shape: ShapeSpec,
    /// Position of the shape's local origin, m.
    #[serde(default)]
    pub position: Arr3,
    /// Orientation as a quaternion `[w, x, y, z]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub quaternion: Option<[f64; 4]>,
    /// Orientation as axis and angle.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis_angle: Option<AxisAngle>,
    /// Density, kg/m³ (give this or `mass`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub density: Option<f64>,
    /// Mass, kg (give this or `density`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mass: Option<f64>,
    /// Initial linear velocity of the centre of mass, m/s.
    #[serde(default)]
    pub velocity: Arr3,
    /// Initial angular velocity (world frame), rad/s.
    #[serde(default)]
    pub angular_velocity: Arr3,
    /// False for a body held still (it still couples, with zero velocity). Default true.
    #[serde(default = "yes")]
    pub dynamic: bool,
}

fn yes() -> bool {
    true
}

impl BodySpec {
    /// The shape and pose part.
    pub fn placed(&self) -> Placed {
        Placed {
            shape: self.shape.clone(),
            position: self.position,
            quaternion: self.quaternion,
            axis_angle: self.axis_angle.clone(),
        }
    }
}

/// A weighted target for a 3-vector.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Target3 {
    /// Target value.
    pub target: Arr3,
    /// Weight (≥ 0).
    #[serde(default = "one_f")]
    pub weight: f64,
}

/// A weighted target orientation, as a quaternion `[w, x, y, z]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TargetQ {
    /// Target quaternion `[w, x, y, z]` (normalised on use).
    pub target: [f64; 4],
    /// Weight (≥ 0).
    #[serde(default = "one_f")]
    pub weight: f64,
}

fn one_f() -> f64 {
    1.0
}

/// The loss on the final state: weighted squared distances of one body's position,
/// orientation (1 − (q·q*)²) and velocity to targets.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LossSpec {
    /// The body's name.
    pub body: String,
    /// Final position target.
    #[serde(default)]
    pub position: Option<Target3>,
    /// Final orientation target.
    #[serde(default)]
    pub orientation: Option<TargetQ>,
    /// Final velocity target.
    #[serde(default)]
    pub velocity: Option<Target3>,
}

/// The optimiser.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum OptimizerSpec {
    /// Plain gradient descent, p ← p − lr·g (the paper's).
    Gd {
        /// Learning rate.
        learning_rate: f64,
    },
    /// Adam (Kingma & Ba 2015).
    Adam {
        /// Learning rate.
        learning_rate: f64,
        /// First-moment decay. Default 0.9.
        #[serde(default = "beta1")]
        beta1: f64,
        /// Second-moment decay. Default 0.999.
        #[serde(default = "beta2")]
        beta2: f64,
    },
    /// L-BFGS (Liu & Nocedal 1989) from argmin, with argmin's Moré–Thuente line search
    /// (strong Wolfe conditions, c1 = 1e-4, c2 = 0.9, the classic companion of L-BFGS):
    /// one epoch is one iteration, which may evaluate the loss and gradient several times. It
    /// has no learning rate: the first step is the steepest-descent direction scaled by the
    /// line search. (argmin's Hager–Zhang search is not offered: it evaluates both ends of
    /// its initial bracket [ε, 1e5] before anything else, and a step of 1e5 gradients throws
    /// a body out of the tank.)
    Lbfgs {
        /// Correction pairs kept. Default 5: the problems here have at most 12 parameters,
        /// and 3 to 7 pairs is the usual range (Nocedal & Wright, section 7.2).
        #[serde(default = "memory")]
        memory: usize,
        /// The run ends (converged) once the gradient norm falls below this. Default √ε ≈
        /// 1.5e-8, argmin's: a gradient that small is round-off of the adjoint.
        #[serde(default = "tolerance_grad")]
        tolerance_grad: f64,
        /// The run ends (converged) once an iteration changes the loss by less than this.
        /// Default ε ≈ 2.2e-16, argmin's: a change at f64 round-off.
        #[serde(default = "tolerance_cost")]
        tolerance_cost: f64,
    },
}

fn memory() -> usize {
    5
}
fn tolerance_grad() -> f64 {
    f64::EPSILON.sqrt()
}
fn tolerance_cost() -> f64 {
    f64::EPSILON
}

fn beta1() -> f64 {
    0.9
}
fn beta2() -> f64 {
    0.999
}

/// What `diffluid optimize` does.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OptimizeSpec {
    /// Initial parameters of the loss body to optimise: any of "v", "w", "x", "q".
    pub params: Vec<String>,
    /// The optimiser.
    pub optimizer: OptimizerSpec,
    /// Epochs (forward + backward + update each).
    pub epochs: usize,
    /// A gradient whose norm exceeds this stops the run (exploding). Default 1e6.
    #[serde(default = "max_grad")]
    pub max_gradient_norm: f64,
    /// Recovery: the loss's position and velocity targets are the final state of a forward
    /// run from this initial velocity of the loss body.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recover_velocity: Option<Arr3>,
    /// Optimise a scene with rapier contact on, the backward pass taking the contact step as
    /// free flight: an approximation (the gradient ignores contact impulses), named here so
    /// it is never silent. Default false: contact and optimisation are then an error.
    #[serde(default)]
    pub through_contact: bool,
    /// Hold the liquid surface fixed during the optimisation's epochs (as the paper did for
    /// its timings: no marker particles in the loop). The gradient is then exact, and an epoch
    /// costs no particle work. `run` keeps the scene's own setting. Default false.
    #[serde(default)]
    pub freeze_surface: bool,
}

fn max_grad() -> f64 {
    1e6
}

/// Rigid contact settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Contact {
    /// Resolve body–wall and body–body contact with rapier after each fluid step. Default
    /// false: then a body that would leave the tank is an error.
    pub enabled: bool,
    /// Coulomb friction coefficient. Default 0.5.
    pub friction: f64,
    /// Restitution. Default 0 (bodies in water do not bounce much).
    pub restitution: f64,
}

impl Default for Contact {
    fn default() -> Self {
        Contact { enabled: false, friction: 0.5, restitution: 0.0 }
    }
}

/// The tank: a box `[0, size]` with solid walls, cut into cubes of side `dx`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Domain {
    /// Extent in metres along x, y (up), z. Each must be a whole number of cells.
    pub size: Arr3,
    /// Cell side in metres.
    pub dx: f64,
}

/// Fixed time stepping (a fixed Δt keeps the step a differentiable map).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Time {
    /// Step in seconds.
    pub dt: f64,
    /// Number of steps a run takes.
    pub steps: usize,
}

/// Liquid properties.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Fluid {
    /// Density in kg/m³.
    pub density: f64,
    /// Gravity in m/s².
    pub gravity: Arr3,
}

/// Preconditioner for the pressure CG.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Preconditioner {
    /// Modified incomplete Cholesky, level 0 (Bridson's τ = 0.97, σ = 0.25).
    Mic0,
    /// One multigrid V-cycle (MGPCG, see `multigrid.rs`).
    Multigrid,
    /// Plain conjugate gradients (for comparison).
    None,
    /// MIC(0) for systems of fewer than [`Preconditioner::AUTO_CROSSOVER`] unknowns,
    /// multigrid from there on.
    Auto,
}

impl Preconditioner {
    /// Unknowns from which `auto` picks multigrid over MIC(0). Measured on the pressure
    /// solve of `benches/solve.rs` (tank, wavy free surface, floating ball) to 1e-8 on a
    /// 2-core machine, median of repeated solves with the preconditioner's set-up included:
    /// 312 unknowns (8³) MIC(0) 0.11 ms (20 iterations) vs multigrid 0.15 ms (8); 1034
    /// (12³) a tie, 0.33 vs 0.35 ms; 2452 (16³) 0.87 vs 0.76 ms; 19.5k (32³) 11 vs 7 ms;
    /// 1.24M (128³, to 1e-6) 94 vs 8 iterations and about 6× the time. MIC(0)'s iterations
    /// grow with the grid, multigrid's hardly do, so the crossover sits between 12³ and 16³
    /// for a cold solve. Inside a time step the solve starts from the last step's pressure
    /// and MIC(0) needs fewer iterations: on block_drop (3,519 unknowns) a whole epoch took
    /// 0.317–0.325 s with MIC(0) and 0.327–0.331 s with multigrid (2 threads), so the
    /// switch sits above that, at 4,000.
    pub const AUTO_CROSSOVER: usize = 4_000;

    /// The preconditioner to use for `unknowns` unknowns: itself, unless `Auto`.
    pub fn resolve(self, unknowns: usize) -> Preconditioner {
        match self {
            Preconditioner::Auto if unknowns < Self::AUTO_CROSSOVER => Preconditioner::Mic0,
            Preconditioner::Auto => Preconditioner::Multigrid,
            other => other,
        }
    }
}

/// How the liquid and the bodies exchange momentum in a step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Coupling {
    /// One pressure solve for liquid and bodies together (Batty et al. 2007): the body's
    /// response to the pressure is part of the system, so it is stable for any density ratio.
    #[default]
    Monolithic,
    /// The partitioned baseline: the liquid is solved around each body moving at its current
    /// velocity (held fixed), then the body is pushed by the resulting pressure force. Light
    /// bodies go unstable (the added-mass instability); kept to show where, not for use.
    Weak,
}

/// Solver settings. Every field has a default, given with its reason.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Solver {
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
    /// Smallest ghost-fluid fraction θ at a liquid–air face. Default 0.01 (Gibou et al.;
    /// bounds the diagonal at 100× a full face).
    pub theta_min: f64,
    /// Push marker particles out of over-full cells after advecting them (particle density
    /// projection, see `density.rs`). Default true: without it the dam break loses about
    /// 10% of its volume to particles bunching at the floor.
    pub density_correction: bool,
    /// Hold the free surface fixed: the marker particles do not move and the liquid signed
    /// distance keeps its initial value (extended into the solids where they are now). The
    /// backward pass always holds the surface fixed (as the paper does); with this switch the
    /// forward pass is exactly the map the adjoint differentiates, which gradient checks need.
    /// It also skips all particle work. Default false.
    pub freeze_surface: bool,
    /// Liquid–body coupling. Default `monolithic`; `weak` is the partitioned baseline the
    /// stability map compares against (no gradients through it).
    pub coupling: Coupling,
}

impl Default for Solver {
    fn default() -> Self {
        Solver {
            tolerance: 1e-8,
            max_iterations: 2000,
            preconditioner: Preconditioner::Auto,
            extrapolation_layers: 3,
            particles_per_cell: 8,
            theta_min: 0.01,
            density_correction: true,
            freeze_surface: false,
            coupling: Coupling::Monolithic,
        }
    }
}

/// What a run writes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Output {
    /// Write liquid particles as binary PLY per frame. Default true.
    pub particles: bool,
    /// Write a frame every this many steps. Default 1.
    pub every: usize,
}

impl Default for Output {
    fn default() -> Self {
        Output { particles: true, every: 1 }
    }
}

/// The 1-based line of `path` (`"domain.dx"`, `"liquid[1]"`, `"solver"`) in a TOML text, when
/// the file is laid out with one table header per section, as the shipped scenes are.
fn locate(src: &str, path: &str) -> Option<usize> {
    let mut parts = path.split('.');
    let head = parts.next()?;
    let key = parts.next();
    let (table, nth) = match head.split_once('[') {
        Some((t, rest)) => (t, rest.trim_end_matches(']').parse::<usize>().ok()?),
        None => (head, 0),
    };
    let headers = [format!("[{table}]"), format!("[[{table}]]")];
    let mut seen = 0usize;
    let mut start = None;
    for (n, line) in src.lines().enumerate() {
        let t = line.trim();
        if headers.iter().any(|h| t == h) {
            if seen == nth {
                start = Some(n);
                break;
            }
            seen += 1;
        }
    }
    let start = match start {
        Some(s) => s,
        // A top-level key, or a dotted key without its own header.
        None => {
            return src
                .lines()
                .position(|l| {
                    let t = l.trim_start();
                    t.starts_with(head) && t[head.len()..].trim_start().starts_with('=')
                })
                .map(|n| n + 1)
        }
    };
    let Some(key) = key else {
        return Some(start + 1);
    };
    for (n, line) in src.lines().enumerate().skip(start + 1) {
        let t = line.trim_start();
        if t.starts_with('[') {
            break;
        }
        if t.starts_with(key) && t[key.len()..].trim_start().starts_with('=') {
            return Some(n + 1);
        }
    }
    Some(start + 1)
}

/// Bounds for messages, without floating-point noise (3.5999999999999996 → 3.6).
fn round6(a: [f64; 3]) -> [f64; 3] {
    a.map(|x| (x * 1e6).round() / 1e6)
}

/// A validation failure: the key it concerns and what is wrong.
struct Problem {
    key: String,
    message: String,
}

fn problem(key: impl Into<String>, message: impl Into<String>) -> Problem {
    Problem { key: key.into(), message: message.into() }
}

fn check_positive(key: &str, x: f64) -> std::result::Result<(), Problem> {
    if x.is_finite() && x > 0.0 {
        Ok(())
    } else {
        Err(problem(key, format!("must be a positive number, got {x}")))
    }
}

fn check_finite(key: &str, xs: &[f64]) -> std::result::Result<(), Problem> {
    if xs.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(problem(key, format!("must be finite, got {xs:?}")))
    }
}

impl Scene {
    /// Reads and validates a scene file.
    pub fn from_file(path: &Path) -> Result<Scene> {
        let text = std::fs::read_to_string(path)
            .map_err(|source| Error::ReadScene { path: path.to_path_buf(), source })?;
        let base = path.parent().map(Path::to_path_buf).unwrap_or_default();
        Scene::from_toml_in(&text, &path.display().to_string(), base)
    }

    /// Parses and validates TOML text whose relative mesh paths start from `base`.
    pub fn from_toml_in(text: &str, origin: &str, base: PathBuf) -> Result<Scene> {
        let mut scene = Scene::parse(text, origin)?;
        scene.base_dir = Some(base);
        scene.validated(text, origin)
    }

    /// Parses and validates a scene from TOML text; `origin` names it in errors. Relative
    /// mesh paths start from `assets/scenes/`.
    pub fn from_toml(text: &str, origin: &str) -> Result<Scene> {
        Scene::from_toml_in(
            text,
            origin,
            Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/scenes"),
        )
    }

    fn parse(text: &str, origin: &str) -> Result<Scene> {
        toml::from_str(text).map_err(|e| {
            let line = e.span().map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1);
            let msg = e.message().trim().replace('\n', " ");
            Error::ParseScene {
                origin: origin.to_string(),
                message: match line {
                    Some(l) => {
                        // Name the table when the error points at its header ("missing field").
                        let header = text.lines().nth(l - 1).map(str::trim).unwrap_or("");
                        if header.starts_with('[') && header.ends_with(']') {
                            format!("line {l}: in {header}: {msg}")
                        } else {
                            format!("line {l}: {msg}")
                        }
                    }
                    None => msg,
                },
            }
        })
    }

    fn validated(self, text: &str, origin: &str) -> Result<Scene> {
        self.validate().map_err(|p| {
            let at = locate(text, &p.key).map(|l| format!("line {l}: ")).unwrap_or_default();
            Error::InvalidScene {
                origin: origin.to_string(),
                message: format!("{at}{}: {}", p.key, p.message),
            }
        })?;
        Ok(self)
    }

    /// A scene shipped with diffluid, by name (`dam_break`, `still_water`, ...).
    pub fn builtin(name: &str) -> Result<Scene> {
        let text =
            BUILTIN_SCENES.iter().find(|(n, _)| *n == name).map(|(_, t)| *t).ok_or_else(|| {
                Error::InvalidScene {
                    origin: "<builtin>".into(),
                    message: format!("no built-in scene named {name:?}"),
                }
            })?;
        Scene::from_toml(text, &format!("<builtin {name}>"))
    }

    /// The embedded default scene.
    pub fn embedded_default() -> Scene {
        Scene::from_toml(DEFAULT_SCENE, "<embedded>").expect("the embedded scene is valid")
    }

    /// Re-checks a scene built or edited in code.
    pub fn check(&self) -> Result<()> {
        self.validate().map_err(|p| Error::InvalidScene {
            origin: self.name.clone(),
            message: format!("{}: {}", p.key, p.message),
        })
    }

    /// The grid the domain is cut into.
    pub fn grid(&self) -> Grid {
        let n = self.domain.size.map(|s| (s / self.domain.dx).round() as usize);
        Grid { n, dx: self.domain.dx }
    }

    /// Folder relative mesh paths start from.
    pub fn base(&self) -> PathBuf {
        self.base_dir.clone().unwrap_or_else(|| PathBuf::from("."))
    }

    /// Built static obstacles.
    pub fn obstacles(&self) -> Vec<Solid> {
        let base = self.base();
        self.obstacle.iter().map(|p| p.build(&base).expect("validated")).collect()
    }

    /// Built liquid regions.
    pub fn liquid_regions(&self) -> Vec<Solid> {
        let base = self.base();
        self.liquid.iter().map(|p| p.build(&base).expect("validated")).collect()
    }

    /// Built rigid bodies in their initial state.
    pub fn bodies(&self) -> Result<Vec<RigidBody>> {
        self.body
            .iter()
            .enumerate()
            .map(|(i, b)| {
                self.build_body(i, b).map_err(|p| Error::InvalidScene {
                    origin: self.name.clone(),
                    message: format!("{}: {}", p.key, p.message),
                })
            })
            .collect()
    }

    fn build_body(&self, i: usize, b: &BodySpec) -> std::result::Result<RigidBody, Problem> {
        let key = format!("body[{i}]");
        let solid = b.placed().build(&self.base()).map_err(|m| problem(&key, m))?;
        let (density, mass) = match (b.density, b.mass) {
            (Some(d), None) => {
                check_positive(&format!("{key}.density"), d)?;
                (d, None)
            }
            (None, Some(m)) => {
                check_positive(&format!("{key}.mass"), m)?;
                (1.0, Some(m))
            }
            _ => return Err(problem(&key, "give exactly one of density and mass")),
        };
        check_finite(&format!("{key}.velocity"), &b.velocity)?;
        check_finite(&format!("{key}.angular_velocity"), &b.angular_velocity)?;
        let name = if b.name.is_empty() { format!("body{i}") } else { b.name.clone() };
        let mut body = RigidBody::new(name, solid.shape, solid.pose, density);
        if !(body.mass.is_finite() && body.mass > 0.0) {
            return Err(problem(&key, "the shape has no volume (degenerate shape)"));
        }
        if let Some(m) = mass {
            body.set_mass(m);
        }
        body.v = v3(b.velocity);
        body.w = v3(b.angular_velocity);
        body.dynamic = b.dynamic;
        let (lo, hi) = body.bounds();
        let size = v3(self.domain.size);
        if lo.min_element() <= 0.0 || (hi - size).max_element() >= 0.0 {
            return Err(problem(
                &key,
                format!(
                    "body spans {:?}..{:?}: it must start inside the tank [0, 0, 0]..{:?} \
                     without touching a wall",
                    round6(lo.to_array()),
                    round6(hi.to_array()),
                    self.domain.size
                ),
            ));
        }
        Ok(body)
    }

    fn validate(&self) -> std::result::Result<(), Problem> {
        let d = &self.domain;
        check_positive("domain.dx", d.dx)?;
        for (a, s) in d.size.iter().enumerate() {
            check_positive(&format!("domain.size[{a}]"), *s)?;
            let n = (s / d.dx).round();
            if n < 1.0 || (n * d.dx - s).abs() > 1e-6 * s {
                return Err(problem(
                    "domain.size",
                    format!(
                        "size {s} along axis {a} is not a whole number of cells of dx = {}",
                        d.dx
                    ),
                ));
            }
        }
        let cells: f64 = d.size.iter().map(|s| (s / d.dx).round()).product();
        if cells > 512.0f64.powi(3) {
            return Err(problem("domain", format!("{cells} cells is more than 512³; raise dx")));
        }
        check_positive("time.dt", self.time.dt)?;
        if self.time.steps == 0 {
            return Err(problem("time.steps", "must be at least 1"));
        }
        check_positive("fluid.density", self.fluid.density)?;
        check_finite("fluid.gravity", &self.fluid.gravity)?;
        let size = v3(d.size);
        let tol = 1e-9 * size.max_element();
        for (i, l) in self.liquid.iter().enumerate() {
            let key = format!("liquid[{i}]");
            let s = l.build(&self.base()).map_err(|m| problem(&key, m))?;
            let (lo, hi) = s.bounds();
            if lo.min_element() < -tol || (hi - size).max_element() > tol {
                return Err(problem(
                    &key,
                    format!(
                        "liquid region spans {:?}..{:?}, outside the domain [0, 0, 0]..{:?}",
                        round6(lo.to_array()),
                        round6(hi.to_array()),
                        d.size
                    ),
                ));
            }
        }
        for (i, o) in self.obstacle.iter().enumerate() {
            o.build(&self.base()).map_err(|m| problem(format!("obstacle[{i}]"), m))?;
        }
        let s = &self.solver;
        if !(s.tolerance.is_finite() && s.tolerance > 0.0 && s.tolerance < 1.0) {
            return Err(problem(
                "solver.tolerance",
                format!("must be in (0, 1), got {}", s.tolerance),
            ));
        }
        if s.max_iterations == 0 {
            return Err(problem("solver.max_iterations", "must be at least 1"));
        }
        let m = (s.particles_per_cell as f64).cbrt().round() as usize;
        if !(1..=4).contains(&m) || m * m * m != s.particles_per_cell {
            return Err(problem(
                "solver.particles_per_cell",
                format!(
                    "must be 1, 8, 27 or 64 (a regular sub-lattice), got {}",
                    s.particles_per_cell
                ),
            ));
        }
        if !(s.theta_min.is_finite() && s.theta_min > 0.0 && s.theta_min <= 0.5) {
            return Err(problem(
                "solver.theta_min",
                format!("must be in (0, 0.5], got {}", s.theta_min),
            ));
        }
        for (i, b) in self.body.iter().enumerate() {
            self.build_body(i, b)?;
        }
        if let Some(l) = &self.loss {
            let names: Vec<String> = (0..self.body.len())
                .map(|i| {
                    if self.body[i].name.is_empty() {
                        format!("body{i}")
                    } else {
                        self.body[i].name.clone()
                    }
                })
                .collect();
            if !names.contains(&l.body) {
                return Err(problem(
                    "loss.body",
                    format!("no body named {:?} (bodies: {names:?})", l.body),
                ));
            }
            let size = v3(self.domain.size);
            if let Some(t) = &l.position {
                check_finite("loss.position.target", &t.target)?;
                let x = v3(t.target);
                if x.min_element() < 0.0 || (x - size).max_element() > 0.0 {
                    return Err(problem(
                        "loss.position.target",
                        format!(
                            "target {:?} is outside the tank [0, 0, 0]..{:?}",
                            t.target, self.domain.size
                        ),
                    ));
                }
            }
            if let Some(t) = &l.velocity {
                check_finite("loss.velocity.target", &t.target)?;
            }
            if let Some(t) = &l.orientation {
                let n = t.target.iter().map(|x| x * x).sum::<f64>().sqrt();
                if !(n.is_finite() && n > 1e-12) {
                    return Err(problem(
                        "loss.orientation.target",
                        "must be a finite non-zero quaternion",
                    ));
                }
            }
            for (key, w) in [
                ("loss.position.weight", l.position.as_ref().map(|t| t.weight)),
                ("loss.orientation.weight", l.orientation.as_ref().map(|t| t.weight)),
                ("loss.velocity.weight", l.velocity.as_ref().map(|t| t.weight)),
            ] {
                if let Some(w) = w {
                    if !(w.is_finite() && w >= 0.0) {
                        return Err(problem(
                            key,
                            format!("must be a non-negative number, got {w}"),
                        ));
                    }
                }
            }
            if l.position.is_none() && l.orientation.is_none() && l.velocity.is_none() {
                return Err(problem(
                    "loss",
                    "give at least one of position, orientation, velocity",
                ));
            }
        }
        if let Some(o) = &self.optimize {
            if self.loss.is_none() {
                return Err(problem("optimize", "needs a [loss] section"));
            }
            if o.params.is_empty() {
                return Err(problem(
                    "optimize.params",
                    "name at least one of \"v\", \"w\", \"x\", \"q\"",
                ));
            }
            for p in &o.params {
                if !["v", "w", "x", "q"].contains(&p.as_str()) {
                    return Err(problem(
                        "optimize.params",
                        format!("unknown parameter {p:?}: use \"v\", \"w\", \"x\" or \"q\""),
                    ));
                }
            }
            let lr = match &o.optimizer {
                OptimizerSpec::Gd { learning_rate } => *learning_rate,
                OptimizerSpec::Adam { learning_rate, beta1, beta2 } => {
                    for (k, b) in [("beta1", beta1), ("beta2", beta2)] {
                        if !(b.is_finite() && *b >= 0.0 && *b < 1.0) {
                            return Err(problem(
                                format!("optimize.optimizer.{k}"),
                                format!("must be in [0, 1), got {b}"),
                            ));
                        }
                    }
                    *learning_rate
                }
                OptimizerSpec::Lbfgs { memory, tolerance_grad, tolerance_cost, .. } => {
                    if *memory == 0 {
                        return Err(problem("optimize.optimizer.memory", "must be at least 1"));
                    }
                    for (k, t) in
                        [("tolerance_grad", tolerance_grad), ("tolerance_cost", tolerance_cost)]
                    {
                        if !(t.is_finite() && *t >= 0.0) {
                            return Err(problem(
                                format!("optimize.optimizer.{k}"),
                                format!("must be a non-negative number, got {t}"),
                            ));
                        }
                    }
                    1.0
                }
            };
            if !(lr.is_finite() && lr > 0.0) {
                return Err(problem(
                    "optimize.optimizer.learning_rate",
                    format!("must be a positive number, got {lr}"),
                ));
            }
            if o.epochs == 0 {
                return Err(problem("optimize.epochs", "must be at least 1"));
            }
            if !(o.max_gradient_norm.is_finite() && o.max_gradient_norm > 0.0) {
                return Err(problem("optimize.max_gradient_norm", "must be a positive number"));
            }
            if let Some(v) = &o.recover_velocity {
                check_finite("optimize.recover_velocity", v)?;
            }
            if self.contact.enabled && !o.through_contact {
                return Err(problem(
                    "optimize",
                    "gradients do not pass through contact: set [contact] enabled = false, or \
                     optimize.through_contact = true to take contact as free flight in the gradient",
                ));
            }
        }
        let c = &self.contact;
        if !(c.friction.is_finite() && c.friction >= 0.0) {
            return Err(problem(
                "contact.friction",
                format!("must be a non-negative number, got {}", c.friction),
            ));
        }
        if !(c.restitution.is_finite() && (0.0..=1.0).contains(&c.restitution)) {
            return Err(problem(
                "contact.restitution",
                format!("must be in [0, 1], got {}", c.restitution),
            ));
        }
        if self.output.every == 0 {
            return Err(problem("output.every", "must be at least 1"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_scenes_parse() {
        for (name, _) in BUILTIN_SCENES {
            Scene::builtin(name).unwrap();
        }
    }

    #[test]
    fn locate_finds_keys_in_tables() {
        let src = "name = \"x\"\n[domain]\nsize = [1, 1, 1]\ndx = 0.1\n[[liquid]]\na = 1\n[[liquid]]\nb = 2\n";
        assert_eq!(locate(src, "domain.dx"), Some(4));
        assert_eq!(locate(src, "liquid[1]"), Some(7));
        assert_eq!(locate(src, "name"), Some(1));
    }
}
