//! The liquid a moving thin body carries: the open part of the faces it seals and crosses
//! (see [`crate::geometry::seal`]).
//!
//! On such a face the liquid left in the control volume (fluid weight `s`) is held to the
//! body's normal velocity `a_fᵀ·V` (with `a_f = [e_f; P·(r_f × e_f)]`, J's column per unit
//! weight), so in the variational solve (Batty et al. 2007) its kinetic energy
//! `½·m_f·(a_fᵀ V)²`, `m_f = ρ·s·λ·dx³` (λ the face's liquid fraction: 1 between liquid
//! cells, the ghost-fluid θ at the free surface, 0 in air), joins the body's, and its
//! momentum before the solve, `m_f·û_f`, joins the body's momentum:
//!
//! ```text
//!   M_e = M + Σ_f m_f·a_f·a_fᵀ,    V_e = M_e⁻¹·(M·V̂ + Σ_f m_f·û_f·a_f)
//! ```
//!
//! and the solve runs with `Δt·M_e⁻¹` and `V_e` in place of `Δt·M⁻¹` and `V̂`. In still
//! water `û_f = g·e_f·Δt` and `V̂ = [g·Δt; 0]`, so the entrained liquid's momentum is the
//! impulse of its own weight, which balances the extra hydrostatic force of its faces in J:
//! the body feels ρ·g·V and the torque of β alone.

use crate::geometry::body::RigidBody;
use crate::geometry::grid::{Grid, Mac};
use crate::geometry::seal::Seal;
use crate::math::dual::Dual;
use crate::math::{comp, unit, TwistParts, Vec3};

use super::{GhostFluid, PressureParams};

/// One face whose liquid moves with the body.
#[derive(Clone, Copy, Debug)]
pub struct EntrainedFace {
    /// The face's axis.
    pub axis: usize,
    /// Face index on its axis's lattice.
    pub face: usize,
    /// The sealed fluid weight s.
    pub s: f64,
    /// The face's liquid fraction λ.
    pub lambda: f64,
    /// ρ·s·λ·dx³, kg.
    pub mass: f64,
    /// `a_f = [e_f; P·(r_f × e_f)]`.
    pub arm: [f64; 6],
    /// The cells on the face's − and + sides.
    pub cells: [usize; 2],
}

/// A coupled body's entrained liquid: its faces, the body's own 6×6 mass matrix M and the
/// inverse of `M_e = M + Σ m_f·a_f·a_fᵀ`.
#[derive(Clone, Debug, Default)]
pub struct Entrained {
    /// The faces (none for a body that seals nothing).
    pub faces: Vec<EntrainedFace>,
    /// The body's mass matrix `diag(m·1, I_w)`.
    pub mass: [[f64; 6]; 6],
    /// `M_e⁻¹`.
    pub inverse: [[f64; 6]; 6],
}

type M6 = [[f64; 6]; 6];

fn mv(m: &M6, x: &[f64; 6]) -> [f64; 6] {
    std::array::from_fn(|r| (0..6).map(|c| m[r][c] * x[c]).sum())
}

fn dot6(a: &[f64; 6], b: &[f64; 6]) -> f64 {
    (0..6).map(|i| a[i] * b[i]).sum()
}

/// The inverse of a symmetric positive definite 6×6 matrix (Gauss–Jordan, partial pivoting).
fn inverse(m: &M6) -> M6 {
    let mut a = *m;
    let mut inv: M6 = std::array::from_fn(|r| std::array::from_fn(|c| f64::from(r == c)));
    for col in 0..6 {
        let piv = (col..6).max_by(|&x, &y| a[x][col].abs().total_cmp(&a[y][col].abs()));
        let piv = piv.unwrap_or(col);
        a.swap(col, piv);
        inv.swap(col, piv);
        let d = a[col][col];
        for c in 0..6 {
            a[col][c] /= d;
            inv[col][c] /= d;
        }
        for r in 0..6 {
            if r != col {
                let f = a[r][col];
                if f != 0.0 {
                    for c in 0..6 {
                        a[r][c] -= f * a[col][c];
                        inv[r][c] -= f * inv[col][c];
                    }
                }
            }
        }
    }
    inv
}

/// A body's mass matrix `diag(m·1, R·I·Rᵀ)`.
pub fn mass_matrix(b: &RigidBody) -> M6 {
    let mut m = [[0.0; 6]; 6];
    for d in 0..3 {
        m[d][d] = b.mass;
    }
    let i = b.world_inertia();
    for r in 0..3 {
        for c in 0..3 {
            m[3 + r][3 + c] = i.col(c).to_array()[r];
        }
    }
    m
}

