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

pub mod adjoint;
pub mod advect;
pub mod bench;
pub mod body;
pub mod cg;
#[cfg(feature = "contact")]
pub mod contact;
pub mod density;
pub mod dual;
pub mod error;
pub mod extrapolate;
pub mod forces;
pub mod fractions;
pub mod grid;
pub mod math;
pub mod mesh;
pub mod mic0;
pub mod multigrid;
pub mod optimize;
pub mod output;
pub mod plot;
pub mod pressure;
pub mod scene;
pub mod shape;
pub mod sim;
pub mod surface;
pub mod vtk;

pub use error::{Error, Result};
pub use scene::Scene;
pub use sim::{Simulation, StepReport};
