//! Gradients of a loss on the final state with respect to the initial state: losses
//! ([`loss`]), the backward pass over a forward pass's tape ([`mod@backward`]), the loss and its
//! gradient in one call with optional checkpointing ([`run`]), and gradient checks against
//! central differences ([`check`]).

pub mod backward;
pub mod check;
pub mod loss;
pub mod run;

pub use backward::{backward, backward_adjoint, GradientMode, GradientOptions};
pub use check::{central_difference, gradcheck, Coordinate, GradcheckReport, GradcheckSettings};
pub use loss::{AdjointState, BodyAdjoint, BodyGradient, BodyTargetLoss, Gradient, Loss};
pub use run::{value_and_gradient, GradientRun, GradientSettings, Rollout};