/// The derivative of the torque arm `P·(r × e)` of a face at `r` from the centre of mass
/// along pose direction k (δr = −e_k for k < 3; a turn δθ = e_{k−3} turns P's axis).
pub fn arm_derivative(body: &RigidBody, r: Vec3, e: Vec3, k: usize) -> Vec3 {
    let spin = body.spin();
    if k < 3 {
        spin.project(-unit(k).cross(e))
    } else {
        spin.rotation_derivative(r.cross(e), unit(k - 3))
    }
}

impl Entrained {
    /// The entrained liquid of `body` with seal `seal`, for φ_L `phi` (extended into the
    /// solids) at cell centres.
    pub fn new(
        grid: &Grid,
        body: &RigidBody,
        seal: &Seal,
        phi: &[f64],
        params: &PressureParams,
    ) -> Entrained {
        let mass = mass_matrix(body);
        let spin = body.spin();
        let cell = grid.dx.powi(3);
        let mut faces = Vec::new();
        for axis in 0..3 {
            let lat = grid.faces(axis);
            let e = unit(axis);
            for sf in seal.faces[axis].iter().filter(|s| s.crossed) {
                let ijk = lat.ijk(sf.face);
                let (Some(m), Some(p)) = grid.face_cells(axis, ijk) else { continue };
                let lambda = liquid_fraction(phi[m], phi[p], params.ghost);
                if lambda <= 0.0 {
                    continue;
                }
                let r = lat.position(ijk[0], ijk[1], ijk[2]) - body.x;
                let t = spin.project(r.cross(e));
                faces.push(EntrainedFace {
                    axis,
                    face: sf.face,
                    s: sf.s,
                    lambda,
                    mass: params.density * sf.s * lambda * cell,
                    arm: [e.x, e.y, e.z, t.x, t.y, t.z],
                    cells: [m, p],
                });
            }
        }
        let mut total = mass;
        for f in &faces {
            for r in 0..6 {
                for c in 0..6 {
                    total[r][c] += f.mass * f.arm[r] * f.arm[c];
                }
            }
        }
        Entrained { faces, mass, inverse: inverse(&total) }
    }

    /// Whether the body carries no liquid.
    pub fn is_empty(&self) -> bool {
        self.faces.is_empty()
    }

    /// `Δt·M_e⁻¹`.
    pub fn dt_minv(&self, dt: f64) -> M6 {
        self.inverse.map(|row| row.map(|x| dt * x))
    }

    /// `V_e = M_e⁻¹·(M·V̂ + Σ m_f·û_f·a_f)` for the body's velocity `v` and the fluid's `u`
    /// before the solve.
    pub fn velocity(&self, v: &[f64; 6], u: &Mac) -> [f64; 6] {
        let mut momentum = mv(&self.mass, v);
        for f in &self.faces {
            let uf = u.c[f.axis][f.face];
            for d in 0..6 {
                momentum[d] += f.mass * uf * f.arm[d];
            }
        }
        mv(&self.inverse, &momentum)
    }

    /// The adjoint of [`Entrained::velocity`]: from `V̄_e`, returns `(V̄, y)` with
    /// `y = M_e⁻¹·V̄_e` and `V̄ = M·y`, and adds `m_f·a_fᵀ·y` to `ubar` on the faces.
    pub fn velocity_adjoint(&self, vbar_e: &[f64; 6], ubar: &mut Mac) -> ([f64; 6], [f64; 6]) {
        let y = mv(&self.inverse, vbar_e);
        for f in &self.faces {
            ubar.c[f.axis][f.face] += f.mass * dot6(&f.arm, &y);
        }
        (mv(&self.mass, &y), y)
    }

    /// ∂L/∂m_f per face (in `faces` order): the entrained mass's part of the adjoint,
    /// `(yᵀa_f)·(û_f − a_fᵀ·V')` with V' the body's velocity after the solve.
    fn mass_adjoint(&self, y: &[f64; 6], v_new: &[f64; 6], u: &Mac) -> Vec<f64> {
        self.faces
            .iter()
            .map(|f| dot6(y, &f.arm) * (u.c[f.axis][f.face] - dot6(&f.arm, v_new)))
            .collect()
    }

