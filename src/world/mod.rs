//! A running simulation and its step.
mod simulation;
pub use simulation::*;
