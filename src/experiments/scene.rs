//! Scene files: TOML read with serde (an unknown key is an error), validated into values a
//! simulation can trust, with errors that name the key and, where there is one, the line.

use super::shapes::{AxisAngle, Placed, ShapeSpec};
use crate::error::{Error, Result};
use crate::geometry::body::{Motion, Param, RigidBody};
use crate::gradients::{
    BodyTargetLoss, FinalTarget, LiquidInBox, Schedule, TrajectoryTerms, Waypoint,
};
pub use crate::io::output::MeshFormat;
use crate::math::{v3, Arr3, Rotation};
use crate::world::settings::{check_finite, check_positive, SettingError};
use crate::world::{
    ContactSettings, Fluid, Simulation, SimulationBuilder, SolverSettings, WorldSettings,
};
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
    ("gradcheck_live", include_str!("../../assets/scenes/gradcheck_live.toml")),
    ("surge_ball", include_str!("../../assets/scenes/surge_ball.toml")),
    ("surge_target", include_str!("../../assets/scenes/surge_target.toml")),
    ("paddle_push", include_str!("../../assets/scenes/paddle_push.toml")),
    ("gradcheck_control", include_str!("../../assets/scenes/gradcheck_control.toml")),
    ("large_tank", include_str!("../../assets/scenes/large_tank.toml")),
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
    pub solver: SolverSettings,
    /// Rigid bodies coupled to the liquid.
    #[serde(default)]
    pub body: Vec<BodySpec>,
    /// Rigid contact (body–wall, body–body), held inside the projection.
    #[serde(default)]
    pub contact: ContactSettings,
    /// What to optimise and how (for `diffluid optimize`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub optimize: Option<OptimizeSpec>,
    /// A loss on the final state or the whole trajectory (for gradients and optimisation).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss: Option<LossSpec>,
    /// Actions at every step on some bodies, and how `diffluid control` optimises them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub control: Option<ControlSpec>,
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
    /// Name used in outputs and by `[loss]` and `[control]` (default `body<i>`): a name
    /// files can take, as the scene's, and no other body's.
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
    /// False for a body the liquid does not move: held still (it still couples, with zero
    /// velocity), or, with a `velocity` or `angular_velocity`, moved along it at that
    /// constant velocity (a paddle or wave maker, a moving boundary of the solve). Default
    /// true.
    #[serde(default = "yes")]
    pub dynamic: bool,
    /// For a `mesh` body, m: an open mesh (a sail, a hull without a deck) loads as a shell
    /// this thick, its mass that of thickness × area at the body's density; a closed mesh
    /// keeps the usual rules. Without it an open mesh is an error.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shell_thickness: Option<f64>,
}

fn yes() -> bool {
    true
}

impl BodySpec {
    /// The body's name: its `name`, or `body<i>` for the i-th body when it has none.
    pub fn name_or_default(&self, i: usize) -> String {
        if self.name.is_empty() {
            format!("body{i}")
        } else {
            self.name.clone()
        }
    }

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
    /// Positions the body passes after given steps (with `[control]`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub waypoint: Vec<WaypointSpec>,
    /// weight·Σ|a|² over every action of `[control]`. Default 0.
    #[serde(default)]
    pub effort: f64,
    /// weight·Δt·Σ|v|² of the body after every step (a running cost). Default 0.
    #[serde(default)]
    pub speed: f64,
    /// The liquid's volume inside a box at the end, against a target (with `[control]`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub liquid_in_box: Option<BoxTarget>,
}

/// A position the loss body passes after `step` steps: weight·|x − position|².
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WaypointSpec {
    /// Steps taken (1 ..= time.steps).
    pub step: usize,
    /// Where the body should be, m.
    pub position: Arr3,
    /// Weight (≥ 0). Default 1.
    #[serde(default = "one_f")]
    pub weight: f64,
}

/// The liquid's volume inside an axis-aligned box at the end: weight·(V − target)².
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoxTarget {
    /// Lower corner, m.
    pub min: Arr3,
    /// Upper corner, m.
    pub max: Arr3,
    /// The volume wanted inside, m³ (0: keep the liquid out).
    pub target: f64,
    /// Weight (≥ 0), per m⁶. Default 1.
    #[serde(default = "one_f")]
    pub weight: f64,
}

