//! Linear solvers for the pressure system: conjugate gradients ([`cg`]) preconditioned by
//! MIC(0) ([`mic0`]) or a multigrid V-cycle ([`multigrid`]), over the 7-point
//! [`stencil::Stencil`] the pressure stage builds. [`LinearSolve`] is how a caller picks one.

pub mod cg;
pub mod mic0;
pub mod multigrid;
pub mod stencil;

/// Systems the solvers' tests share.
#[cfg(test)]
pub(crate) mod testing {
    use crate::geometry::grid::Grid;
    use crate::stages::pressure::{GhostFluid, PressureParams, PressureSystem};

    /// A tank of `n` cells filled to `level` (a sloped surface; above 1 it is full and
    /// closed), with a blob of fractional face weights standing in for a body.
    pub(crate) fn tank(n: [usize; 3], level: f64) -> PressureSystem {
        let grid = Grid { n, dx: 1.0 / n[0] as f64 };
        let cells = grid.cells();
        let mut phi = vec![0.0; cells.len()];
        cells.fill_par(&mut phi, |i, j, k| {
            let p = cells.position(i, j, k);
            p.y - level - 0.1 * p.x + 0.05 * p.z
        });
        let weights = [0, 1, 2].map(|a| {
            let lat = grid.faces(a);
            let mut w = vec![0.0; lat.len()];
            lat.fill_par(&mut w, |i, j, k| {
                let f = [i, j, k];
                if f[a] == 0 || f[a] == grid.n[a] {
                    return 0.0;
                }
                let p = lat.position(i, j, k);
                let r = (p - crate::math::v3([0.5, 0.2, 0.3])).length();
                // Solid inside r < 0.1, fractional over the next 0.05.
                ((r - 0.1) / 0.05).clamp(0.0, 1.0)
            });
            w
        });
        PressureSystem::build(
            &grid,
            &phi,
            &crate::geometry::weights::FaceWeights::new(&weights),
            PressureParams { dt: 0.01, density: 1000.0, ghost: GhostFluid::clamped(0.01) },
        )
    }
}

use serde::{Deserialize, Serialize};

/// Preconditioner for the pressure CG.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Preconditioner {
    /// Modified incomplete Cholesky, level 0 (Bridson's τ = 0.97, σ = 0.25).
    Mic0,
    /// One multigrid V-cycle (MGPCG, see [`multigrid`]).
    Multigrid,
    /// Plain conjugate gradients (for comparison).
    None,
    /// MIC(0) for systems of fewer than [`Preconditioner::AUTO_CROSSOVER`] unknowns,
    /// multigrid from there on.
    Auto,
}

impl Preconditioner {
    /// Unknowns from which `auto` picks multigrid over MIC(0). MIC(0)'s iterations grow with
    /// the grid, multigrid's hardly do: for a cold solve the crossover sits between 12³ and
    /// 16³ unknowns, and inside a time step (warm-started, fewer MIC(0) iterations) above
    /// `block_drop`'s 3,519. The measurements are in docs/performance.md ("Why the hot paths
    /// are written as they are").
    pub const AUTO_CROSSOVER: usize = 4_000;

    /// The preconditioner to use for `unknowns` unknowns: itself, unless `Auto`.
    pub fn resolve(self, unknowns: usize) -> Preconditioner {
        match self {
            Preconditioner::Auto if unknowns < Self::AUTO_CROSSOVER => Preconditioner::Mic0,
            Preconditioner::Auto => Preconditioner::Multigrid,
            other => other,
        }
    }
}

/// How to solve a pressure system: the preconditioner and the stopping rule.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinearSolve {
    /// Preconditioner ([`Preconditioner::Auto`] picks one by size).
    pub preconditioner: Preconditioner,
    /// Stop when ‖r‖₂ ≤ tolerance·‖b‖₂.
    pub tolerance: f64,
    /// Iteration cap; reaching it is reported as not converged.
    pub max_iterations: usize,
}

impl LinearSolve {
    /// A preconditioner and a stopping rule.
    pub fn new(preconditioner: Preconditioner, tolerance: f64, max_iterations: usize) -> Self {
        LinearSolve { preconditioner, tolerance, max_iterations }
    }
}
