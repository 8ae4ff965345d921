//! The backward pass (the paper's Algorithm 3): the tape the forward pass records, the
//! adjoint state, losses, and the reverse pipeline that walks the stored steps stage by
//! stage, each stage the exact transpose of its forward linearisation:
//!
//! 6ᵀ rigid integration (quaternion product and normalisation), 5ᵀ velocity correction
//! (rigid faces, closed faces, extrapolation layers), 4ᵀ projection (one more solve with the
//! same operator), 2ᵀ gravity (identity), 1ᵀ advection ((W + ∂W/∂u·u)ᵀ).
//!
//! The liquid surface (particles, φ_L) is held fixed in the backward pass, as in the paper;
//! with `solver.freeze_surface` the forward pass holds it fixed too, and the gradient is then
//! the exact gradient of the forward map. [`GradientMode::Full`] carries the dependence of
//! the geometry on the body poses (face fractions, J, the world inertia, the rigid velocity
//! set inside bodies); [`GradientMode::Paper`] drops it, as the paper does.

use crate::error::{Error, Result};
use crate::geometry::body::{quat_step_adjoint, quat_tangent_gradient, RigidBody};
use crate::geometry::fractions;
use crate::geometry::grid::Mac;
use crate::math::{Rotation, Vec3};
use crate::stages::advect::advect_adjoint;
use crate::stages::extrapolate::correct_velocity_adjoint;
use crate::stages::pressure::{BodyCoupling, PressureParams, PressureSystem};
use crate::stages::surface;
use crate::world::{dt_minv, Simulation};

/// A body's state at the start of a step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BodyState {
    /// Centre of mass.
    pub x: Vec3,
    /// Orientation.
    pub q: Rotation,
    /// Linear velocity.
    pub v: Vec3,
    /// Angular velocity (world).
    pub w: Vec3,
}

impl BodyState {
    /// The state of a body.
    pub fn of(b: &RigidBody) -> BodyState {
        BodyState { x: b.x, q: b.q, v: b.v, w: b.w }
    }

    fn apply(&self, b: &mut RigidBody) {
        b.x = self.x;
        b.q = self.q;
        b.v = self.v;
        b.w = self.w;
    }
}

/// What one forward step leaves for the backward pass: only what cannot be recomputed
/// cheaply. The geometry, the pressure operator and its masks are rebuilt from the body
/// states; the pressure needs a solve, so it is stored.
#[derive(Clone, Debug)]
pub struct StepRecord {
    /// Fluid velocity at the start of the step (advection's input).
    pub u: Mac,
    /// Bodies at the start of the step.
    pub bodies: Vec<BodyState>,
    /// Each body's [v; ω] after the pressure solve (the rigid integration's input).
    pub v_after: Vec<[f64; 6]>,
    /// Pressure per liquid cell.
    pub p: Vec<f64>,
    /// Particle φ_L of the step (empty when the surface is frozen: the initial one).
    pub phi: Vec<f64>,
    /// The contact impulse (as a velocity change [Δv; Δω], per dynamic body) the projection
    /// held on each body; zero without contact. The gradient takes it as a constant.
    pub contact_kick: Vec<[f64; 6]>,
    /// Each body's face fractions at the start of the step (a few kB; recomputing them cost
    /// 4% of the backward pass).
    pub body_faces: Vec<fractions::BodyFaces>,
}

/// The recorded forward pass.
#[derive(Clone, Debug, Default)]
pub struct Tape {
    /// One record per step.
    pub steps: Vec<StepRecord>,
}

impl Tape {
    /// Bytes stored per step (mean over the tape).
    pub fn bytes_per_step(&self) -> usize {
        if self.steps.is_empty() {
            return 0;
        }
        let total: usize = self
            .steps
            .iter()
            .map(|s| {
                8 * (s.u.c.iter().map(Vec::len).sum::<usize>() + s.p.len() + s.phi.len())
                    + s.bodies.len() * std::mem::size_of::<BodyState>()
                    + s.v_after.len() * 48
                    + s.contact_kick.len() * 48
                    + s.body_faces
                        .iter()
                        .map(|b| b.faces.iter().map(Vec::len).sum::<usize>() * 16)
                        .sum::<usize>()
            })
            .sum();
        total / self.steps.len()
    }
}

