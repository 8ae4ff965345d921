//! The stages of a step, each forward function with its adjoint beside it.
pub mod advect;
pub mod band;
pub mod contact;
pub mod density;
pub mod extrapolate;
pub mod forces;
pub mod pressure;
pub mod solid_phi;
pub mod surface;
