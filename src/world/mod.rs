//! A running simulation ([`Simulation`]), its settings, and its step: the parts of a step the
//! forward and backward passes share ([`step`]) and the tape the forward pass records for the
//! backward pass ([`tape`]).

pub mod settings;
mod simulation;
pub mod step;
pub mod tape;

pub use settings::{ContactSettings, Fluid, NarrowBand, SolverSettings, WorldSettings};
pub use simulation::{BodyHandle, Simulation, SimulationBuilder};
pub use step::{BodyForce, Energy, StageSeconds, StepReport, StepSystem};
pub use tape::{StepRecord, Tape};
