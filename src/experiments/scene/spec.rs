//! The scene file's tables as serde reads them: the scene itself, the tank, time, bodies and
//! output (`[loss]` is in `loss.rs`, `[control]` and `[optimize]` in `optimizer.rs`). An
//! unknown key is an error.

use super::loss::LossSpec;
use super::optimizer::{ControlSpec, OptimizeSpec};
use crate::experiments::shapes::{AxisAngle, Placed, ShapeSpec};
use crate::io::output::MeshFormat;
use crate::math::Arr3;
use crate::world::{ContactSettings, Fluid, SolverSettings};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

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
