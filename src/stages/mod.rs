//! The stages of a step, each forward function with its adjoint beside it, and their order
//! ([`Stage::ALL`]).
pub mod advect;
pub mod band;
pub mod contact;
pub mod density;
pub mod extrapolate;
pub mod forces;
pub mod particles;
pub mod pressure;
pub mod project;
pub mod rigid;
pub mod solid_phi;
mod stage;
pub mod surface;
pub mod system;

pub use stage::{Stage, StageClock, StageSeconds};