/// Actions at every step (`diffluid control`): a dynamic body takes an external force and
/// torque `[fx, fy, fz, τx, τy, τz]` (world frame, N and N·m), a body with `dynamic = false`
/// a velocity and angular velocity `[vx, vy, vz, ωx, ωy, ωz]` (it moves along them, from
/// rest if it has no `velocity`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControlSpec {
    /// The steered bodies, by name.
    pub bodies: Vec<String>,
    /// Steps each action is held; time.steps must be a multiple of it. Default 1.
    #[serde(default = "one_usize")]
    pub steps_per_action: usize,
    /// Every action's starting value, one per body (default zeros).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub initial: Vec<[f64; 6]>,
    /// The largest magnitude of an action's entry: the optimiser clips to it. Optional.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bound: Option<f64>,
    /// The entries the optimiser changes, by name: `vx vy vz wx wy wz` for a body with
    /// `dynamic = false`, `fx fy fz tx ty tz` for a dynamic one (the others keep their
    /// `initial` values). Default: all six.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub free: Vec<String>,
    /// The optimiser (`gd` or `adam`).
    pub optimizer: OptimizerSpec,
    /// Epochs (forward + backward + update each).
    pub epochs: usize,
}

fn one_usize() -> usize {
    1
}

/// The index in an action of an entry named in `control.free`.
pub fn action_entry(name: &str) -> Option<usize> {
    ["vx", "vy", "vz", "wx", "wy", "wz"]
        .iter()
        .position(|n| *n == name)
        .or_else(|| ["fx", "fy", "fz", "tx", "ty", "tz"].iter().position(|n| *n == name))
}

/// The name body `i` goes by.
fn key_name(i: usize, b: &BodySpec) -> String {
    b.name_or_default(i)
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
    pub params: Vec<Param>,
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
    /// The backward pass's surface: `"live"` (default: the surface's motion differentiated,
    /// the exact gradient of the map) or `"frozen"` (the paper's approximation: the surface
    /// taken as fixed in the backward pass while the forward pass moves it).
    #[serde(default)]
    pub surface_gradient: SurfaceGradientSpec,
    /// Hold the liquid surface fixed during the optimisation's epochs (as the paper did for
    /// its timings: no marker particles in the loop). The gradient is then exact, and an epoch
    /// costs no particle work. `run` keeps the scene's own setting. Default false.
    #[serde(default)]
    pub freeze_surface: bool,
    /// Optimise the loss smoothed over a Gaussian perturbation of the initial state (see
    /// [`crate::gradients::smooth`]): `{ samples = K, sigma = { v, w, x, q }, seed }`, K runs
    /// an epoch. For horizons where the map jumps. Default: the plain gradient.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub smoothing: Option<crate::gradients::Smoothing>,
}

/// The backward pass's surface, as a scene names it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SurfaceGradientSpec {
    /// Differentiate the surface's motion.
    #[default]
    Live,
    /// Hold it fixed in the backward pass.
    Frozen,
}

fn max_grad() -> f64 {
    1e6
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

/// What a run writes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Output {
    /// Write liquid particles as binary PLY per frame. Default true.
    pub particles: bool,
    /// Write a frame every this many steps. Default 1.
    pub every: usize,
    /// Write the liquid's surface as a closed triangle mesh per frame (under `surface/`, and
    /// in the ParaView frames with `--vtk`). Needs the `surface` feature. Default false.
    pub surface: bool,
    /// The surface's resolution: distance samples per cell along each axis, 1 to 8. Default
    /// 2 (what each costs: docs/performance.md, "Surface meshes").
    pub surface_samples: usize,
    /// The surface's file format. Default "ply" (binary, for Blender, ParaView, MeshLab).
    pub surface_format: MeshFormat,
}

