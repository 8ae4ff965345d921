//! Linear solvers for the pressure system: preconditioned conjugate gradients, MIC(0) and a
//! multigrid V-cycle.
pub mod cg;
pub mod mic0;
pub mod multigrid;
