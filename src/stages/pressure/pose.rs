//! The pose part of the projection adjoint: how the system moves with a body's pose.

use crate::geometry::grid::Mac;
use crate::geometry::weights::FaceWeights;
use crate::math::Vec3;

use super::*;

/// What the pose part of the projection adjoint ([`projection_pose_adjoint`]) reads.
pub struct PoseAdjointInputs<'a> {
    /// The step's system (its `bodies` the coupled bodies' terms).
    pub sys: &'a PressureSystem,
    /// The combined fluid weights.
    pub weights: &'a FaceWeights,
    /// φ_L (extended into the solids).
    pub phi: &'a [f64],
    /// The static solids' weights.
    pub static_weights: &'a FaceWeights,
    /// The fluid velocity before the projection.
    pub u_hat: &'a Mac,
    /// The step's pressure.
    pub p: &'a [f64],
    /// The adjoint solve's solution.
    pub s: &'a [f64],
    /// The step.
    pub dt: f64,
}

/// ∂L/∂[δx; δθ] of one body through the projection's geometry, for fixed velocities: with
/// the adjoint solve's s and the adjoint V′ of the body's velocity after the solve,
/// `dL = sᵀ(δb − δA·p) + V′·(δMi·J p + Mi·δJ p)` where b = −F(w)·û − Jᵀ v̂,
/// A = S(w) + Jᵀ Mi J and Mi = Δt·M⁻¹. δw = −δβ on faces the clamp leaves alone, δJ comes
/// from δβ and from the torque arms (δr = −δx), δMi from the rotation of the inertia.
///
/// For a body carrying liquid (`entrained` not empty), `faces` are J's faces ([`Seal::coupling`]
/// of the fractions), `v_hat` its velocity with that liquid's momentum (V_e), and δMi is left
/// to [`Entrained::pose_adjoint`], which differentiates M_e whole.
///
/// [`Seal::coupling`]: crate::geometry::seal::Seal::coupling
/// [`Entrained::pose_adjoint`]: super::Entrained::pose_adjoint
pub fn projection_pose_adjoint(
    g: &PoseAdjointInputs<'_>,
    body: &crate::geometry::body::RigidBody,
    faces: &[Vec<(usize, crate::math::dual::Dual<6>)>; 3],
    coupling: usize,
    v_hat: &[f64; 6],
    adj_v: &[f64; 6],
    entrained: &super::Entrained,
) -> [f64; 6] {
    let turn = if entrained.is_empty() { Inverse::Turns } else { Inverse::Elsewhere };
    body_pose_adjoint(g, body, faces, &g.sys.bodies[coupling], turn, v_hat, adj_v)
}

/// Where δ(Δt·M⁻¹) of a body's pose goes.
#[derive(Clone, Copy, PartialEq)]
enum Inverse {
    /// Nothing of the solve moves the body (a kinematic one).
    Fixed,
    /// It is the turn of the world inertia, here.
    Turns,
    /// It is taken elsewhere (with the entrained liquid's).
    Elsewhere,
}

/// [`projection_pose_adjoint`] of a kinematic body (`sys.kinematic`'s coupling `bc`, its
/// prescribed [v; ω]): its J pushes the right-hand side and its fractions take the fluid's
/// weights, but nothing of the solve moves it (no M⁻¹ terms).
pub fn kinematic_pose_adjoint(
    g: &PoseAdjointInputs<'_>,
    body: &crate::geometry::body::RigidBody,
    faces: &[Vec<(usize, crate::math::dual::Dual<6>)>; 3],
    bc: &BodyCoupling,
    v: &[f64; 6],
) -> [f64; 6] {
    body_pose_adjoint(g, body, faces, bc, Inverse::Fixed, v, &[0.0; 6])
}

