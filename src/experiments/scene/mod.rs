//! Scene files: TOML read with serde (an unknown key is an error), validated into values a
//! simulation can trust, with errors that name the key and, where there is one, the line.
//!
//! The files, each one concern: the tables as serde reads them (`spec.rs`: the scene, tank,
//! time, bodies and output; `loss.rs`: `[loss]`; `optimizer.rs`: `[control]`, `[optimize]`
//! and the optimiser), `parse.rs` (TOML text to a checked scene, errors with their line),
//! `validate.rs` (every check, each naming its key), `build.rs` (the simulation a scene
//! describes), `objective.rs` (its loss and control schedule) and `builtin.rs` (the scenes
//! shipped with diffluid).

mod build;
mod builtin;
mod loss;
mod objective;
mod optimizer;
mod parse;
mod spec;
mod validate;

pub use crate::io::output::MeshFormat;
pub use builtin::{BUILTIN_SCENES, DEFAULT_SCENE};
pub use loss::{BoxTarget, LossSpec, Target3, TargetQ, WaypointSpec};
pub use optimizer::{action_entry, ControlSpec, OptimizeSpec, OptimizerSpec, SurfaceGradientSpec};
pub use spec::{BodySpec, Domain, Output, Scene, Time};
