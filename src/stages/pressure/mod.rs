//! The pressure projection (the `pressure` stage, see `stages/project.rs`): right-hand side → solve → velocity update, each a
//! function of its own.
//!
//! Unknowns are the liquid cells only (φ_L < 0 with at least one open face), numbered in
//! lexicographic order. With face fluid weights `w_f` (open area fraction), the ghost-fluid
//! fraction θ on liquid–air faces (Gibou et al. 2002) and `s = Δt·dx/ρ`, row i reads
//!
//! ```text
//!   Σ_f s·w_f/θ_f · (p_i − p_nbr(f)) = −Σ_f σ_if·dx²·w_f·u_f       (p_air = 0, θ = 1 inside)
//! ```
//!
//! which is the paper's `A p = (1/ρ) Gᵀ M_F u` with `A = (Δt/ρ²) Gᵀ M_F G`, scaled by nothing:
//! the residual `b − A p` of row i is exactly minus the volume flux out of cell i after the
//! velocity update, so a relative residual is a relative divergence. The operator is applied
//! matrix-free from a stored 7-point stencil; rigid bodies add a rank-6 term per body.

//!
//! One concern a file: the system's build (`build.rs`), its solve and velocity update
//! (`solve.rs`), their adjoints (`adjoint.rs`), the pose part of the adjoint (`pose.rs`), a
//! body's coupling (`coupling.rs`), the preconditioner cache (`preconditioner.rs`) and the
//! memory pool systems are built into (`pool.rs`).

use crate::geometry::grid::{Grid, NONE};
use crate::geometry::weights::{cell_face, open_neighbour, AxisWeights, FaceWeights};
use crate::solvers::stencil::Stencil;
use serde::{Deserialize, Serialize};

mod adjoint;
mod build;
mod coupling;
mod entrained;
mod pool;
mod pose;
mod preconditioner;
mod solve;

pub use adjoint::ProjectionAdjoint;
pub use coupling::BodyCoupling;
pub use entrained::{arm_derivative, mass_matrix, Entrained, EntrainedFace};
pub use pool::{SystemMemory, SystemPool};
pub use pose::{kinematic_pose_adjoint, projection_pose_adjoint, PoseAdjointInputs};
use preconditioner::{PreconditionerCache, Prepared};

/// The pressure gradient across one face in terms of the rows beside it (see
/// [`PressureSystem::face_gradient`]): `c·(p[rp] − p[rm])` with p = 0 on a side in air. A
/// face between two rows has c = 1; a face with one side in air carries the ghost-fluid 1/θ
/// on its liquid side. One coefficient for both sides, and 4-byte alignment, keep a
/// [`ProjectedFace`] at 20 bytes (aligned to 8, its coefficient made it 24: 5.8 MB more at
/// `large_tank`'s peak, whose system lists 1.4 M faces). Its fields are read by value.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, packed(4))]
pub struct FaceGradient {
    /// Row on the − side ([`NONE`] in air).
    pub rm: u32,
    /// Row on the + side ([`NONE`] in air).
    pub rp: u32,
    /// The coefficient of each side that is a row.
    pub c: f64,
}

impl FaceGradient {
    /// The − side's coefficient (0 in air).
    #[inline]
    pub fn cm(&self) -> f64 {
        if self.rm != NONE {
            self.c
        } else {
            0.0
        }
    }

    /// The + side's coefficient (0 in air).
    #[inline]
    pub fn cp(&self) -> f64 {
        if self.rp != NONE {
            self.c
        } else {
            0.0
        }
    }

    /// `cp·p[rp] − cm·p[rm]`.
    #[inline]
    pub fn apply(&self, p: &[f64]) -> f64 {
        let at = |r: u32| if r != NONE { self.c * p[r as usize] } else { 0.0 };
        at(self.rp) - at(self.rm)
    }
}

