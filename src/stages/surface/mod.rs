//! The free surface: marker particles, their advection, and the liquid signed distance φ_L,
//! each with its adjoint (the live-surface gradient of `gradients::backward`).
//!
//! Particles are seeded on a regular sub-lattice (m³ per cell), advected with RK2 in the
//! grid velocity, pushed out of static solids and kept inside the tank. φ_L at a cell centre
//! is `min_p |x − x_p| − r`: negative in liquid. It is a distance only within a cell or two
//! of the surface (deep inside it is just negative), which is all the ghost-fluid boundary
//! reads. The radius `r` is chosen so that a flat, freshly seeded surface on a cell face is
//! reconstructed exactly halfway between the cell centres that straddle it
//! (see [`particle_radius`]).

mod advection;
mod bins;
mod deposit;
mod distance;
mod ghosts;
mod lanes;
mod pockets;
mod push;
mod seeding;
mod softmin;
#[cfg(test)]
mod tests;

pub use advection::*;
pub use bins::*;
pub use deposit::*;
pub use distance::*;
pub use ghosts::*;
pub use pockets::*;
pub use push::*;
pub use seeding::*;
pub use softmin::{soft_particle_radius, SOFT_REACH};