/// The adjoint of one body's state: ∂L/∂x, ∂L/∂q (in the quaternion embedding), ∂L/∂v,
/// ∂L/∂ω.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BodyAdjoint {
    /// ∂L/∂x.
    pub x: Vec3,
    /// ∂L/∂q as a 4-vector.
    pub q: Rotation,
    /// ∂L/∂v.
    pub v: Vec3,
    /// ∂L/∂ω.
    pub w: Vec3,
}

impl BodyAdjoint {
    /// Zero.
    pub fn zero() -> BodyAdjoint {
        BodyAdjoint {
            x: Vec3::ZERO,
            q: Rotation::from_xyzw(0.0, 0.0, 0.0, 0.0),
            v: Vec3::ZERO,
            w: Vec3::ZERO,
        }
    }
}

/// ∂L/∂(state): fluid velocity and bodies.
#[derive(Clone, Debug)]
pub struct AdjointState {
    /// ∂L/∂u.
    pub u: Mac,
    /// Per body.
    pub bodies: Vec<BodyAdjoint>,
}

/// The gradient of a loss with respect to the initial state.
#[derive(Clone, Debug)]
pub struct Gradient {
    /// ∂L/∂u₀ on every face.
    pub u: Mac,
    /// Per body: ∂L/∂v₀, ∂L/∂ω₀, ∂L/∂x₀ and ∂L/∂θ₀ (orientation, in the world-frame tangent
    /// space q → exp(θ)·q).
    pub bodies: Vec<BodyGradient>,
}

/// One body's initial-state gradient.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BodyGradient {
    /// ∂L/∂v₀.
    pub v: Vec3,
    /// ∂L/∂ω₀.
    pub w: Vec3,
    /// ∂L/∂x₀.
    pub x: Vec3,
    /// ∂L/∂θ₀.
    pub q: Vec3,
}

/// Which gradient to compute.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GradientMode {
    /// Everything, including how the geometry depends on body poses.
    Full,
    /// The paper's approximation: J, the face weights, M_S and the rigid face velocities are
    /// taken as independent of the body pose within a step.
    Paper,
}

/// A loss on the final state.
pub trait Loss: Sync {
    /// L(final state).
    fn value(&self, sim: &Simulation) -> f64;
    /// ∂L/∂(final state).
    fn gradient(&self, sim: &Simulation) -> AdjointState;
}

/// Weighted squared distances of one body's final position, orientation and velocity to
/// targets: `wₓ·|x − x*|² + w_q·(1 − (q·q*)²) + w_v·|v − v*|²` (the orientation term is
/// zero at q = ±q*).
#[derive(Clone, Debug, PartialEq)]
pub struct BodyTargetLoss {
    /// Which body.
    pub body: usize,
    /// Target position and weight.
    pub position: Option<(Vec3, f64)>,
    /// Target orientation and weight.
    pub orientation: Option<(Rotation, f64)>,
    /// Target velocity and weight.
    pub velocity: Option<(Vec3, f64)>,
}

impl BodyTargetLoss {
    /// The loss a scene's `[loss]` section describes (None when it has none).
    pub fn from_scene(scene: &crate::experiments::scene::Scene) -> Option<BodyTargetLoss> {
        let l = scene.loss.as_ref()?;
        let body = (0..scene.body.len()).find(|&i| {
            let n = &scene.body[i].name;
            (if n.is_empty() { format!("body{i}") } else { n.clone() }) == l.body
        })?;
        let v3 = crate::math::v3;
        Some(BodyTargetLoss {
            body,
            position: l.position.as_ref().map(|t| (v3(t.target), t.weight)),
            orientation: l.orientation.as_ref().map(|t| {
                let q = t.target;
                (Rotation::from_xyzw(q[1], q[2], q[3], q[0]).normalize(), t.weight)
            }),
            velocity: l.velocity.as_ref().map(|t| (v3(t.target), t.weight)),
        })
    }
}

impl Loss for BodyTargetLoss {
    fn value(&self, sim: &Simulation) -> f64 {
        let b = &sim.bodies[self.body];
        let mut l = 0.0;
        if let Some((t, w)) = self.position {
            l += w * (b.x - t).length_squared();
        }
        if let Some((t, w)) = self.orientation {
            l += w * (1.0 - b.q.dot(t).powi(2));
        }
        if let Some((t, w)) = self.velocity {
            l += w * (b.v - t).length_squared();
        }
        l
    }