impl Default for Output {
    fn default() -> Self {
        Output {
            particles: true,
            every: 1,
            surface: false,
            surface_samples: 2,
            surface_format: MeshFormat::Ply,
        }
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

/// `table.key` of a `key = value` line `l` (1-based) under a `[table]` or `[[table]]`
/// header (`key` alone at the top level).
fn dotted_key(src: &str, l: usize) -> Option<String> {
    let lines: Vec<&str> = src.lines().collect();
    let line = lines.get(l - 1)?;
    if line.trim_start().starts_with('#') {
        return None;
    }
    let key = line.split_once('=')?.0.trim();
    if key.is_empty() || key.contains(['[', '{', '"']) {
        return None;
    }
    let table = lines[..l - 1]
        .iter()
        .rev()
        .map(|s| s.trim())
        .find(|s| s.starts_with('[') && s.ends_with(']'))
        .map(|h| h.trim_matches(|c| c == '[' || c == ']'));
    Some(match table {
        Some(t) => format!("{t}.{key}"),
        None => key.to_string(),
    })
}

/// A validation failure: the key it concerns and what is wrong.
type Problem = SettingError;

fn problem(key: impl Into<String>, message: impl Into<String>) -> Problem {
    SettingError::new(key, message)
}

impl Scene {
    /// Reads and validates a scene file.
    pub fn from_file(path: &Path) -> Result<Scene> {
        let text = crate::math::input::read_text(path)
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
    /// mesh paths start from the current folder (use [`Scene::from_toml_in`] to give another).
    pub fn from_toml(text: &str, origin: &str) -> Result<Scene> {
        Scene::from_toml_in(text, origin, PathBuf::from("."))
    }

    fn parse(text: &str, origin: &str) -> Result<Scene> {
        toml::from_str(text).map_err(|e| {
            let msg = e.message().trim().replace('\n', " ");
            // A field the whole file lacks (span 0..0): no line to point at (it said
            // `line 1: name: missing field `fluid``, naming whatever came first).
            if e.span() == Some(0..0) {
                if let Some(field) =
                    msg.strip_prefix("missing field `").and_then(|m| m.strip_suffix('`'))
                {
                    let what = if ["domain", "time", "fluid"].contains(&field) {
                        format!("the [{field}] table is missing")
                    } else {
                        format!("the key `{field}` is missing (at the top, before any table)")
                    };
                    return Error::ParseScene { origin: origin.to_string(), message: what };
                }
            }
            let line = e.span().map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1);
            Error::ParseScene {
                origin: origin.to_string(),
                message: match line {
                    Some(l) => {
                        // Name the table when the error points at its header ("missing field").
                        let header = text.lines().nth(l - 1).map(str::trim).unwrap_or("");
                        if header.starts_with('[') && header.ends_with(']') {
                            format!("line {l}: in {header}: {msg}")
                        } else if let Some(key) = dotted_key(text, l) {
                            format!("line {l}: {key}: {msg}")
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
        // The built-in scenes ship with the crate: their relative mesh paths start from its
        // `assets/scenes/`.
        let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/scenes");
        Scene::from_toml_in(text, &format!("<builtin {name}>"), base)
    }

    /// The embedded default scene.
    pub fn embedded_default() -> Scene {
        let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("assets/scenes");
        Scene::from_toml_in(DEFAULT_SCENE, "<embedded>", base).expect("the embedded scene is valid")
    }

    /// Re-checks a scene built or edited in code.
    pub fn check(&self) -> Result<()> {
        self.validate().map_err(|p| Error::InvalidScene {
            origin: self.name.clone(),
            message: format!("{}: {}", p.key, p.message),
        })
    }

    /// Folder relative mesh paths start from.
    pub fn base(&self) -> PathBuf {
        self.base_dir.clone().unwrap_or_else(|| PathBuf::from("."))
    }

    /// The scene with its liquid surface held fixed (`solver.freeze_surface`): the map the
    /// frozen-surface gradient is exact for.
    pub fn with_frozen_surface(mut self) -> Scene {
        self.solver.freeze_surface = true;
        self
    }

    /// The world settings the scene asks for.
    pub fn settings(&self) -> WorldSettings {
        WorldSettings {
            dt: self.time.dt,
            fluid: self.fluid,
            solver: self.solver.clone(),
            contact: self.contact.clone(),
        }
    }

    /// The simulation the scene describes, in its initial state.
    pub fn build(&self) -> Result<Simulation> {
        let invalid = |p: Problem| Error::InvalidScene {
            origin: self.name.clone(),
            message: format!("{}: {}", p.key, p.message),
        };
        self.builder().map_err(invalid)?.build().map_err(|e| match e {
            Error::InvalidSettings { key, message } => invalid(problem(key, message)),
            e => e,
        })
    }

    /// The world builder with every part of the scene in it (shapes built, meshes loaded).
    fn builder(&self) -> std::result::Result<SimulationBuilder, Problem> {
        let base = self.base();
        let mut b = Simulation::builder(self.domain.size, self.domain.dx).settings(self.settings());
        let mut notes = Vec::new();
        for (i, l) in self.liquid.iter().enumerate() {
            let s = l.build_noting(&base, &mut notes);
            b = b.liquid(s.map_err(|m| problem(format!("liquid[{i}]"), m))?);
        }
        for (i, o) in self.obstacle.iter().enumerate() {
            let s = o.build_noting(&base, &mut notes);
            b = b.obstacle(s.map_err(|m| problem(format!("obstacle[{i}]"), m))?);
        }
        for (i, spec) in self.body.iter().enumerate() {
            b = b.body(self.build_body(i, spec, &mut notes)?);
        }
        for n in notes {
            b = b.warning(n);
        }
        Ok(b)
    }

    /// The i-th body in its initial state.
    fn build_body(
        &self,
        i: usize,
        b: &BodySpec,
        notes: &mut Vec<String>,
    ) -> std::result::Result<RigidBody, Problem> {
        let key = format!("body[{i}]");
        let solid = match (b.shell_thickness, &b.shape) {
            (None, _) => b.placed().build_noting(&self.base(), notes),
            (Some(t), ShapeSpec::Mesh { .. }) => {
                check_positive(&format!("{key}.shell_thickness"), t)?;
                b.placed().build_shell(&self.base(), t)
            }
            (Some(_), _) => {
                let message = "applies to a mesh body (shape kind = \"mesh\") only";
                return Err(problem(format!("{key}.shell_thickness"), message));
            }
        };
        let solid = solid.map_err(|m| problem(&key, m))?;
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
        let mut body =
            RigidBody::with_density(b.name_or_default(i), solid.shape, solid.pose, density);
        if !(body.mass.is_finite() && body.mass > 0.0) {
            return Err(problem(&key, "the shape has no volume (degenerate shape)"));
        }
        if let Some(m) = mass {
            body.set_mass(m);
        }
        body.v = v3(b.velocity);
        body.w = v3(b.angular_velocity);
        // A body that is not dynamic but has a velocity moves along it: a prescribed motion
        // (a paddle, a wave maker) the pressure solve sees.
        // A steered body that is not dynamic starts from rest when it has no velocity.
        let steered = self.control.as_ref().is_some_and(|c| c.bodies.contains(&key_name(i, b)));
        let still = b.velocity == [0.0; 3] && b.angular_velocity == [0.0; 3] && !steered;
        body.motion = match (b.dynamic, still) {
            (true, _) => Motion::Dynamic,
            (false, true) => Motion::Fixed,
            (false, false) => Motion::Kinematic,
        };
        Ok(body)
    }

    /// The loss the `[loss]` section describes (None when there is none).
    pub fn loss(&self) -> Option<BodyTargetLoss> {
        let l = self.loss.as_ref()?;
        let body = self.body_index(&l.body)?;
        Some(BodyTargetLoss {
            body,
            position: l.position.as_ref().map(|t| (v3(t.target), t.weight)),
            orientation: l.orientation.as_ref().map(|t| {
                let q = t.target;
                (Rotation::from_xyzw(q[1], q[2], q[3], q[0]).normalize(), t.weight)
            }),
            velocity: l.velocity.as_ref().map(|t| (v3(t.target), t.weight)),
        })
    }

    /// The index of the body named `name`.
    pub fn body_index(&self, name: &str) -> Option<usize> {
        (0..self.body.len()).find(|&i| self.body[i].name_or_default(i) == name)
    }

    /// The loss of the `[loss]` section on a whole trajectory (its final target, waypoints,
    /// effort, speed and liquid box); None without one.
    pub fn trajectory_loss(&self) -> Option<TrajectoryTerms> {
        let l = self.loss.as_ref()?;
        let target = self.loss()?;
        let body = target.body;
        let final_target = (target.position.is_some()
            || target.orientation.is_some()
            || target.velocity.is_some())
        .then_some(FinalTarget {
            body,
            position: target.position,
            orientation: target.orientation,
            velocity: target.velocity,
        });
        Some(TrajectoryTerms {
            waypoints: l
                .waypoint
                .iter()
                .map(|w| Waypoint {
                    body,
                    step: w.step,
                    position: v3(w.position),
                    weight: w.weight,
                })
                .collect(),
            target: final_target,
            effort: l.effort,
            speed: (l.speed != 0.0).then_some((body, l.speed)),
            liquid_in_box: l.liquid_in_box.as_ref().map(|b| LiquidInBox {
                min: v3(b.min),
                max: v3(b.max),
                target: b.target,
                weight: b.weight,
            }),
        })
    }

    /// The schedule of the `[control]` section on `sim` (built from this scene), its actions
    /// at their starting values; None without one.
    pub fn schedule(&self, sim: &Simulation) -> Option<Result<Schedule>> {
        let c = self.control.as_ref()?;
        let handles: Vec<_> =
            c.bodies.iter().filter_map(|n| self.body_index(n)).map(|i| sim.handles()[i]).collect();
        let row: Vec<[f64; 6]> =
            if c.initial.is_empty() { vec![[0.0; 6]; c.bodies.len()] } else { c.initial.clone() };
        let actions = vec![row; self.time.steps / c.steps_per_action.max(1)];
        Some(Schedule::new(sim, &handles, c.steps_per_action, actions))
    }

    /// The scene's and the bodies' names: each may name files (see
    /// [`crate::io::output::check_name`]), and no two bodies share one (a body's name is its
    /// key: its frames, its rows in `bodies.csv`, the body `[loss]` and `[control]` mean).
    fn check_names(&self) -> std::result::Result<(), Problem> {
        use crate::io::output::check_name;
        check_name(&self.name).map_err(|m| problem("name", m))?;
        let mut names: Vec<String> = Vec::with_capacity(self.body.len());
        for (i, b) in self.body.iter().enumerate() {
            let name = b.name_or_default(i);
            let key = format!("body[{i}].name");
            check_name(&name).map_err(|m| problem(&key, m))?;
            if let Some(j) = names.iter().position(|n| *n == name) {
                let default =
                    if b.name.is_empty() { ", the name an unnamed body gets" } else { "" };
                return Err(problem(
                    key,
                    format!(
                        "{name:?}{default} is body[{j}]'s name too: each body needs its own \
                         (it names the body's files and rows, and the body a loss means)"
                    ),
                ));
            }
            names.push(name);
        }
        Ok(())
    }

    fn validate(&self) -> std::result::Result<(), Problem> {
        self.check_names()?;
        if self.time.steps == 0 {
            return Err(problem("time.steps", "must be at least 1"));
        }
        self.builder()?.check()?;
        if let Some(l) = &self.loss {
            let names: Vec<String> =
                self.body.iter().enumerate().map(|(i, b)| b.name_or_default(i)).collect();
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
            for (k, w) in l.waypoint.iter().enumerate() {
                let key = format!("loss.waypoint[{k}]");
                if !(1..=self.time.steps).contains(&w.step) {
                    return Err(problem(
                        format!("{key}.step"),
                        format!("must be in 1..={}, got {}", self.time.steps, w.step),
                    ));
                }
                check_finite(&format!("{key}.position"), &w.position)?;
                if !(w.weight.is_finite() && w.weight >= 0.0) {
                    return Err(problem(format!("{key}.weight"), "must be a non-negative number"));
                }
            }
            for (key, w) in [("loss.effort", l.effort), ("loss.speed", l.speed)] {
                if !(w.is_finite() && w >= 0.0) {
                    return Err(problem(key, format!("must be a non-negative number, got {w}")));
                }
            }
            if let Some(b) = &l.liquid_in_box {
                check_finite("loss.liquid_in_box.min", &b.min)?;
                check_finite("loss.liquid_in_box.max", &b.max)?;
                if (0..3).any(|d| b.max[d] <= b.min[d]) {
                    return Err(problem(
                        "loss.liquid_in_box",
                        "max must be above min on every axis",
                    ));
                }
                for (key, x) in [
                    ("loss.liquid_in_box.target", b.target),
                    ("loss.liquid_in_box.weight", b.weight),
                ] {
                    if !(x.is_finite() && x >= 0.0) {
                        return Err(problem(
                            key,
                            format!("must be a non-negative number, got {x}"),
                        ));
                    }
                }
            }
            let trajectory_terms = !l.waypoint.is_empty()
                || l.effort > 0.0
                || l.speed > 0.0
                || l.liquid_in_box.is_some();
            if trajectory_terms && self.control.is_none() {
                return Err(problem(
                    "loss",
                    "waypoint, effort, speed and liquid_in_box are terms on a trajectory: they \
                     need a [control] section",
                ));
            }
            if l.position.is_none()
                && l.orientation.is_none()
                && l.velocity.is_none()
                && !trajectory_terms
            {
                return Err(problem(
                    "loss",
                    "give at least one of position, orientation, velocity",
                ));
            }
        }
        if let Some(c) = &self.control {
            let names: Vec<String> =
                self.body.iter().enumerate().map(|(i, b)| b.name_or_default(i)).collect();
            if c.bodies.is_empty() {
                return Err(problem("control.bodies", "name at least one body"));
            }
            for n in &c.bodies {
                if !names.contains(n) {
                    return Err(problem(
                        "control.bodies",
                        format!("no body named {n:?} (bodies: {names:?})"),
                    ));
                }
            }
            if c.steps_per_action == 0 {
                return Err(problem("control.steps_per_action", "must be at least 1"));
            }
            if self.time.steps % c.steps_per_action != 0 {
                return Err(problem(
                    "control.steps_per_action",
                    format!(
                        "time.steps ({}) must be a multiple of it ({})",
                        self.time.steps, c.steps_per_action
                    ),
                ));
            }
            if !c.initial.is_empty() && c.initial.len() != c.bodies.len() {
                return Err(problem(
                    "control.initial",
                    format!(
                        "one action per body: {} for {} bodies",
                        c.initial.len(),
                        c.bodies.len()
                    ),
                ));
            }
            if c.initial.iter().flatten().any(|x| !x.is_finite()) {
                return Err(problem("control.initial", "must be finite"));
            }
            if let Some(b) = c.bound {
                if !(b.is_finite() && b > 0.0) {
                    return Err(problem(
                        "control.bound",
                        format!("must be a positive number, got {b}"),
                    ));
                }
            }
            if c.epochs == 0 {
                return Err(problem("control.epochs", "must be at least 1"));
            }
            for f in &c.free {
                if action_entry(f).is_none() {
                    return Err(problem(
                        "control.free",
                        format!(
                            "unknown entry {f:?}: use vx vy vz wx wy wz (a velocity) or fx fy fz \
                             tx ty tz (a force and torque)"
                        ),
                    ));
                }
            }
            match &c.optimizer {
                OptimizerSpec::Gd { learning_rate } | OptimizerSpec::Adam { learning_rate, .. } => {
                    if !(learning_rate.is_finite() && *learning_rate > 0.0) {
                        return Err(problem(
                            "control.optimizer.learning_rate",
                            format!("must be a positive number, got {learning_rate}"),
                        ));
                    }
                }
                OptimizerSpec::Lbfgs { .. } => {
                    return Err(problem("control.optimizer", "control takes gd or adam"))
                }
            }
            if self.loss.is_none() {
                return Err(problem("control", "needs a [loss] section"));
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
            if let Some(Err(Error::InvalidSettings { key, message })) =
                o.smoothing.as_ref().map(|s| s.validate())
            {
                return Err(problem(key, message));
            }
        }
        if self.output.every == 0 {
            return Err(problem("output.every", "must be at least 1"));
        }
        if !(1..=8).contains(&self.output.surface_samples) {
            return Err(problem(
                "output.surface_samples",
                format!("must be 1 to 8, got {}", self.output.surface_samples),
            ));
        }
        if self.output.surface && !cfg!(feature = "surface") {
            return Err(problem("output.surface", crate::io::output::SURFACE_FEATURE_MISSING));
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

    /// The memory check's particle count is at least what the built-in scenes seed (so its
    /// bytes are not an underestimate), and not more than twice it: with a band, the count
    /// is the band's, not the liquid's (`large_tank` seeds 0.63 M particles; its liquid
    /// holds 3.7 M).
    #[test]
    fn memory_estimate_counts_the_particles_seeded() {
        for name in ["large_tank", "dam_break", "block_drop", "floating_box"] {
            let scene = Scene::builtin(name).unwrap();
            let builder = scene.builder().unwrap();
            let grid = builder.check().unwrap();
            let (bytes, particles) = builder.memory_estimate(&grid);
            let seeded = scene.build().unwrap().particles.len() as f64;
            // `auto` may estimate the full volume for a band it then takes (the estimate sees
            // the regions' bounds, the choice their cells): never more than that.
            let mut full = scene.clone();
            full.solver.narrow_band = 0.into();
            let full = full.builder().unwrap().memory_estimate(&grid).1;
            let auto = scene.solver.narrow_band == crate::world::NarrowBand::Auto;
            assert!(
                particles >= seeded
                    && (particles <= 2.0 * seeded || (auto && particles <= full)),
                "{name}: {particles} particles estimated, {seeded} seeded, {full} for the full volume"
            );
            assert!(bytes >= 250.0 * grid.num_cells() as f64 + 56.0 * seeded, "{name}");
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
