//! Gradients of a loss with respect to the initial state and to every step's actions:
//! losses on the final state ([`loss`]), the backward pass over a forward pass's tape
//! ([`mod@backward`]), the loss and its gradient in one call with optional checkpointing
//! ([`run`]), control (per-step actions in a [`schedule`], trajectory losses, [`control`]
//! and [`trajectory`]), and gradient checks against central differences ([`check`]).

pub mod backward;
pub mod check;
pub mod control;
pub mod loss;
pub mod run;
pub mod schedule;
pub mod smooth;
pub mod trajectory;

pub use backward::{backward, backward_adjoint, GradientMode, GradientOptions};
pub use check::{
    central_difference, gradcheck, gradcheck_controlled, Coordinate, GradcheckReport,
    GradcheckSettings,
};
pub use control::{
    value_and_gradient_controlled, ControlRun, ControlledRun, Stepper, Trajectory, TrajectoryLoss,
    TrajectorySeed,
};
pub use loss::{AdjointState, BodyAdjoint, BodyGradient, BodyTargetLoss, Gradient, Loss};
pub use run::{value_and_gradient, GradientRun, GradientSettings, Rollout};
pub use schedule::{ActionKind, Actions, Schedule};
pub use smooth::{
    value_and_smoothed_gradient, SmoothedRun, Smoothing, SmoothingEstimator, SmoothingScale,
};
pub use trajectory::{FinalTarget, LiquidInBox, TrajectoryTerms, Waypoint};