/// How the liquid and the bodies exchange momentum in a step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Coupling {
    /// One pressure solve for liquid and bodies together (Batty et al. 2007): the body's
    /// response to the pressure is part of the system, so it is stable for any density ratio.
    #[default]
    Monolithic,
    /// The partitioned baseline: the liquid is solved around each body moving at its current
    /// velocity (held fixed), then the body is pushed by the resulting pressure force. Light
    /// bodies go unstable (the added-mass instability); kept to show where, not for use.
    Weak,
}

/// Everything the pressure stage needs besides the velocities.
#[derive(Clone, Copy, Debug)]
pub struct PressureParams {
    /// Time step.
    pub dt: f64,
    /// Liquid density.
    pub density: f64,
    /// The ghost-fluid θ at the free surface.
    pub ghost: GhostFluid,
}

/// The assembled (matrix-free) pressure system of one step.
#[derive(Clone, Debug)]
pub struct PressureSystem {
    /// The grid.
    pub grid: Grid,
    /// Step parameters.
    pub params: PressureParams,
    /// Cell of each unknown.
    pub cell_of_row: Vec<u32>,
    /// Unknown of each cell, [`NONE`] for air and solid.
    pub row_of_cell: Vec<u32>,
    /// The fluid stencil (empty when the system was built without its operator: see
    /// [`PressureSystem::build_without_operator_in`]).
    pub stencil: Stencil,
    /// True when some liquid cell touches air (then A is definite); false without the
    /// operator.
    pub has_air: bool,
    /// Rank-6 coupling terms, one per dynamic body.
    pub bodies: Vec<BodyCoupling>,
    /// Per axis, the faces the velocity update acts on (open faces next to a liquid cell),
    /// in increasing face order, with their pressure gradients.
    pub faces: [Vec<ProjectedFace>; 3],
    /// The preconditioner, factored from the stencil at the first solve and reused by every
    /// later one (a step's contact iterations solve up to five times with one operator).
    preconditioner: PreconditionerCache,
    /// Whether the operator (the stencil) was built.
    operator: bool,
}

/// A face the velocity update acts on.
#[derive(Clone, Copy, Debug)]
pub struct ProjectedFace {
    /// Face index on its axis's lattice.
    pub face: u32,
    /// The pressure gradient across it.
    pub gradient: FaceGradient,
}

const _: () = assert!(std::mem::size_of::<ProjectedFace>() == 20);

/// The ghost-fluid fraction θ of a liquid–air face (Gibou et al. 2002): where φ_L crosses zero
/// between the two centres, measured from the liquid side, θ = φ_l/(φ_l − φ_a), clamped below
/// at `theta_min`. Its derivative in φ grows without bound as both cells near φ = 0; a floor
/// on the denominator (max(φ_a − φ_l, dx/2)) bounds it, but made the surge rougher, not
/// smoother (docs/gradients.md, "The density projection's interior").
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GhostFluid {
    /// Lower clamp on θ.
    pub theta_min: f64,
}

impl GhostFluid {
    /// θ clamped at `theta_min`.
    pub const fn clamped(theta_min: f64) -> GhostFluid {
        GhostFluid { theta_min }
    }

    /// θ before its clamp: the share of the way from the liquid cell's centre to the air
    /// cell's where φ_L crosses zero.
    #[inline]
    pub fn fraction(phi_liquid: f64, phi_air: f64) -> f64 {
        -phi_liquid / (phi_air - phi_liquid)
    }

    /// (∂/∂φ_l, ∂/∂φ_a) of [`GhostFluid::fraction`].
    #[inline]
    pub fn fraction_gradient(phi_liquid: f64, phi_air: f64) -> (f64, f64) {
        let den = phi_air - phi_liquid;
        let den2 = den * den;
        (-phi_air / den2, phi_liquid / den2)
    }

    /// θ of a face from a liquid cell at `phi_liquid` (< 0) to an air cell at `phi_air`.
    #[inline]
    pub fn theta(&self, phi_liquid: f64, phi_air: f64) -> f64 {
        GhostFluid::fraction(phi_liquid, phi_air).max(self.theta_min)
    }