    /// The pose part: ∂L/∂[δx; δθ] through M_e and the entrained momentum, for fixed
    /// velocities. With y = M_e⁻¹·V̄_e, the body's velocity `v_hat` before and `v_new` after
    /// the solve, `dL = yᵀ·δM·(V̂ − V') + Σ_f [δm_f·(yᵀa)(û − aᵀV') + m_f·(yᵀδa)(û − aᵀV') −
    /// m_f·(yᵀa)(δaᵀV')]`; δm_f = −ρ·λ·dx³·δβ_f (the sealed weight is what β leaves), δM
    /// the turn of the world inertia. `beta` are the body's fractions with their pose
    /// derivatives (sorted by face per axis).
    #[allow(clippy::too_many_arguments)]
    pub fn pose_adjoint(
        &self,
        grid: &Grid,
        body: &RigidBody,
        beta: &[Vec<(usize, Dual<6>)>; 3],
        y: &[f64; 6],
        v_hat: &[f64; 6],
        v_new: &[f64; 6],
        u: &Mac,
        density: f64,
    ) -> [f64; 6] {
        let mut out = [0.0; 6];
        // The world inertia turns with the body: δI = [e]×·I − I·[e]×.
        let dv: [f64; 6] = std::array::from_fn(|d| v_hat[d] - v_new[d]);
        let i_w = body.world_inertia();
        let wv = dv.angular();
        let yw = y.angular();
        for k in 3..6 {
            let e = unit(k - 3);
            let di = e.cross(i_w * wv) - i_w * e.cross(wv);
            out[k] += yw.dot(di);
        }
        let cell = grid.dx.powi(3);
        let dm = self.mass_adjoint(y, v_new, u);
        for (f, g) in self.faces.iter().zip(&dm) {
            let lat = grid.faces(f.axis);
            let e = unit(f.axis);
            let ijk = lat.ijk(f.face);
            let r = lat.position(ijk[0], ijk[1], ijk[2]) - body.x;
            if let Ok(i) = beta[f.axis].binary_search_by_key(&f.face, |(g, _)| *g) {
                let db = beta[f.axis][i].1.d;
                for k in 0..6 {
                    out[k] -= density * f.lambda * cell * db[k] * g;
                }
            }
            let ya = dot6(y, &f.arm);
            let slip = u.c[f.axis][f.face] - dot6(&f.arm, v_new);
            for k in 0..6 {
                let da = arm_derivative(body, r, e, k);
                let y_da = (0..3).map(|c| y[3 + c] * comp(da, c)).sum::<f64>();
                let da_v = (0..3).map(|c| v_new[3 + c] * comp(da, c)).sum::<f64>();
                out[k] += f.mass * (y_da * slip - ya * da_v);
            }
        }
        out
    }

    /// ∂L/∂φ_L per cell through the liquid fractions λ (the ghost-fluid θ on faces at the
    /// free surface), added into `out`; `phi` as the system was built with.
    pub fn phi_adjoint(
        &self,
        y: &[f64; 6],
        v_new: &[f64; 6],
        u: &Mac,
        phi: &[f64],
        ghost: GhostFluid,
        out: &mut [f64],
    ) {
        let dm = self.mass_adjoint(y, v_new, u);
        for (f, g) in self.faces.iter().zip(&dm) {
            let [m, p] = f.cells;
            let (pm, pp) = (phi[m], phi[p]);
            let (l, a) = match (pm < 0.0, pp < 0.0) {
                (true, false) => (m, p),
                (false, true) => (p, m),
                _ => continue,
            };
            let (pl, pa) = (phi[l], phi[a]);
            let Some((dl, da)) = ghost.theta_gradient(pl, pa) else {
                continue;
            };
            // m = ρ·s·λ·dx³: ∂m/∂λ = m/λ (λ > 0 on every entrained face).
            let lbar = g * f.mass / f.lambda;
            out[l] += lbar * dl;
            out[a] += lbar * da;
        }
    }
}

/// The liquid fraction of a face between cells of φ_L `a` and `b`: 1 between liquid cells,
/// the ghost-fluid θ (clamped below as the solve clamps it) from a liquid cell to air, 0
/// between air cells.
fn liquid_fraction(a: f64, b: f64, ghost: GhostFluid) -> f64 {
    match (a < 0.0, b < 0.0) {
        (true, true) => 1.0,
        (true, false) => ghost.theta(a, b),
        (false, true) => ghost.theta(b, a),
        (false, false) => 0.0,
    }
}
