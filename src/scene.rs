//! Scene files: TOML read with serde (an unknown key is an error), validated into values a
//! simulation can trust, with errors that name the key and, where there is one, the line.

use crate::error::{Error, Result};
use crate::grid::Grid;
use crate::math::{v3, Arr3};
use crate::shape::{Placed, Solid};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The scene `cargo run --release` runs when no scene is given.
pub const DEFAULT_SCENE: &str = include_str!("../assets/scenes/dam_break.toml");

/// Scenes shipped with diffluid, by name, so tests and the CLI can load them anywhere.
pub const BUILTIN_SCENES: &[(&str, &str)] = &[
    ("dam_break", include_str!("../assets/scenes/dam_break.toml")),
    (
        "still_water",
        include_str!("../assets/scenes/still_water.toml"),
    ),
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
    /// What to write out.
    #[serde(default)]
    pub output: Output,
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
    /// Plain conjugate gradients (for comparison).
    None,
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
    /// Preconditioner. Default `mic0`.
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
}

impl Default for Solver {
    fn default() -> Self {
        Solver {
            tolerance: 1e-8,
            max_iterations: 2000,
            preconditioner: Preconditioner::Mic0,
            extrapolation_layers: 3,
            particles_per_cell: 8,
            theta_min: 0.01,
            density_correction: true,
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
        Output {
            particles: true,
            every: 1,
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

/// A validation failure: the key it concerns and what is wrong.
struct Problem {
    key: String,
    message: String,
}

fn problem(key: impl Into<String>, message: impl Into<String>) -> Problem {
    Problem {
        key: key.into(),
        message: message.into(),
    }
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
        let text = std::fs::read_to_string(path).map_err(|source| Error::ReadScene {
            path: path.to_path_buf(),
            source,
        })?;
        Scene::from_toml(&text, &path.display().to_string())
    }

    /// Parses and validates a scene from TOML text; `origin` names it in errors.
    pub fn from_toml(text: &str, origin: &str) -> Result<Scene> {
        let scene: Scene = toml::from_str(text).map_err(|e| {
            let line = e
                .span()
                .map(|s| text[..s.start.min(text.len())].lines().count().max(1));
            let msg = e.message().trim().replace('\n', " ");
            Error::ParseScene {
                origin: origin.to_string(),
                message: match line {
                    Some(l) => format!("line {l}: {msg}"),
                    None => msg,
                },
            }
        })?;
        scene.validate().map_err(|p| {
            let at = locate(text, &p.key)
                .map(|l| format!("line {l}: "))
                .unwrap_or_default();
            Error::InvalidScene {
                origin: origin.to_string(),
                message: format!("{at}{}: {}", p.key, p.message),
            }
        })?;
        Ok(scene)
    }

    /// A scene shipped with diffluid, by name (`dam_break`, `still_water`, ...).
    pub fn builtin(name: &str) -> Result<Scene> {
        let text = BUILTIN_SCENES
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, t)| *t)
            .ok_or_else(|| Error::InvalidScene {
                origin: "<builtin>".into(),
                message: format!("no built-in scene named {name:?}"),
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
        let n = self
            .domain
            .size
            .map(|s| (s / self.domain.dx).round() as usize);
        Grid {
            n,
            dx: self.domain.dx,
        }
    }

    /// Built static obstacles.
    pub fn obstacles(&self) -> Vec<Solid> {
        self.obstacle
            .iter()
            .map(|p| p.build().expect("validated"))
            .collect()
    }

    /// Built liquid regions.
    pub fn liquid_regions(&self) -> Vec<Solid> {
        self.liquid
            .iter()
            .map(|p| p.build().expect("validated"))
            .collect()
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
            return Err(problem(
                "domain",
                format!("{cells} cells is more than 512³; raise dx"),
            ));
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
            let s = l.build().map_err(|m| problem(&key, m))?;
            let (lo, hi) = s.bounds();
            if lo.min_element() < -tol || (hi - size).max_element() > tol {
                return Err(problem(
                    &key,
                    format!(
                        "liquid region spans {:?}..{:?}, outside the domain [0, 0, 0]..{:?}",
                        lo.to_array(),
                        hi.to_array(),
                        d.size
                    ),
                ));
            }
        }
        for (i, o) in self.obstacle.iter().enumerate() {
            o.build()
                .map_err(|m| problem(format!("obstacle[{i}]"), m))?;
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