    /// (∂θ/∂φ_l, ∂θ/∂φ_a), or `None` where θ sits at its clamp (no derivative).
    #[inline]
    pub fn theta_gradient(&self, phi_liquid: f64, phi_air: f64) -> Option<(f64, f64)> {
        if GhostFluid::fraction(phi_liquid, phi_air) <= self.theta_min {
            return None;
        }
        Some(GhostFluid::fraction_gradient(phi_liquid, phi_air))
    }
}

/// Calls `visit(face, − cell, + cell)` for the open faces (weight > 0) of `axis` in slab k of
/// its face lattice that have a cell on both sides, in the rows (j, k) of faces that `live`
/// accepts, in face order, without a division per face: f runs over the face lattice, c over
/// the cell on each face's + side.
#[inline]
fn open_faces(
    grid: &Grid,
    axis: usize,
    k: usize,
    weights: &FaceWeights,
    live: impl Fn(usize, usize) -> bool,
    mut visit: impl FnMut(usize, usize, usize),
) {
    let [nx, ny, _] = grid.faces(axis).n;
    let n = grid.n;
    let w = weights.axis(axis);
    // The cell on the − side of a face is this far below the one on its + side.
    let below = [1, n[0], n[0] * n[1]][axis];
    if axis == 2 && (k == 0 || k == n[2]) {
        return;
    }
    for j in 0..ny {
        if axis == 1 && (j == 0 || j == n[1]) || !live(j, k) {
            continue;
        }
        let (f0, c0) = (nx * (j + ny * k), n[0] * (j + n[1] * k));
        let (lo, hi) = if axis == 0 { (1, n[0]) } else { (0, nx) };
        for i in lo..hi {
            let f = f0 + i;
            if w.open(f) {
                let c = c0 + i;
                visit(f, c - below, c);
            }
        }
    }
}

/// Whether cell `c` has a face of positive weight (a liquid cell is an unknown when it has).
pub fn has_open_face(grid: &Grid, weights: &FaceWeights, c: usize) -> bool {
    has_open_face_at(grid, &weights.axes(), grid.cells().ijk(c))
}

