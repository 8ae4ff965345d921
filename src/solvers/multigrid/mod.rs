//! A geometric multigrid V-cycle as a preconditioner for the pressure CG (MGPCG, McAdams,
//! Sifakis & Teran 2010), beside [`crate::solvers::mic0`].
//!
//! **Levels.** The finest level is the pressure stencil on the whole cell lattice: the
//! unknowns keep their rows, every other cell (air, solid) is absent, which on the fine
//! level is exactly the Dirichlet (air, p = 0, with the ghost-fluid θ already in the
//! diagonal) or Neumann (solid, weight 0) condition the stencil was built with. A coarse
//! cell is a 2×2×2 block of fine cells (fewer at the upper ends of a lattice whose size is
//! not even), and the coarse operator is the Galerkin product `½·Pᵀ A P` with `P` the
//! piecewise-constant prolongation from a block to its fine cells that are present. It is
//! again a symmetric weakly diagonally dominant 7-point stencil, so nothing else is needed
//! to coarsen fractional face weights (bodies), ghost-fluid diagonals and odd lattice sizes:
//! they are summed into the coarse coefficients. The factor ½ is the ratio between the
//! Galerkin and the rediscretised coarse Laplacian in 3-D (a coarse face spans four fine
//! faces, while the rediscretised coupling at spacing 2h is twice the fine one); without it
//! piecewise-constant prolongation makes the coarse correction about twice too small
//! (Braess 1995, who over-corrects by a factor instead). The rank-6 rigid-body terms are
//! left out, as in MIC(0): they are a low-rank change that CG absorbs in a few iterations.
//!
//! **Smoother.** Red–black Gauss–Seidel, colour = parity of i + j + k. The cycle smooths
//! red then black ([`SMOOTHING`] times) on the way down and black then red on the way up,
//! and the coarsest level is a palindromic sequence of half-sweeps; restriction is `Pᵀ`
//! (the transpose of prolongation). So the whole V-cycle, as a map from residual to
//! correction, is symmetric, and positive definite because Gauss–Seidel converges in the
//! energy norm of any symmetric positive semi-definite matrix with a positive diagonal: it is
//! a valid CG preconditioner. In a closed tank with no air every level is singular with the
//! constant in its null space; the cycle does not divide by anything that vanishes there
//! (only by diagonals, which are positive), and CG projects the constant out.
//!
//! **Parallelism.** Each colour is stored apart, so a half-sweep writes one colour while it
//! reads the other, one independent update per cell; restriction sums each block's children
//! in a fixed order. No reduction depends on the thread count: the cycle is bit-identical
//! with any number of rayon threads.
//!
//! The files: `tuning.rs` (the cycle's constants, each with how it was chosen), `lattice.rs`
//! (the Galerkin coarse operator on a whole lattice), `level.rs` (a level's cells by colour,
//! their f32 coefficients, its vectors), `split.rs` (a level from a lattice, or the finest
//! from the pressure rows), `hierarchy.rs` (`Multigrid`: the levels built, into old memory)
//! and `cycle.rs` (one V-cycle: the red–black smoother, restriction, prolongation).

mod cycle;
mod hierarchy;
mod lattice;
mod level;
mod split;
#[cfg(test)]
mod tests;
mod tuning;

pub use hierarchy::Multigrid;
pub use tuning::{COARSEST_CELLS, COARSEST_SWEEPS, COARSE_SCALE, SMOOTHING};
