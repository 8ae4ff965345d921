//! diffluid: differentiable Eulerian liquid simulation with strong two-way rigid coupling.
//!
//! The forward step is a pipeline of stages, one module each (see [`sim`]):
//! [`surface`] (marker particles, liquid signed distance), [`advect`], [`forces`],
//! [`pressure`] (with [`cg`], [`mic0`] and [`multigrid`]), and [`extrapolate`]. Geometry enters through
//! [`shape`] (parry shapes) and [`fractions`] (face weights from signed distances); scenes
//! are TOML files read by [`scene`].
#![warn(missing_docs)]
// Loops over the three axes index several per-axis arrays at once; an index reads better.
#![allow(clippy::needless_range_loop)]

pub mod error;
pub mod experiments;
pub mod geometry;
pub mod gradients;
pub mod io;
pub mod math;
pub mod solvers;
pub mod stages;
pub mod world;

pub use error::{Error, Result};
pub use experiments::scene::Scene;
pub use world::{Simulation, StepReport};
