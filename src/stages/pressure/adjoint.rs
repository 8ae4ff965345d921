//! The adjoints of the solve and the update: the adjoint solve, and ∂L through the
//! weights, the ghost-fluid θ and the bodies' velocities.

use crate::geometry::grid::{Mac, NONE};
use crate::geometry::weights::FaceWeights;
use crate::math::par::for_each_keyed_mut;
use crate::solvers::cg::CgStats;
use crate::solvers::LinearSolve;

use super::*;

impl PressureSystem {
    /// −∂/∂w_f of ⟨s, A(w)·p⟩ for face `f` of `axis`: `Δt·dx/ρ · θ·(g·s)(g·p)` with g the
    /// face's pressure gradient (carrying 1/θ on a ghost-fluid face), 0 where the update does
    /// not act. With δw = −δβ on a face a body covers, this times ∂β/∂pose is the operator's
    /// part of the pose derivative −sᵀ·δA·p.
    pub fn weight_adjoint(
        &self,
        axis: usize,
        f: usize,
        weights: &FaceWeights,
        phi: &[f64],
        s: &[f64],
        p: &[f64],
    ) -> f64 {
        let Some(fg) = self.face_gradient(axis, f, weights, phi) else {
            return 0.0;
        };
        let theta = 1.0 / fg.c;
        let scale = self.params.dt * self.grid.dx / self.params.density;
        scale * theta * fg.apply(s) * fg.apply(p)
    }

    /// ∂L/∂φ per cell through the ghost-fluid θ = φ_l/(φ_l − φ_a) of the liquid–air faces
    /// (the free surface's position), for the solve's solution `p`, the adjoint solve's `s`
    /// and the adjoint `ubar` of the updated velocity: dL = −sᵀ·(∂A/∂θ)·p·dθ + ūᵀ·(∂u/∂θ)·dθ,
    /// with A ∋ Δt·dx/ρ·w/θ on the liquid cell's diagonal and u_f = û_f ∓ k·p_l/θ. Zero where
    /// θ is clamped at θ_min.
    /// `weights` are the face weights the system was built with.
    pub fn phi_adjoint(
        &self,
        phi: &[f64],
        weights: &FaceWeights,
        s: &[f64],
        p: &[f64],
        ubar: &Mac,
    ) -> Vec<f64> {
        let mut out = vec![0.0; self.grid.num_cells()];
        let scale = self.params.dt * self.grid.dx / self.params.density;
        let k = self.params.dt / (self.params.density * self.grid.dx);
        for a in 0..3 {
            let lat = self.grid.faces(a);
            for pf in &self.faces[a] {
                let g = &pf.gradient;
                // The liquid row and its side: + side liquid when the − side is air.
                let (r, sign) = match (g.rm == NONE, g.rp == NONE) {
                    (true, false) => (g.rp as usize, 1.0),
                    (false, true) => (g.rm as usize, -1.0),
                    _ => continue,
                };
                let (m, pl) = self.grid.face_cells(a, lat.ijk(pf.face as usize));
                let (m, pl) = (m.expect("an interior face"), pl.expect("an interior face"));
                let (l, air) = if sign > 0.0 { (pl, m) } else { (m, pl) };
                let (pl_, pa) = (phi[l], phi[air]);
                let Some((dl, da)) = self.params.ghost.theta_gradient(pl_, pa) else {
                    continue;
                };
                let theta = self.params.ghost.theta(pl_, pa);
                let theta2 = theta * theta;
                // u_f = û_f − k·sign·p_l/θ.
                let theta_bar = s[r] * scale * weights.weight(a, pf.face as usize) * p[r] / theta2
                    + ubar.c[a][pf.face as usize] * sign * k * p[r] / theta2;
                out[l] += theta_bar * dl;
                out[air] += theta_bar * da;
            }
        }
        out
    }

    /// Adjoint of [`PressureSystem::update_velocity`] with respect to p: given the adjoint
    /// of the updated face velocities, returns `−k·G̃ᵀ·adj` per row.
    pub fn update_velocity_adjoint(&self, adj_u: &Mac) -> Vec<f64> {
        let k = self.params.dt / (self.params.density * self.grid.dx);
        let mut out = vec![0.0; self.len()];
        for a in 0..3 {
            for pf in &self.faces[a] {
                let adj = adj_u.c[a][pf.face as usize];
                if adj == 0.0 {
                    continue;
                }
                let g = &pf.gradient;
                if g.rp != NONE {
                    out[g.rp as usize] -= k * g.c * adj;
                }
                if g.rm != NONE {
                    out[g.rm as usize] += k * g.c * adj;
                }
            }
        }
        out
    }

