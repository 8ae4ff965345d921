//! Gradients: the backward pass, losses, body parameters.
mod backward;
pub use backward::*;