/// The pose part of the projection adjoint of a body whose coupling is `bc`, in the
/// operator (`coupled`, a dynamic body) or only in the right-hand side (a kinematic one).
fn body_pose_adjoint(
    g: &PoseAdjointInputs<'_>,
    body: &crate::geometry::body::RigidBody,
    faces: &[Vec<(usize, crate::math::dual::Dual<6>)>; 3],
    bc: &BodyCoupling,
    inverse: Inverse,
    v_hat: &[f64; 6],
    adj_v: &[f64; 6],
) -> [f64; 6] {
    let sys = g.sys;
    let grid = sys.grid;
    let area = grid.dx * grid.dx;
    let row_val = |c: Option<usize>, x: &[f64]| match c.map(|c| sys.row_of_cell[c]) {
        Some(r) if r != crate::geometry::grid::NONE => x[r as usize],
        _ => 0.0,
    };
    let spin = body.spin();
    let (js, jp) = (bc.force(g.s), bc.force(g.p));
    let mi = bc.dt_minv;
    let mi_jp = bc.dt_minv_times(&jp);
    let mut out = [0.0; 6];
    // δJ·x for x = s and x = p, per direction: [direction][component].
    let mut djs = [[0.0; 6]; 6];
    let mut djp = [[0.0; 6]; 6];
    for axis in 0..3 {
        let lat = grid.faces(axis);
        let e = crate::math::unit(axis);
        for (f, beta) in faces[axis].iter() {
            let f = *f;
            let ijk = lat.ijk(f);
            let (m, pl) = grid.face_cells(axis, ijk);
            // Fluid weight: w = clamp(w_static − β): its derivative is −δβ inside the clamp.
            let raw = g.static_weights.weight(axis, f) - beta.v;
            if raw > 0.0 && raw < 1.0 && g.weights.weight(axis, f) > 0.0 {
                let uh = g.u_hat.c[axis][f];
                let flux = area * uh * (row_val(m, g.s) - row_val(pl, g.s));
                let stencil = sys.weight_adjoint(axis, f, g.weights, g.phi, g.s, g.p);
                // sᵀδb ∋ −sᵀ δF û = −Σ dx²·δw·û·(s_m − s_p), δw = −δβ; −sᵀ δS p likewise.
                for k in 0..6 {
                    out[k] += beta.d[k] * (flux + stencil);
                }
            }
            // δJ columns on the two cells beside the face.
            let r = lat.position(ijk[0], ijk[1], ijk[2]) - body.x;
            let t = spin.project(r.cross(e));
            let col = [e.x, e.y, e.z, t.x, t.y, t.z];
            let (sm, sp) = (row_val(m, g.s), row_val(pl, g.s));
            let (pm, pp) = (row_val(m, g.p), row_val(pl, g.p));
            let (ns, np) = (area * (sm - sp), area * (pm - pp));
            for k in 0..6 {
                for c in 0..6 {
                    djs[k][c] += ns * beta.d[k] * col[c];
                    djp[k][c] += np * beta.d[k] * col[c];
                }
                // δr = −e_k: δ(P·(r × e)) = −P·(e_k × e); a rotation δθ = e_k turns the
                // symmetry axis of P: δP·(r × e).
                let dt_ = if k < 3 {
                    spin.project(-crate::math::unit(k).cross(e))
                } else {
                    spin.rotation_derivative(r.cross(e), crate::math::unit(k - 3))
                };
                for c in 0..3 {
                    djs[k][3 + c] += ns * beta.v * crate::math::comp(dt_, c);
                    djp[k][3 + c] += np * beta.v * crate::math::comp(dt_, c);
                }
            }
        }
    }
    let dot6 = |a: &[f64; 6], b: &[f64; 6]| (0..6).map(|i| a[i] * b[i]).sum::<f64>();
    let mv = |m: &[[f64; 6]; 6], x: &[f64; 6]| -> [f64; 6] {
        std::array::from_fn(|r| (0..6).map(|c| m[r][c] * x[c]).sum())
    };
    // δMi for the rotation directions: Δt·([e]×·I⁻¹ − I⁻¹·[e]×) on the angular block.
    let inv = body.world_inertia().inverse();
    let inv_a: [[f64; 3]; 3] =
        std::array::from_fn(|r| std::array::from_fn(|c| inv.col(c).to_array()[r]));
    for k in 0..6 {
        let mut dmi = [[0.0; 6]; 6];
        if k >= 3 && inverse == Inverse::Turns {
            let ax = crate::math::unit(k - 3);
            let cross = |v: [f64; 3]| {
                let w = ax.cross(Vec3::new(v[0], v[1], v[2]));
                [w.x, w.y, w.z]
            };
            // [e]× I⁻¹: columns of I⁻¹ crossed; I⁻¹ [e]×: I⁻¹ applied to e × unit columns.
            for c in 0..3 {
                let colc = [inv_a[0][c], inv_a[1][c], inv_a[2][c]];
                let left = cross(colc);
                let ec = ax.cross(crate::math::unit(c));
                for r in 0..3 {
                    let right = (0..3).map(|q| inv_a[r][q] * crate::math::comp(ec, q)).sum::<f64>();
                    dmi[3 + r][3 + c] = g.dt * (left[r] - right);
                }
            }
        }
        let dmi_jp = mv(&dmi, &jp);
        let mi_djp = mv(&mi, &djp[k]);
        let lhs = -dot6(&djs[k], v_hat)
            - (dot6(&djs[k], &mi_jp) + dot6(&js, &dmi_jp) + dot6(&js, &mi_djp));
        out[k] += lhs + dot6(adj_v, &dmi_jp) + dot6(adj_v, &mi_djp);
    }
    out
}