    fn gradient(&self, sim: &Simulation) -> AdjointState {
        let mut bodies = vec![BodyAdjoint::zero(); sim.bodies.len()];
        let b = &sim.bodies[self.body];
        let g = &mut bodies[self.body];
        if let Some((t, w)) = self.position {
            g.x = 2.0 * w * (b.x - t);
        }
        if let Some((t, w)) = self.orientation {
            g.q = t * (-2.0 * w * b.q.dot(t));
        }
        if let Some((t, w)) = self.velocity {
            g.v = 2.0 * w * (b.v - t);
        }
        AdjointState { u: Mac::zeros(sim.grid()), bodies }
    }
}

/// What the geometric part of the projection adjoint reads.
struct GeometryInputs<'a> {
    sys: &'a PressureSystem,
    weights: &'a [Vec<f64>; 3],
    phi: &'a [f64],
    static_weights: &'a [Vec<f64>; 3],
    u_hat: &'a Mac,
    p: &'a [f64],
    s: &'a [f64],
    dt: f64,
}

/// ∂L/∂[δx; δθ] of one body through the projection's geometry, for fixed velocities: with
/// the adjoint solve's s and the adjoint V′ of the body's velocity after the solve,
/// `dL = sᵀ(δb − δA·p) + V′·(δMi·J p + Mi·δJ p)` where b = −F(w)·û − Jᵀ v̂,
/// A = S(w) + Jᵀ Mi J and Mi = Δt·M⁻¹. δw = −δβ on faces the clamp leaves alone, δJ comes
/// from δβ and from the torque arms (δr = −δx), δMi from the rotation of the inertia.
fn geometry_gradient(
    g: &GeometryInputs<'_>,
    body: &RigidBody,
    faces: &[Vec<(usize, crate::math::dual::Dual<6>)>; 3],
    coupling: usize,
    v_hat: &[f64; 6],
    adj_v: &[f64; 6],
) -> [f64; 6] {
    let sys = g.sys;
    let grid = sys.grid;
    let area = grid.dx * grid.dx;
    let scale = sys.params.dt * grid.dx / sys.params.density;
    let row_val = |c: Option<usize>, x: &[f64]| match c.map(|c| sys.row_of_cell[c]) {
        Some(r) if r != crate::geometry::grid::NONE => x[r as usize],
        _ => 0.0,
    };
    let bc = &sys.bodies[coupling];
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
            let raw = g.static_weights[axis][f] - beta.v;
            if raw > 0.0 && raw < 1.0 && g.weights[axis][f] > 0.0 {
                let uh = g.u_hat.c[axis][f];
                let flux = area * uh * (row_val(m, g.s) - row_val(pl, g.s));
                let stencil = match sys.face_gradient(axis, f, g.weights, g.phi) {
                    Some(fg) => {
                        // θ·(g·s)(g·p), with g carrying 1/θ on a ghost-fluid face.
                        let theta = if fg.cp == 0.0 {
                            1.0 / fg.cm
                        } else if fg.cm == 0.0 {
                            1.0 / fg.cp
                        } else {
                            1.0
                        };
                        scale * theta * fg.apply(g.s) * fg.apply(g.p)
                    }
                    None => 0.0,
                };
                // sᵀδb ∋ −sᵀ δF û = −Σ dx²·δw·û·(s_m − s_p), δw = −δβ; −sᵀ δS p likewise.
                for k in 0..6 {
                    out[k] += beta.d[k] * (flux + stencil);
                }
            }
            // δJ columns on the two cells beside the face.
            let r = lat.position(ijk[0], ijk[1], ijk[2]) - body.x;
            let t = r.cross(e);
            let col = [e.x, e.y, e.z, t.x, t.y, t.z];
            let (sm, sp) = (row_val(m, g.s), row_val(pl, g.s));
            let (pm, pp) = (row_val(m, g.p), row_val(pl, g.p));
            let (ns, np) = (area * (sm - sp), area * (pm - pp));
            for k in 0..6 {
                for c in 0..6 {
                    djs[k][c] += ns * beta.d[k] * col[c];
                    djp[k][c] += np * beta.d[k] * col[c];
                }
                if k < 3 {
                    // δr = −e_k: δ(r × e) = −e_k × e.
                    let dt_ = -crate::math::unit(k).cross(e);
                    for c in 0..3 {
                        djs[k][3 + c] += ns * beta.v * crate::math::comp(dt_, c);
                        djp[k][3 + c] += np * beta.v * crate::math::comp(dt_, c);
                    }
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
        if k >= 3 {
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

/// Runs the backward pass over `tape`, which `initial` (the simulation as it was before
/// the taped steps) recorded, from the adjoint of the final state, and returns the gradient
/// with respect to `initial`'s state.
pub fn backward(
    initial: &Simulation,
    tape: &Tape,
    final_adjoint: AdjointState,
    mode: GradientMode,
) -> Result<Gradient> {
    let adj = backward_adjoint(initial, tape, final_adjoint, mode)?;
    Ok(to_gradient(initial, adj))
}

/// The initial-state gradient of an adjoint state (orientations into the tangent space).
fn to_gradient(initial: &Simulation, adj: AdjointState) -> Gradient {
    let bodies = adj
        .bodies
        .iter()
        .zip(&initial.bodies)
        .map(|(a, b)| BodyGradient { v: a.v, w: a.w, x: a.x, q: quat_tangent_gradient(b.q, a.q) })
        .collect();
    Gradient { u: adj.u, bodies }
}

/// [`backward`] without the final conversion: the adjoint of `initial`'s state.
pub fn backward_adjoint(
    initial: &Simulation,
    tape: &Tape,
    final_adjoint: AdjointState,
    mode: GradientMode,
) -> Result<AdjointState> {
    crate::geometry::grid::on_pool(|| backward_adjoint_on_pool(initial, tape, final_adjoint, mode))
}

fn backward_adjoint_on_pool(
    initial: &Simulation,
    tape: &Tape,
    final_adjoint: AdjointState,
    mode: GradientMode,
) -> Result<AdjointState> {
    let scene = initial.scene();
    let through_contact = scene.optimize.as_ref().is_some_and(|o| o.through_contact);
    if scene.contact.enabled && !initial.bodies.is_empty() && !through_contact {
        return Err(Error::InvalidScene {
            origin: scene.name.clone(),
            message: "gradients through rapier contact are not available: set [contact] \
                      enabled = false for the backward pass"
                .into(),
        });
    }
    if scene.solver.coupling != crate::experiments::scene::Coupling::Monolithic {
        return Err(Error::InvalidScene {
            origin: scene.name.clone(),
            message: "gradients are only available for solver.coupling = \"monolithic\"".into(),
        });
    }
    let grid = *initial.grid();
    let dt = scene.time.dt;
    let solver = &scene.solver;
    let params = PressureParams { dt, density: scene.fluid.density, theta_min: solver.theta_min };
    let frozen_phi = initial.particle_phi();
    let mut bodies: Vec<RigidBody> = initial.bodies.clone();
    let mut adj = final_adjoint;

    for (t, rec) in tape.steps.iter().enumerate().rev() {
        // Rebuild the step's geometry and operator from the recorded body states.
        for (b, s) in bodies.iter_mut().zip(&rec.bodies) {
            s.apply(b);
        }
        let geo = initial.geometry_with(&bodies, rec.body_faces.clone());
        let mut phi = if rec.phi.is_empty() { frozen_phi.clone() } else { rec.phi.clone() };
        surface::extend_into_solids(&mut phi, &grid, &geo.centre_in_solid);
        let mut sys = PressureSystem::build(&grid, &phi, &geo.weights, params);
        let dynamic: Vec<usize> = (0..bodies.len()).filter(|&i| bodies[i].dynamic).collect();
        for &i in &dynamic {
            let jac = fractions::body_jacobian(&grid, &geo.body_faces[i], bodies[i].x);
            sys.bodies.push(BodyCoupling::new(&sys.row_of_cell, &jac, dt_minv(&bodies[i], dt)));
        }
        // The faces the step reads after advection, and the projection's (valid) faces.
        let needed = crate::stages::advect::needed_faces(&grid, &phi, &geo.body_faces);
        let valid0: [Vec<u8>; 3] = [0, 1, 2].map(|a| {
            let mut v = vec![0u8; grid.faces(a).len()];
            for pf in &sys.faces[a] {
                v[pf.face as usize] = 1;
            }
            v
        });

        // 6ᵀ: rigid integration. The body's velocity after the step is v' itself.
        let mut vbar: Vec<[f64; 6]> = vec![[0.0; 6]; bodies.len()];
        let mut new_bodies = vec![BodyAdjoint::zero(); bodies.len()];
        for (i, b) in bodies.iter().enumerate() {
            let a = &adj.bodies[i];
            if !b.dynamic {
                new_bodies[i].x = a.x;
                new_bodies[i].q = a.q;
                continue;
            }
            let va = rec.v_after[i];
            let w_after = Vec3::new(va[3], va[4], va[5]);
            let (qbar, wbar) = quat_step_adjoint(rec.bodies[i].q, w_after, dt, a.q);
            new_bodies[i].x = a.x;
            new_bodies[i].q = qbar;
            let vb = a.v + dt * a.x;
            let wb = a.w + wbar;
            vbar[i] = [vb.x, vb.y, vb.z, wb.x, wb.y, wb.z];
        }

        // The fractions' derivatives along each body's pose (full gradient only).
        let dual_faces: Vec<_> = if mode == GradientMode::Full {
            bodies
                .iter()
                .map(|b| {
                    fractions::body_faces_generic(
                        &grid,
                        b.bounds(),
                        |p| b.sdf_pose_dual(p),
                        Some(b.volume()),
                    )
                })
                .collect()
        } else {
            Vec::new()
        };
        // Recompute the step's intermediate fields: û (advected, with gravity) and the
        // corrected field before the bodies' velocities are set. The backward pass reads them
        // only on the faces the bodies cover, so only those are advected.
        let mut at_bodies = crate::stages::advect::needed_faces(&grid, &[], &geo.body_faces);
        for faces in &dual_faces {
            for (a, m) in at_bodies.iter_mut().enumerate() {
                for (f, _) in &faces[a] {
                    m[*f] = true;
                }
            }
        }
        let mut u_hat = crate::stages::advect::advect(&rec.u, &grid, dt, Some(&at_bodies));
        crate::stages::forces::add_gravity(&mut u_hat, scene.fluid.gravity, dt);
        let mut u_corr = u_hat.clone();
        sys.update_velocity(&rec.p, &mut u_corr);
        let mut valid0 = valid0;
        crate::stages::extrapolate::mark_body_faces(&mut valid0, &geo.body_faces);
        let mut pose_grad = vec![[0.0f64; 6]; bodies.len()];

        // 5ᵀ: walls and static solids, extrapolation layers, then the bodies' velocities on
        // the faces they cover.
        let mut ubar = std::mem::replace(&mut adj.u, Mac::zeros(&grid));
        correct_velocity_adjoint(
            &mut ubar,
            &valid0,
            &initial.statics().weights,
            &grid,
            solver.extrapolation_layers,
        );
        let mut after = bodies.clone();
        for (b, va) in after.iter_mut().zip(&rec.v_after) {
            b.v = Vec3::new(va[0], va[1], va[2]);
            b.w = Vec3::new(va[3], va[4], va[5]);
        }
        let bva = crate::stages::extrapolate::apply_body_velocities_adjoint(
            &mut ubar,
            &u_corr,
            &after,
            &geo.body_faces,
            &geo.weights,
            &grid,
        );
        for (i, r) in bva.iter().enumerate() {
            if !bodies[i].dynamic {
                continue;
            }
            for d in 0..6 {
                vbar[i][d] += r.vel[d];
            }
            if mode == GradientMode::Full {
                new_bodies[i].x += r.x;
                // ∂L/∂β_f · ∂β_f/∂pose on the faces the body covers in part.
                let lookup: std::collections::HashMap<(usize, usize), [f64; 6]> = (0..3)
                    .flat_map(|a| dual_faces[i][a].iter().map(move |(f, b)| ((a, *f), b.d)))
                    .collect();
                for &(a, f, c) in &r.dbeta {
                    if let Some(d) = lookup.get(&(a, f)) {
                        for k in 0..6 {
                            pose_grad[i][k] += c * d[k];
                        }
                    }
                }
            }
        }

        // 4ᵀ: projection.
        let adj_v: Vec<[f64; 6]> = dynamic.iter().map(|&i| vbar[i]).collect();
        let (uhat, vhat, _s, stats) = sys.projection_adjoint(&ubar, &adj_v, solver);
        if !stats.converged {
            return Err(Error::NotConverged {
                step: t + 1,
                iterations: stats.iterations,
                residual: stats.relative_residual,
                tolerance: solver.tolerance,
            });
        }
        for (k, &i) in dynamic.iter().enumerate() {
            new_bodies[i].v = Vec3::new(vhat[k][0], vhat[k][1], vhat[k][2]);
            new_bodies[i].w = Vec3::new(vhat[k][3], vhat[k][4], vhat[k][5]);
        }
        if mode == GradientMode::Full {
            let g = crate::math::v3(scene.fluid.gravity);
            let geo_in = GeometryInputs {
                sys: &sys,
                weights: &geo.weights,
                phi: &phi,
                static_weights: &initial.statics().weights,
                u_hat: &u_hat,
                p: &rec.p,
                s: &_s,
                dt,
            };
            for (k, &i) in dynamic.iter().enumerate() {
                let b = &bodies[i];
                let kick = rec.contact_kick.get(k).copied().unwrap_or([0.0; 6]);
                let vh0 =
                    [b.v.x + dt * g.x, b.v.y + dt * g.y, b.v.z + dt * g.z, b.w.x, b.w.y, b.w.z];
                let vh: [f64; 6] = std::array::from_fn(|d| vh0[d] + kick[d]);
                let gr = geometry_gradient(&geo_in, b, &dual_faces[i], k, &vh, &adj_v[k]);
                for d in 0..6 {
                    pose_grad[i][d] += gr[d];
                }
            }
            for &i in &dynamic {
                let gr = pose_grad[i];
                new_bodies[i].x += Vec3::new(gr[0], gr[1], gr[2]);
                let gq = crate::geometry::body::quat_from_tangent_gradient(
                    bodies[i].q,
                    Vec3::new(gr[3], gr[4], gr[5]),
                );
                new_bodies[i].q = Rotation::from_xyzw(
                    new_bodies[i].q.x + gq.x,
                    new_bodies[i].q.y + gq.y,
                    new_bodies[i].q.z + gq.z,
                    new_bodies[i].q.w + gq.w,
                );
            }
        }

        // 2ᵀ: gravity is the identity. 1ᵀ: advection.
        let u0 = advect_adjoint(&rec.u, &uhat, &grid, dt, Some(&needed));
        adj = AdjointState { u: u0, bodies: new_bodies };
    }
    Ok(adj)
}

/// A loss and its gradient, with what they cost.
#[derive(Clone, Debug)]
pub struct GradientRun {
    /// L at the final state.
    pub loss: f64,
    /// ∂L/∂(initial state).
    pub gradient: Gradient,
    /// The final state.
    pub final_state: Simulation,
    /// Tape bytes per step (of the segment held at once, with checkpointing).
    pub tape_bytes_per_step: usize,
    /// Wall time of the forward pass, s.
    pub forward_seconds: f64,
    /// Wall time of the backward pass (including re-running segments), s.
    pub backward_seconds: f64,
}

/// Runs `steps` steps from `initial`, evaluates `loss` and its gradient with respect to the
/// initial state. With `checkpoint_every = Some(k)`, the forward pass keeps a snapshot every
/// k steps instead of the whole tape, and the backward pass re-runs one segment at a time
/// (√N segments keep memory at O(√N) steps); the forward map is deterministic, so the
/// gradient is bit-identical to the one without checkpoints.
pub fn value_and_gradient(
    initial: &Simulation,
    steps: usize,
    loss: &dyn Loss,
    mode: GradientMode,
    checkpoint_every: Option<usize>,
) -> Result<GradientRun> {
    crate::geometry::grid::on_pool(|| {
        value_and_gradient_on_pool(initial, steps, loss, mode, checkpoint_every)
    })
}

fn value_and_gradient_on_pool(
    initial: &Simulation,
    steps: usize,
    loss: &dyn Loss,
    mode: GradientMode,
    checkpoint_every: Option<usize>,
) -> Result<GradientRun> {
    let clock = std::time::Instant::now();
    let seg = checkpoint_every.unwrap_or(steps).max(1);
    let mut sim = initial.clone();
    let mut snapshots = Vec::new();
    let mut full_tape = Tape::default();
    for n in 0..steps {
        if checkpoint_every.is_some() {
            if n % seg == 0 {
                snapshots.push(sim.clone());
            }
            sim.step()?;
        } else {
            sim.step_taped(&mut full_tape)?;
        }
    }
    let forward_seconds = clock.elapsed().as_secs_f64();
    let clock = std::time::Instant::now();
    let value = loss.value(&sim);
    let mut adj = loss.gradient(&sim);
    let mut bytes = full_tape.bytes_per_step();
    if checkpoint_every.is_none() {
        adj = backward_adjoint(initial, &full_tape, adj, mode)?;
    } else {
        for (k, snap) in snapshots.iter().enumerate().rev() {
            let len = seg.min(steps - k * seg);
            let mut s = snap.clone();
            let mut tape = Tape::default();
            for _ in 0..len {
                s.step_taped(&mut tape)?;
            }
            bytes = bytes.max(tape.bytes_per_step());
            adj = backward_adjoint(snap, &tape, adj, mode)?;
        }
    }
    let gradient = to_gradient(initial, adj);
    Ok(GradientRun {
        loss: value,
        gradient,
        final_state: sim,
        tape_bytes_per_step: bytes,
        forward_seconds,
        backward_seconds: clock.elapsed().as_secs_f64(),
    })
}

/// One initial body parameter: v, ω, x or the orientation (as a world-frame rotation).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BodyParam {
    /// Linear velocity component.
    V(usize),
    /// Angular velocity component.
    W(usize),
    /// Position component.
    X(usize),
    /// Orientation: a rotation about world axis k.
    Q(usize),
}

impl BodyParam {
    /// All twelve, in order v, ω, x, q.
    pub fn all() -> [BodyParam; 12] {
        std::array::from_fn(|k| {
            let d = k % 3;
            match k / 3 {
                0 => BodyParam::V(d),
                1 => BodyParam::W(d),
                2 => BodyParam::X(d),
                _ => BodyParam::Q(d),
            }
        })
    }

    /// `v[0]`, `w[2]`, `q[1]`...
    pub fn name(&self) -> String {
        match self {
            BodyParam::V(d) => format!("v[{d}]"),
            BodyParam::W(d) => format!("w[{d}]"),
            BodyParam::X(d) => format!("x[{d}]"),
            BodyParam::Q(d) => format!("q[{d}]"),
        }
    }

    /// The gradient's component for this parameter.
    pub fn of(&self, g: &BodyGradient) -> f64 {
        match *self {
            BodyParam::V(d) => g.v.to_array()[d],
            BodyParam::W(d) => g.w.to_array()[d],
            BodyParam::X(d) => g.x.to_array()[d],
            BodyParam::Q(d) => g.q.to_array()[d],
        }
    }

    /// Moves body `b` of `sim` by `h` along this parameter.
    pub fn perturb(&self, sim: &mut Simulation, b: usize, h: f64) {
        let body = &mut sim.bodies[b];
        match *self {
            BodyParam::V(d) => body.v += h * crate::math::unit(d),
            BodyParam::W(d) => body.w += h * crate::math::unit(d),
            BodyParam::X(d) => body.x += h * crate::math::unit(d),
            BodyParam::Q(d) => {
                body.q = (Rotation::from_scaled_axis(h * crate::math::unit(d)) * body.q).normalize()
            }
        }
    }
}

/// Central difference `(L(p + ε) − L(p − ε)) / 2ε` of a `steps`-step run from `initial`
/// along one body parameter.
pub fn central_difference(
    initial: &Simulation,
    steps: usize,
    loss: &dyn Loss,
    body: usize,
    param: BodyParam,
    eps: f64,
) -> Result<f64> {
    let at = |h: f64| -> Result<f64> {
        let mut s = initial.clone();
        param.perturb(&mut s, body, h);
        for _ in 0..steps {
            s.step()?;
        }
        Ok(loss.value(&s))
    };
    Ok((at(eps)? - at(-eps)?) / (2.0 * eps))
}