    /// Subtracts from `adj` the transpose of [`PressureSystem::fluid_flux`] applied to a row
    /// adjoint `s` (zero in air and solid): the face adjoint `dx²·w_f·(s_m − s_p)` on each
    /// projected face, for the system's face weights `weights`.
    pub fn subtract_fluid_flux_adjoint(&self, s: &[f64], weights: &FaceWeights, adj: &mut Mac) {
        let area = self.grid.dx * self.grid.dx;
        let sv = |r: u32| if r != NONE { s[r as usize] } else { 0.0 };
        for a in 0..3 {
            let face = |pf: &ProjectedFace| pf.face as usize;
            let w = weights.axis(a);
            for_each_keyed_mut(&mut adj.c[a], &self.faces[a], face, |_, pf, x| {
                let g = &pf.gradient;
                *x -= area * w.weight(pf.face as usize) * (sv(g.rm) - sv(g.rp));
            });
        }
    }

    /// The adjoint solve of the projection: from the adjoints of the projected face
    /// velocities `adj_u` and of the bodies' `[v; ω]` after the solve, `s` with
    /// `A s = ∂(velocity update)ᵀ·adj_u + Δt·J M_S⁻¹·adj_v` (one more solve with the same
    /// operator).
    pub fn adjoint_solve(
        &self,
        adj_u: &Mac,
        adj_v: &[[f64; 6]],
        how: &LinearSolve,
    ) -> (Vec<f64>, CgStats) {
        let mut pbar = self.update_velocity_adjoint(adj_u);
        for (b, av) in self.bodies.iter().zip(adj_v) {
            b.add_jt(&b.dt_minv_times(av), &mut pbar);
        }
        // No warm start here: the adjoint pressure of the step after this one saves half an
        // iteration of 18 on block_drop, one of 9 on large_tank.
        self.solve(&pbar, how)
    }

    /// The coupled bodies' `[v; ω]` adjoint before the projection, `adj_v − J s`.
    pub fn body_velocity_adjoint(&self, adj_v: &[[f64; 6]], s: &[f64]) -> Vec<[f64; 6]> {
        self.bodies
            .iter()
            .zip(adj_v)
            .map(|(b, av)| {
                let js = b.force(s);
                std::array::from_fn(|d| av[d] - js[d])
            })
            .collect()
    }

    /// Adjoint of the whole projection (right-hand side, solve, velocity and body updates)
    /// for fixed geometry (paper, eqs. 8–9, in this code's terms): from the adjoints of the
    /// projected face velocities `adj_u` and of the bodies' `[v; ω]` after the solve, one more
    /// solve with the same operator gives `s` ([`PressureSystem::adjoint_solve`]), and the
    /// adjoints before the projection are `adj_u − Fᵀ s` (left in `adj_u`) and `adj_v − J s`.
    /// With `surface` (φ_L extended into the solids, and the step's pressure), also ∂L/∂φ_L
    /// through the ghost-fluid θ ([`PressureSystem::phi_adjoint`]). `weights` are the face
    /// weights the system was built with.
    pub fn projection_adjoint(
        &self,
        adj_u: &mut Mac,
        adj_v: &[[f64; 6]],
        weights: &FaceWeights,
        how: &LinearSolve,
        surface: Option<(&[f64], &[f64])>,
    ) -> ProjectionAdjoint {
        let (s, stats) = self.adjoint_solve(adj_u, adj_v, how);
        let phi = surface.map(|(phi, p)| self.phi_adjoint(phi, weights, &s, p, adj_u));
        self.subtract_fluid_flux_adjoint(&s, weights, adj_u);
        let v_hat = self.body_velocity_adjoint(adj_v, &s);
        ProjectionAdjoint { v_hat, s, stats, phi }
    }
}

/// What [`PressureSystem::projection_adjoint`] gives besides the field's adjoint.
#[derive(Debug)]
pub struct ProjectionAdjoint {
    /// ∂L/∂[v; ω] of each coupled body before the solve.
    pub v_hat: Vec<[f64; 6]>,
    /// The adjoint solve's solution.
    pub s: Vec<f64>,
    /// Its statistics.
    pub stats: CgStats,
    /// ∂L/∂φ_L per cell through θ, when asked.
    pub phi: Option<Vec<f64>>,
}
