//! Gradients: the adjoint against central differences, |adjoint − fd| ≤ atol + rtol·|fd|,
//! end to end (one step, short rollouts, thin bodies) and for the smoothed loss.

#[allow(dead_code)] // each group uses part of it
#[path = "../common/mod.rs"]
mod common;

mod adjoint;
mod smooth_defaults;
mod smoothing;
mod soft_surface;
mod thin_gradients;
