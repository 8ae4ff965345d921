//! The system's operator, right-hand side, solve and velocity update.

use crate::geometry::grid::{Mac, NONE};
use crate::geometry::weights::FaceWeights;
use crate::math::buffer::refill;
use crate::math::par::for_each_keyed_mut;
use crate::solvers::cg::{pcg_from, CgSettings, CgStats};
use crate::solvers::stencil::Stencil;
use crate::solvers::LinearSolve;
use rayon::prelude::*;

use super::*;

impl PressureSystem {
    /// Number of unknowns.
    pub fn len(&self) -> usize {
        self.cell_of_row.len()
    }

    /// True when there is no liquid cell.
    pub fn is_empty(&self) -> bool {
        self.cell_of_row.is_empty()
    }

    /// The fluid stencil, which a solve reads.
    ///
    /// # Panics
    /// When the system was built without it ([`PressureSystem::build_without_operator_in`]).
    pub fn operator(&self) -> &Stencil {
        assert!(
            self.operator,
            "the pressure system was built without its operator (for a step given its \
             pressures), and cannot be solved or applied"
        );
        &self.stencil
    }

    /// y = A x (the fluid stencil).
    pub fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.operator().apply(x, y);
        for b in &self.bodies {
            let s = b.dt_minv_times(&b.force(x));
            b.add_jt(&s, y);
        }
    }

    /// Volume flux out of each liquid cell through its fluid faces, `Σ_f σ_if·dx²·w_f·u_f`.
    pub fn fluid_flux(&self, u: &Mac, weights: &FaceWeights) -> Vec<f64> {
        let area = self.grid.dx * self.grid.dx;
        self.flux_times(u, weights, area)
    }

    /// `Σ_f σ_if·w_f·u_f` times `scale` (`dx²`, or `−dx²` for minus the flux: the same bits
    /// as negating it after, rounding being symmetric). A row's cell's (i, j, k) is the last
    /// row's with i + 1 when the two cells are neighbours along x (most rows), so the loop
    /// divides only at the start of a run of cells.
    fn flux_times(&self, u: &Mac, weights: &FaceWeights, scale: f64) -> Vec<f64> {
        let grid = &self.grid;
        let cells = grid.cells();
        let w = weights.axes();
        let mut out = vec![0.0; self.cell_of_row.len()];
        const ROWS: usize = 4096;
        out.par_chunks_mut(ROWS).zip(self.cell_of_row.par_chunks(ROWS)).for_each(|(out, rows)| {
            let mut last: Option<(usize, [usize; 3])> = None;
            for (o, &c) in out.iter_mut().zip(rows) {
                let c = c as usize;
                let ijk = match last {
                    Some((p, [i, j, k])) if c == p + 1 && i + 1 < grid.n[0] => [i + 1, j, k],
                    _ => cells.ijk(c),
                };
                last = Some((c, ijk));
                let mut f = 0.0;
                for a in 0..3 {
                    let lo = cell_face(grid, a, ijk, 0);
                    let hi = cell_face(grid, a, ijk, 1);
                    f += w[a].weight(hi) * u.c[a][hi] - w[a].weight(lo) * u.c[a][lo];
                }
                *o = f * scale;
            }
        });
        out
    }

    /// Right-hand side `(1/ρ) Gᵀ M_F u − Jᵀ V`: minus the volume flux out of each cell,
    /// through its fluid faces and pushed by each body's velocity `V = [v; ω]` (one per
    /// entry of `bodies`).
    pub fn rhs(&self, u: &Mac, weights: &FaceWeights, body_velocity: &[[f64; 6]]) -> Vec<f64> {
        assert_eq!(body_velocity.len(), self.bodies.len());
        let area = self.grid.dx * self.grid.dx;
        let mut b = self.flux_times(u, weights, -area);
        for (body, v) in self.bodies.iter().zip(body_velocity) {
            let minus_v = v.map(|x| -x);
            body.add_jt(&minus_v, &mut b);
        }
        b
    }

    /// Factors the preconditioner a solve with `how` reads, if it is not yet (a solve does
    /// it first otherwise): for a caller that builds the system ahead of its solve. Nothing
    /// without liquid or without the operator.
    pub fn prepare(&self, how: &LinearSolve) {
        if self.operator && !self.is_empty() {
            self.preconditioner.get(how.preconditioner.resolve(self.len()), self);
        }
    }

    /// Solves A p = b from p = 0 ([`Preconditioner::Auto`](crate::solvers::Preconditioner::Auto) picks the preconditioner by the
    /// number of unknowns).
    pub fn solve(&self, b: &[f64], how: &LinearSolve) -> (Vec<f64>, CgStats) {
        self.solve_from(b, vec![0.0; self.len()], how)
    }

    /// [`PressureSystem::solve`] from the initial guess `p` (one value per unknown).
    pub fn solve_from(&self, b: &[f64], mut p: Vec<f64>, how: &LinearSolve) -> (Vec<f64>, CgStats) {
        assert_eq!(p.len(), self.len());
        let settings = CgSettings {
            tolerance: how.tolerance,
            max_iterations: how.max_iterations,
            project_constant: !self.has_air,
        };
        let apply = |x: &[f64], y: &mut [f64]| self.apply(x, y);
        // The solve runs as one task on a rayon worker, so its many small parallel loops
        // (dozens per wavefront-scheduled MIC(0) or per V-cycle) are forked from inside the
        // pool instead of each waking a worker from outside (two thread switches apiece), and
        // the other workers stay awake through it instead of falling asleep between loops.
        let stats = crate::math::pool::on_pool_awake(|| {
            let prepared = self.preconditioner.get(how.preconditioner.resolve(self.len()), self);
            match prepared.as_ref() {
                Prepared::Mic0(m) => pcg_from(
                    apply,
                    |r: &[f64], z: &mut [f64]| m.apply(self.operator(), r, z),
                    b,
                    &mut p,
                    &settings,
                ),
                Prepared::Multigrid(m) => pcg_from(apply, m, b, &mut p, &settings),
                Prepared::None => pcg_from(
                    apply,
                    |r: &[f64], z: &mut [f64]| z.copy_from_slice(r),
                    b,
                    &mut p,
                    &settings,
                ),
            }
        });
        (p, stats)
    }

    /// Applies `u −= (Δt/ρ) ∇p` on every open face next to a liquid cell (with p = 0 in air
    /// at distance θ·dx) and returns the mask of faces so updated (the valid faces).
    pub fn update_velocity(&self, p: &[f64], u: &mut Mac) -> [Vec<u8>; 3] {
        self.velocity_update_with(p, u, |x, du| *x -= du)
    }

    /// [`PressureSystem::update_velocity`] without the mask, for a caller that does not read
    /// it (three face-sized arrays fewer to clear and fill).
    pub fn subtract_pressure_gradient(&self, p: &[f64], u: &mut Mac) {
        self.velocity_apply(p, u, |x, du| *x -= du)
    }

    /// [`PressureSystem::update_velocity`] of a zero field, written over those faces of `u`
    /// (its other faces left as they are, whatever they hold).
    pub fn velocity_update_into(&self, p: &[f64], u: &mut Mac) -> [Vec<u8>; 3] {
        self.velocity_update_with(p, u, |x, du| *x = 0.0 - du)
    }

    /// `apply(u_f, (Δt/ρ) ∇p)` on the faces the update acts on; their mask.
    pub(super) fn velocity_update_with(
        &self,
        p: &[f64],
        u: &mut Mac,
        apply: impl Fn(&mut f64, f64) + Sync,
    ) -> [Vec<u8>; 3] {
        self.velocity_apply(p, u, apply);
        let face = |pf: &ProjectedFace| pf.face as usize;
        [0, 1, 2].map(|a| {
            let mut valid = vec![0u8; self.grid.faces(a).len()];
            for_each_keyed_mut(&mut valid, &self.faces[a], face, |_, _, v| *v = 1);
            valid
        })
    }

    /// `apply(u_f, (Δt/ρ) ∇p)` on the faces the update acts on, the three axes side by side.
    fn velocity_apply(&self, p: &[f64], u: &mut Mac, apply: impl Fn(&mut f64, f64) + Sync) {
        let k = self.params.dt / (self.params.density * self.grid.dx);
        let face = |pf: &ProjectedFace| pf.face as usize;
        let axis = |a: usize, ua: &mut Vec<f64>| {
            for_each_keyed_mut(ua, &self.faces[a], face, |_, pf, x| {
                apply(x, k * pf.gradient.apply(p))
            });
        };
        let [ux, uy, uz] = &mut u.c;
        rayon::join(|| axis(0, ux), || rayon::join(|| axis(1, uy), || axis(2, uz)));
    }

    /// What [`PressureSystem::update_velocity`] subtracts from face `f` of `axis` for the
    /// pressure `p` (0 on a face it does not update).
    pub fn velocity_update_at(&self, axis: usize, f: usize, p: &[f64]) -> f64 {
        let k = self.params.dt / (self.params.density * self.grid.dx);
        match self.faces[axis].binary_search_by_key(&(f as u32), |pf| pf.face) {
            Ok(i) => k * self.faces[axis][i].gradient.apply(p),
            Err(_) => 0.0,
        }
    }

    /// The pressure gradient across face `f` of `axis` as `cp·p[rp] − cm·p[rm]` (scaled by
    /// 1/dx elsewhere), when the velocity update acts on the face: an open face next to a
    /// liquid cell. A side in air has no row (p = 0 there) and the other side's coefficient
    /// carries the ghost-fluid 1/θ.
    #[inline]
    pub fn face_gradient(
        &self,
        axis: usize,
        f: usize,
        weights: &FaceWeights,
        phi: &[f64],
    ) -> Option<FaceGradient> {
        if weights.closed(axis, f) {
            return None;
        }
        let grid = &self.grid;
        let (m, pl) = grid.face_cells(axis, grid.faces(axis).ijk(f));
        self.gradient_between(m?, pl?, phi)
    }

    /// [`PressureSystem::face_gradient`] of an open face between cells `m` (its − side) and
    /// `pl`: Some exactly when either is an unknown (the condition `projected_faces` counts
    /// by, without computing the coefficient, which is measurably faster).
    #[inline]
    pub(super) fn gradient_between(
        &self,
        m: usize,
        pl: usize,
        phi: &[f64],
    ) -> Option<FaceGradient> {
        let (rm, rp) = (self.row_of_cell[m], self.row_of_cell[pl]);
        let ghost = self.params.ghost;
        match (rm != NONE, rp != NONE) {
            (true, true) => Some(FaceGradient { rm, rp, c: 1.0 }),
            (true, false) => Some(FaceGradient { rm, rp, c: 1.0 / ghost.theta(phi[m], phi[pl]) }),
            (false, true) => Some(FaceGradient { rm, rp, c: 1.0 / ghost.theta(phi[pl], phi[m]) }),
            (false, false) => None,
        }
    }

    /// Pressure on the whole cell grid (zero outside the liquid).
    pub fn scatter(&self, p: &[f64]) -> Vec<f64> {
        let mut out = Vec::new();
        self.scatter_into(p, &mut out);
        out
    }

    /// [`PressureSystem::scatter`] written over `out`.
    pub fn scatter_into(&self, p: &[f64], out: &mut Vec<f64>) {
        refill(out, self.grid.num_cells(), 0.0);
        for (r, &c) in self.cell_of_row.iter().enumerate() {
            out[c as usize] = p[r];
        }
    }
}