/// [`has_open_face`] of the cell at `ijk`, with each axis's weights.
#[inline]
fn has_open_face_at(grid: &Grid, w: &[AxisWeights<'_>; 3], ijk: [usize; 3]) -> bool {
    (0..3).any(|a| (0..2).any(|s| w[a].open(cell_face(grid, a, ijk, s))))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::grid::Mac;
    use crate::solvers::{LinearSolve, Preconditioner};

    /// A small tank with a free surface and a partly blocked face.
    /// The system with the φ_L and face weights it was built from.
    fn system() -> PressureSystem {
        system_with_inputs().0
    }

    fn system_with_inputs() -> (PressureSystem, Vec<f64>, FaceWeights) {
        let grid = Grid { n: [5, 6, 4], dx: 0.1 };
        let cells = grid.cells();
        let mut phi = vec![0.0; cells.len()];
        cells.fill_par(&mut phi, |_, j, _| (j as f64 + 0.5) * 0.1 - 0.33);
        let mut weights = [0, 1, 2].map(|a| {
            let lat = grid.faces(a);
            let mut w = vec![1.0; lat.len()];
            lat.fill_par(&mut w, |i, j, k| {
                let f = [i, j, k];
                if f[a] == 0 || f[a] == grid.n[a] {
                    0.0
                } else {
                    1.0
                }
            });
            w
        });
        weights[0][grid.faces(0).index(2, 1, 1)] = 0.3;
        let weights = FaceWeights::new(&weights);
        let sys = PressureSystem::build(
            &grid,
            &phi,
            &weights,
            PressureParams { dt: 0.01, density: 1000.0, ghost: GhostFluid::clamped(0.01) },
        );
        (sys, phi, weights)
    }

    /// The flux with (i, j, k) carried from row to row is, bit for bit, the sum over each
    /// row's faces found from its cell's own (i, j, k), and the right-hand side its negative.
    #[test]
    fn fluid_flux_is_the_sum_over_each_rows_faces() {
        let (sys, _, weights) = system_with_inputs();
        let grid = sys.grid;
        let mut u = Mac::zeros(&grid);
        for (a, c) in u.c.iter_mut().enumerate() {
            c.iter_mut().enumerate().for_each(|(f, x)| *x = ((f * 7 + a) % 11) as f64 - 4.9);
        }
        let w = weights.axes();
        let want: Vec<f64> = sys
            .cell_of_row
            .iter()
            .map(|&c| {
                let ijk = grid.cells().ijk(c as usize);
                let mut f = 0.0;
                for a in 0..3 {
                    let lo = cell_face(&grid, a, ijk, 0);
                    let hi = cell_face(&grid, a, ijk, 1);
                    f += w[a].weight(hi) * u.c[a][hi] - w[a].weight(lo) * u.c[a][lo];
                }
                f * (grid.dx * grid.dx)
            })
            .collect();
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&sys.fluid_flux(&u, &weights)), bits(&want));
        let minus: Vec<f64> = want.iter().map(|x| -x).collect();
        assert_eq!(bits(&sys.rhs(&u, &weights, &[])), bits(&minus));
    }

    #[test]
    fn projected_faces_are_every_face_with_a_gradient_once() {
        // The face list the velocity update walks must be exactly the faces where the
        // per-face rule gives a gradient, each once, in order.
        let (sys, phi, weights) = system_with_inputs();
        for a in 0..3 {
            let brute: Vec<u32> = (0..sys.grid.faces(a).len())
                .filter(|&f| sys.face_gradient(a, f, &weights, &phi).is_some())
                .map(|f| f as u32)
                .collect();
            let listed: Vec<u32> = sys.faces[a].iter().map(|pf| pf.face).collect();
            assert!(!brute.is_empty());
            assert_eq!(listed, brute, "axis {a}");
            for pf in &sys.faces[a] {
                let g = sys.face_gradient(a, pf.face as usize, &weights, &phi).unwrap();
                let h = pf.gradient;
                assert_eq!(g, h, "face {}", pf.face);
            }
        }
    }

    /// A system built into another's memory (a larger grid's, its multigrid factored) is the
    /// system built afresh, and solves the same to the bit.
    #[test]
    fn built_into_old_memory_is_built_afresh() {
        let (sys, phi, weights) = system_with_inputs();
        let grid = Grid { n: [9, 7, 8], dx: 0.1 };
        let other_phi = vec![-1.0; grid.num_cells()];
        let other_w = FaceWeights::new(&[0, 1, 2].map(|a| vec![0.5; grid.faces(a).len()]));
        let other = PressureSystem::build(&grid, &other_phi, &other_w, sys.params);
        let how = LinearSolve {
            tolerance: 1e-10,
            max_iterations: 200,
            preconditioner: Preconditioner::Multigrid,
        };
        let _ = other.solve(&vec![1.0; other.len()], &how);
        let pool = SystemPool::default();
        pool.give(other);
        let memory = pool.take();
        assert!(memory.multigrid.is_some(), "the factored multigrid is handed on");
        let reused = PressureSystem::build_in(memory, &sys.grid, &phi, &weights, sys.params);
        assert_eq!(reused.cell_of_row, sys.cell_of_row);
        assert_eq!(reused.row_of_cell, sys.row_of_cell);
        assert_eq!(reused.stencil.diag, sys.stencil.diag);
        assert_eq!(reused.stencil.plus, sys.stencil.plus);
        assert_eq!(reused.stencil.nbr, sys.stencil.nbr);
        assert_eq!(reused.has_air, sys.has_air);
        for a in 0..3 {
            let key = |f: &ProjectedFace| {
                let g = f.gradient;
                (f.face, g.rm, g.rp, g.c.to_bits())
            };
            let (x, y): (Vec<_>, Vec<_>) =
                (reused.faces[a].iter().map(key).collect(), sys.faces[a].iter().map(key).collect());
            assert_eq!(x, y, "axis {a}");
        }
        let b: Vec<f64> = (0..sys.len()).map(|r| ((r * 7) % 5) as f64 - 2.0).collect();
        let (p0, _) = sys.solve(&b, &how);
        let (p1, _) = reused.solve(&b, &how);
        assert!(p0.iter().zip(&p1).all(|(x, y)| x.to_bits() == y.to_bits()));
    }

    /// Built without its operator, into a solved system's memory: the unknowns and the
    /// velocity update are the full build's to the bit, and solving panics instead of reading
    /// the old system's stencil.
    #[test]
    fn built_without_operator_updates_alike_and_cannot_solve() {
        let (sys, phi, weights) = system_with_inputs();
        let how = LinearSolve {
            tolerance: 1e-10,
            max_iterations: 200,
            preconditioner: Preconditioner::Multigrid,
        };
        let b: Vec<f64> = (0..sys.len()).map(|r| ((r * 7) % 5) as f64 - 2.0).collect();
        let (p, _) = sys.solve(&b, &how);
        let pool = SystemPool::default();
        pool.give(sys.clone());
        let lean = PressureSystem::build_without_operator_in(
            pool.take(),
            &sys.grid,
            &phi,
            &weights,
            sys.params,
        );
        assert_eq!(lean.cell_of_row, sys.cell_of_row);
        assert_eq!(lean.row_of_cell, sys.row_of_cell);
        assert!(lean.stencil.diag.is_empty() && lean.stencil.nbr.is_empty());
        let field = |s: &PressureSystem| {
            let mut u = Mac::zeros(&s.grid);
            s.update_velocity(&p, &mut u);
            u.c.map(|c| c.iter().map(|x| x.to_bits()).collect::<Vec<_>>())
        };
        assert_eq!(field(&lean), field(&sys));
        let solved =
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| lean.solve(&b, &how)));
        let message = solved.expect_err("a system without its operator solved");
        let text = message
            .downcast_ref::<&str>()
            .copied()
            .or_else(|| message.downcast_ref::<String>().map(String::as_str))
            .unwrap_or("");
        assert!(text.contains("without its operator"), "{text}");
    }

    #[test]
    fn projection_adjoint_is_the_transpose() {
        // For fixed geometry the projection is linear in (û, v̂):
        // ⟨P(û, v̂), (ū, v̄)⟩ = ⟨(û, v̂), Pᵀ(ū, v̄)⟩, to the solver's tolerance.
        let (mut sys, _, weights) = system_with_inputs();
        let grid = sys.grid;
        // A body touching a few rows, with an SPD Δt·M⁻¹.
        let jac: Vec<(usize, [f64; 6])> = (0..6)
            .map(|r| {
                let c = sys.cell_of_row[r * 3] as usize;
                (c, std::array::from_fn(|d| ((r * 7 + d * 3) % 5) as f64 * 0.01 - 0.02))
            })
            .collect();
        let mut m = [[0.0; 6]; 6];
        for d in 0..6 {
            m[d][d] = 0.05 + 0.01 * d as f64;
        }
        m[3][4] = 0.004;
        m[4][3] = 0.004;
        sys.bodies.push(BodyCoupling::new(&sys.row_of_cell, &jac, m));
        let field = |seed: usize| {
            let mut u = Mac::zeros(&grid);
            for a in 0..3 {
                for (f, x) in u.c[a].iter_mut().enumerate() {
                    *x = ((f * 7919 + a * 131 + seed) % 97) as f64 / 48.0 - 1.0;
                }
            }
            u
        };
        let (uh, ub) = (field(1), field(2));
        let (vh, vb) = ([0.3, -0.2, 0.5, 0.1, 0.7, -0.4], [-0.6, 0.25, 0.1, 0.9, -0.3, 0.2]);
        let tol = 1e-14;
        // Forward.
        let b = sys.rhs(&uh, &weights, &[vh]);
        let how = LinearSolve {
            preconditioner: Preconditioner::Mic0,
            tolerance: tol,
            max_iterations: 10_000,
        };
        let (p, _) = sys.solve(&b, &how);
        let mut u1 = uh.clone();
        sys.update_velocity(&p, &mut u1);
        let dv = sys.bodies[0].dt_minv_times(&sys.bodies[0].force(&p));
        let v1: [f64; 6] = std::array::from_fn(|d| vh[d] + dv[d]);
        // Adjoint.
        let mut ua = ub.clone();
        let va = sys.projection_adjoint(&mut ua, &[vb], &weights, &how, None).v_hat;
        let lhs = u1.dot(&ub) + (0..6).map(|d| v1[d] * vb[d]).sum::<f64>();
        let rhs = uh.dot(&ua) + (0..6).map(|d| vh[d] * va[0][d]).sum::<f64>();
        assert!((lhs - rhs).abs() <= 1e-10 * lhs.abs().max(rhs.abs()), "{lhs} vs {rhs}");
    }

    /// The free surface's position: ∂L/∂φ through the ghost-fluid θ (operator and update)
    /// against central differences of the whole projection, L = ⟨c, u'⟩.
    #[test]
    fn phi_adjoint_matches_central_differences() {
        let (sys, phi, weights) = system_with_inputs();
        let grid = sys.grid;
        let params = sys.params;
        let mut uh = Mac::zeros(&grid);
        let mut c = Mac::zeros(&grid);
        for a in 0..3 {
            for (f, x) in uh.c[a].iter_mut().enumerate() {
                *x = ((f * 7919 + a * 131) % 97) as f64 / 48.0 - 1.0;
            }
            for (f, x) in c.c[a].iter_mut().enumerate() {
                *x = ((f * 104729 + a * 71) % 89) as f64 / 44.0 - 1.0;
            }
        }
        let how = LinearSolve {
            preconditioner: Preconditioner::Mic0,
            tolerance: 1e-14,
            max_iterations: 10_000,
        };
        let run = |phi: &[f64]| {
            let sys = PressureSystem::build(&grid, phi, &weights, params);
            let (p, _) = sys.solve(&sys.rhs(&uh, &weights, &[]), &how);
            let mut u = uh.clone();
            sys.update_velocity(&p, &mut u);
            (u.dot(&c), p)
        };
        let (_, p) = run(&phi);
        let (s, _) = sys.solve(&sys.update_velocity_adjoint(&c), &how);
        let g = sys.phi_adjoint(&phi, &weights, &s, &p, &c);
        assert!(g.iter().filter(|x| **x != 0.0).count() > 20, "the surface cells carry a gradient");
        let d: Vec<f64> = (0..phi.len()).map(|i| ((i * 13) % 7) as f64 / 3.0 - 1.0).collect();
        let eps = 1e-8;
        let at = |s: f64| run(&phi.iter().zip(&d).map(|(x, y)| x + s * y).collect::<Vec<_>>()).0;
        let fd = (at(eps) - at(-eps)) / (2.0 * eps);
        let ad: f64 = g.iter().zip(&d).map(|(a, b)| a * b).sum();
        assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "adjoint {ad:e}, central difference {fd:e}");
    }

    #[test]
    fn operator_is_symmetric() {
        let sys = system();
        let n = sys.len();
        let x: Vec<f64> = (0..n).map(|i| ((i * 7919) % 13) as f64 - 6.0).collect();
        let y: Vec<f64> = (0..n).map(|i| ((i * 104729) % 17) as f64 - 8.0).collect();
        let (mut ax, mut ay) = (vec![0.0; n], vec![0.0; n]);
        sys.apply(&x, &mut ax);
        sys.apply(&y, &mut ay);
        let (l, r) = (crate::geometry::grid::dot(&ax, &y), crate::geometry::grid::dot(&x, &ay));
        assert!((l - r).abs() <= 1e-13 * l.abs().max(r.abs()), "{l} vs {r}");
    }
}
