//! The backward pass (the paper's Algorithm 3): walks the taped steps in reverse and, per
//! step, rebuilds the step's system with the forward pass's own
//! [`StepSystem::assemble`], then runs the stages' adjoints in the mirrored order, each the
//! exact transpose of its forward linearisation:
//!
//! 6ᵀ rigid integration (quaternion product and normalisation), 5ᵀ velocity correction
//! (rigid faces, closed faces, extrapolation layers), 4ᵀ projection (one more solve with the
//! same operator, the pose derivative of its geometry, and ∂L/∂φ_L through the ghost-fluid
//! θ), 2ᵀ forces (the identity, and the torque's pose derivative), 1ᵀ advection
//! ((W + ∂W/∂u·u)ᵀ), 0ᵀ the marker particles (density projection, push-outs, advection),
//! whose positions are part of the state: the adjoint carries ∂L/∂(particles) from step to
//! step.
//!
//! [`SurfaceGradient::Live`] (the default) differentiates the surface's motion, so the
//! gradient is that of the forward map wherever no cell or face changes kind;
//! [`SurfaceGradient::Frozen`] holds the surface fixed in the backward pass, as the paper did
//! (exact only when `solver.freeze_surface` holds it fixed in the forward pass too).
//! [`GradientMode::Full`] carries the dependence of the geometry on the body poses (face
//! fractions, J, the world inertia, the rigid velocity set inside bodies, the push-outs);
//! [`GradientMode::Paper`] drops it, as the paper does.

use super::loss::{AdjointState, BodyAdjoint, BodyGradient, Gradient};
use crate::error::{Error, GradientError, Result, Solve};
use crate::geometry::body::{
    carry_angular_momentum_adjoint, quat_step, quat_step_adjoint, Motion, RigidBody,
};
use crate::geometry::grid::Mac;
use crate::math::dual::Dual;
use crate::math::pool::run_spread;
use crate::math::so3;
use crate::math::{Rotation, Vec3};
use crate::stages::advect::{advect_adjoint_into, needed_faces};
use crate::stages::band::Band;
use crate::stages::density::{DensityInputs, DensityProjection};
use crate::stages::extrapolate::correct_with_bodies_adjoint;
use crate::stages::forces::{body_velocity_pose_adjoint, load_velocity};
use crate::stages::pressure::{
    kinematic_pose_adjoint, projection_pose_adjoint, Coupling, PoseAdjointInputs,
};
use crate::stages::surface;
use crate::world::step::{predicted_velocity, Geometry};
use crate::world::tape::ParticleRecord;
use crate::world::{Simulation, StepRecord, StepSystem, Tape};
use std::time::Instant;

/// Which gradient to compute.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum GradientMode {
    /// Everything, including how the geometry depends on body poses.
    #[default]
    Full,
    /// The paper's approximation: J, the face weights, M_S and the rigid face velocities are
    /// taken as independent of the body pose within a step.
    Paper,
}

/// Whether the backward pass follows the liquid surface.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SurfaceGradient {
    /// The surface's motion is differentiated: the marker particles' advection (with its
    /// sub-steps and the push out of solids and bodies), the density projection, φ_L from the
    /// particles and the ghost-fluid θ it sets in the pressure solve. Exact for the forward
    /// map wherever no cell or face changes kind.
    #[default]
    Live,
    /// The paper's approximation: the surface is taken as fixed within the backward pass
    /// (the particles' dependence on the state is dropped). Exact only when the forward pass
    /// holds the surface fixed too (`solver.freeze_surface`); cheaper.
    Frozen,
}

impl GradientMode {
    /// Both, in order.
    pub const ALL: [GradientMode; 2] = [GradientMode::Full, GradientMode::Paper];

    /// `"full"` or `"paper"`: the name the Python package and error messages use.
    pub fn name(self) -> &'static str {
        match self {
            GradientMode::Full => "full",
            GradientMode::Paper => "paper",
        }
    }
}

impl std::str::FromStr for GradientMode {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<GradientMode, String> {
        GradientMode::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| format!("mode: \"full\" or \"paper\", not {s:?}"))
    }
}

impl SurfaceGradient {
    /// Both, in order.
    pub const ALL: [SurfaceGradient; 2] = [SurfaceGradient::Live, SurfaceGradient::Frozen];

    /// `"live"` or `"frozen"`: the name the Python package and scene files use.
    pub fn name(self) -> &'static str {
        match self {
            SurfaceGradient::Live => "live",
            SurfaceGradient::Frozen => "frozen",
        }
    }
}

impl std::str::FromStr for SurfaceGradient {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<SurfaceGradient, String> {
        SurfaceGradient::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| format!("surface: \"live\" or \"frozen\", not {s:?}"))
    }
}

/// How the backward pass treats what it cannot differentiate.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GradientOptions {
    /// Full or the paper's approximation.
    pub mode: GradientMode,
    /// The moving surface, or the paper's fixed one.
    pub surface: SurfaceGradient,
    /// Accept taped steps in which rapier contact acted, taking contact as free flight (its
    /// impulse a constant): an approximation, so it must be asked for. Without it such a tape
    /// is an error.
    pub through_contact: bool,
}

impl GradientOptions {
    /// The options for `mode`, contact not accepted.
    pub fn new(mode: GradientMode) -> GradientOptions {
        GradientOptions { mode, ..Default::default() }
    }
}

/// Wall time of each stage's adjoint over a backward pass, in seconds (summed over steps).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct AdjointSeconds {
    /// Rebuilding the steps' systems ([`StepSystem::assemble`]) and the pose derivatives of
    /// the fractions.
    pub assemble: f64,
    /// 6ᵀ.
    pub rigid: f64,
    /// 5ᵀ, with the intermediate fields it reads.
    pub correct_velocity: f64,
    /// 4ᵀ: the adjoint solve and the pose part.
    pub pressure: f64,
    /// 1ᵀ.
    pub advect_velocity: f64,
    /// 0ᵀ: the marker particles (advection, push-outs, density projection, φ_L).
    pub advect_particles: f64,
}

impl std::ops::AddAssign for AdjointSeconds {
    fn add_assign(&mut self, o: AdjointSeconds) {
        self.assemble += o.assemble;
        self.rigid += o.rigid;
        self.correct_velocity += o.correct_velocity;
        self.pressure += o.pressure;
        self.advect_velocity += o.advect_velocity;
        self.advect_particles += o.advect_particles;
    }
}

/// Whether `initial` and `tape` can be differentiated with `options`: monolithic coupling,
/// contact only when the options accept it (see [`check_settings`]), and the same bodies in
/// every taped step.
pub fn check_differentiable(
    initial: &Simulation,
    tape: &Tape,
    options: &GradientOptions,
) -> Result<()> {
    check_settings(initial, tape.through_contact(), options)?;
    for (t, rec) in tape.steps.iter().enumerate() {
        if rec.bodies.len() != initial.bodies().len() {
            return Err(GradientError::BodiesChanged {
                step: t + 1,
                taped: rec.bodies.len(),
                initial: initial.bodies().len(),
            }
            .into());
        }
    }
    Ok(())
}

/// Whether steps from `initial`, in which rapier contact acted if `through_contact`, can be
/// differentiated with `options`: monolithic coupling, and contact only when the options
/// accept it. The one place this rule is written.
pub fn check_settings(
    initial: &Simulation,
    through_contact: bool,
    options: &GradientOptions,
) -> Result<()> {
    if initial.settings().solver.coupling != Coupling::Monolithic {
        return Err(GradientError::WeakCoupling.into());
    }
    if through_contact && !options.through_contact {
        return Err(GradientError::ThroughContact.into());
    }
    Ok(())
}

/// Runs the backward pass over `tape`, which `initial` (the simulation as it was before
/// the taped steps) recorded, from the adjoint of the final state, and returns the gradient
/// with respect to `initial`'s state.
pub fn backward(
    initial: &Simulation,
    tape: &Tape,
    final_adjoint: AdjointState,
    options: &GradientOptions,
) -> Result<Gradient> {
    let (adj, _) = backward_adjoint(initial, tape, final_adjoint, options)?;
    Ok(to_gradient(initial, adj))
}

/// The initial-state gradient of an adjoint state (orientations into the tangent space).
pub fn to_gradient(initial: &Simulation, adj: AdjointState) -> Gradient {
    let bodies = adj
        .bodies
        .iter()
        .zip(initial.bodies())
        .enumerate()
        .map(|(i, (a, b))| BodyGradient {
            v: a.v,
            w: a.w,
            x: a.x,
            q: so3::tangent_gradient(b.q, a.q),
            mass: adj.mass.get(i).copied().unwrap_or(0.0),
        })
        .collect();
    Gradient { u: adj.u, bodies, particles: adj.particles }
}

/// [`backward`] without the final conversion: the adjoint of `initial`'s state, and what
/// each stage's adjoint cost.
pub fn backward_adjoint(
    initial: &Simulation,
    tape: &Tape,
    final_adjoint: AdjointState,
    options: &GradientOptions,
) -> Result<(AdjointState, AdjointSeconds)> {
    backward_adjoint_hooked(initial, tape, final_adjoint, options, 0, &mut |_, _| {})
}

/// [`backward_adjoint`] that hands the adjoint at every boundary between steps to
/// `at_boundary` as the sweep passes it: after the adjoint of the tape's step t + 1 (counted
/// from 0), `at_boundary(first + t, adj)` with `adj` the adjoint of the state that step
/// started from. A trajectory loss adds its terms there, and a per-step action reads its
/// gradient there ([`super::control`]). The boundary after the tape's last step is the
/// caller's (it hands in `final_adjoint`).
pub fn backward_adjoint_hooked(
    initial: &Simulation,
    tape: &Tape,
    final_adjoint: AdjointState,
    options: &GradientOptions,
    first: usize,
    at_boundary: &mut (dyn FnMut(usize, &mut AdjointState) + Send),
) -> Result<(AdjointState, AdjointSeconds)> {
    check_differentiable(initial, tape, options)?;
    run_spread(initial.spread(), || {
        let mut times = AdjointSeconds::default();
        let mut adj = final_adjoint;
        for (t, rec) in tape.steps.iter().enumerate().rev() {
            adj = step_adjoint(initial, rec, adj, options, first + t + 1, &mut times)?;
            at_boundary(first + t, &mut adj);
        }
        Ok((adj, times))
    })
}

/// The bodies whose pose a step's adjoint differentiates: the coupled ones and the
/// kinematic ones (a control moves those), in order.
fn posed(sys: &StepSystem) -> Vec<usize> {
    let mut out: Vec<usize> =
        sys.coupled.iter().copied().chain(sys.kinematic.iter().map(|k| k.0)).collect();
    out.sort_unstable();
    out
}

/// a + b, component-wise (two adjoints in the quaternion embedding).
fn add_quat(a: Rotation, b: Rotation) -> Rotation {
    Rotation::from_xyzw(a.x + b.x, a.y + b.y, a.z + b.z, a.w + b.w)
}

/// The bodies of `initial` in the states and with the loads `rec` recorded at the start of
/// its step.
fn bodies_at(initial: &Simulation, rec: &StepRecord) -> Vec<RigidBody> {
    let mut bodies = initial.bodies().to_vec();
    for ((b, s), load) in bodies.iter_mut().zip(&rec.bodies).zip(&rec.loads) {
        b.set_state(s);
        b.set_load(load);
    }
    bodies
}

/// The adjoint of one step: from the adjoint of the state after step `step` (recorded as
/// `rec`), the adjoint of the state before it.
fn step_adjoint(
    initial: &Simulation,
    rec: &StepRecord,
    adj: AdjointState,
    options: &GradientOptions,
    step: usize,
    times: &mut AdjointSeconds,
) -> Result<AdjointState> {
    let mode = options.mode;
    let live = options.surface == SurfaceGradient::Live;
    let grid = *initial.grid();
    let dt = initial.dt();
    let settings = initial.settings();
    let mut clock = Instant::now();
    let mut lap = |slot: &mut f64| {
        let now = Instant::now();
        *slot += (now - clock).as_secs_f64();
        clock = now;
    };

    // The step's system, assembled as the forward step assembled it.
    let bodies = bodies_at(initial, rec);
    let geometry = initial.geometry_with(&bodies, rec.body_faces.clone());
    let phi = if rec.phi.is_empty() { initial.particle_phi() } else { rec.phi.clone() };
    let live_surface = live && rec.particles.is_some();
    let memory = initial.spare().systems().take();
    let sys = StepSystem::assemble(&grid, &bodies, geometry, phi, initial.step_params(dt), memory);
    // The fractions' derivatives along each body's pose (full gradient only).
    let dual_faces: Vec<[Vec<(usize, Dual<6>)>; 3]> = if mode == GradientMode::Full {
        bodies.iter().map(|b| b.face_fractions_dual(&grid)).collect()
    } else {
        Vec::new()
    };
    lap(&mut times.assemble);

    // 6ᵀ: rigid integration. The body's velocity after the step is v' itself.
    let mut vbar: Vec<[f64; 6]> = vec![[0.0; 6]; bodies.len()];
    let mut out = vec![BodyAdjoint::zero(); bodies.len()];
    for (i, b) in bodies.iter().enumerate() {
        let a = &adj.bodies[i];
        out[i].x = a.x;
        out[i].q = a.q;
        if !b.motion.integrated_here() {
            // Held still, or moved by the caller: its pose after the step is its pose before.
            vbar[i] = [a.v.x, a.v.y, a.v.z, a.w.x, a.w.y, a.w.z];
            continue;
        }
        let va = rec.v_after[i];
        let (q0, w_after) = (rec.bodies[i].q, Vec3::new(va[3], va[4], va[5]));
        let q1 = quat_step(q0, w_after, dt);
        // A dynamic body carries its angular momentum to the new orientation.
        let (mut qbar1, mut w_carry, mut q0_carry) =
            (a.q, a.w, Rotation::from_xyzw(0.0, 0.0, 0.0, 0.0));
        if b.motion == Motion::Dynamic {
            let (t0, t1, wb) =
                carry_angular_momentum_adjoint(&b.local_inertia, q0, q1, w_after, a.w);
            qbar1 = add_quat(a.q, so3::from_tangent_gradient(q1, t1));
            q0_carry = so3::from_tangent_gradient(q0, t0);
            w_carry = wb;
        }
        let (qbar, wbar) = quat_step_adjoint(q0, w_after, dt, qbar1);
        out[i].q = add_quat(qbar, q0_carry);
        let vb = a.v + dt * a.x;
        let wb = w_carry + wbar;
        vbar[i] = [vb.x, vb.y, vb.z, wb.x, wb.y, wb.z];
    }
    lap(&mut times.rigid);

    // The intermediate fields 5ᵀ and 4ᵀ read: û (advected, with gravity) and the field after
    // the pressure update, only on the faces the bodies cover (where they are read).
    let mut at_bodies = needed_faces(&grid, &[], &sys.geometry.body_faces);
    for faces in &dual_faces {
        for (a, m) in at_bodies.iter_mut().enumerate() {
            for (f, _) in &faces[a] {
                m[*f] = true;
            }
        }
    }
    let out_field = initial.spare().velocity(&grid);
    let gravity = settings.fluid.gravity;
    let u_hat = predicted_velocity(&rec.u, &grid, dt, gravity, &at_bodies, out_field);
    let u_corr = |a: usize, f: usize| u_hat.c[a][f] - sys.pressure.velocity_update_at(a, f, &rec.p);

    // 5ᵀ: the bodies' part on faces in air, extrapolation layers and walls, the bodies' part
    // on the projected and closed faces.
    let mut ubar = adj.u;
    let mut after = bodies.clone();
    for (b, va) in after.iter_mut().zip(&rec.v_after) {
        b.v = Vec3::new(va[0], va[1], va[2]);
        b.w = Vec3::new(va[3], va[4], va[5]);
    }
    let bva = correct_with_bodies_adjoint(
        &mut ubar,
        u_corr,
        &rec.air_body_faces,
        &sys.projected_mask(),
        &after,
        &sys.geometry.body_faces,
        &sys.geometry.weights,
        &initial.statics().weights,
        &grid,
        settings.solver.extrapolation_layers,
    );
    let mut pose_grad = vec![[0.0f64; 6]; bodies.len()];
    for (i, r) in bva.iter().enumerate() {
        // A fixed body's pose and velocity are constants; a kinematic one's are the
        // prescribed motion's (a control's).
        if !(bodies[i].moves() || bodies[i].motion == Motion::Kinematic) {
            continue;
        }
        for d in 0..6 {
            vbar[i][d] += r.vel[d];
        }
        if mode == GradientMode::Full {
            out[i].x += r.x;
            for d in 0..3 {
                pose_grad[i][3 + d] += crate::math::comp(r.q, d);
            }
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
    lap(&mut times.correct_velocity);

    // 4ᵀ: projection.
    let adj_v: Vec<[f64; 6]> = sys.coupled.iter().map(|&i| vbar[i]).collect();
    let how = settings.solver.linear();
    let (s, stats) = sys.pressure.adjoint_solve(&ubar, &adj_v, &how);
    // The surface's part: ∂L/∂φ_L through the ghost-fluid θ, carried back out of the solids
    // to the cells the extension read.
    let mut phi_bar = live_surface
        .then(|| sys.pressure.phi_adjoint(&sys.phi, &sys.geometry.weights, &s, &rec.p, &ubar));
    if !stats.converged {
        return Err(Error::NotConverged {
            solve: Solve::PressureAdjoint,
            step,
            iterations: stats.iterations,
            residual: stats.relative_residual,
            tolerance: settings.solver.tolerance,
        });
    }
    // ū before the projection, in place: ū − Fᵀs; the bodies' v̄ − J·s.
    let mut uhat_bar = ubar;
    sys.pressure.subtract_fluid_flux_adjoint(&s, &sys.geometry.weights, &mut uhat_bar);
    let mut vhat_bar = sys.pressure.body_velocity_adjoint(&adj_v, &s);
    // The liquid a thin body carries: V_e = M_e⁻¹·(M·V̂ + Σ m_f·û_f·a_f) back to V̂ and û,
    // and through its masses' liquid fractions to φ_L. y = M_e⁻¹·V̄_e per coupled body.
    let v_e = sys.entrained_velocities(&rec.v_hat, &u_hat);
    let mut ys = vec![[0.0; 6]; sys.coupled.len()];
    for (k, ent) in sys.entrained.iter().enumerate().filter(|(_, e)| !e.is_empty()) {
        let (vb, y) = ent.velocity_adjoint(&vhat_bar[k], &mut uhat_bar);
        vhat_bar[k] = vb;
        ys[k] = y;
        if let Some(g) = phi_bar.as_mut() {
            let v_new = &rec.v_after[sys.coupled[k]];
            ent.phi_adjoint(&y, v_new, &u_hat, &sys.phi, settings.solver.theta_min, g);
        }
    }
    let phi_bar = phi_bar.map(|mut g| {
        sys.extension.transpose(&mut g);
        g
    });
    for (k, &i) in sys.coupled.iter().enumerate() {
        out[i].v = Vec3::new(vhat_bar[k][0], vhat_bar[k][1], vhat_bar[k][2]);
        out[i].w = Vec3::new(vhat_bar[k][3], vhat_bar[k][4], vhat_bar[k][5]);
    }
    // The masses, the inertias scaling with them (M → s·M): 4ᵀ gives −V̂̄·(V′ − V̂)/m (the
    // pressure's impulse M·(V′ − V̂) held, ∂L/∂M⁻¹ = V̂̄ ⊗ impulse), 2ᵀ gives
    // −Δt·V̂̄·[F/m; I_w⁻¹τ]/m.
    let mut mass = adj.mass;
    mass.resize(bodies.len(), 0.0);
    for (k, &i) in sys.coupled.iter().enumerate() {
        let b = &bodies[i];
        let dv = load_velocity(b, dt);
        let (vh, va, vb) = (rec.v_hat[k], rec.v_after[i], vhat_bar[k]);
        let impulse: f64 = (0..6).map(|d| vb[d] * (va[d] - vh[d])).sum();
        let load: f64 = (0..6).map(|d| vb[d] * dv[d]).sum();
        mass[i] -= (impulse + load) / b.mass;
    }
    // Kinematic bodies: b ∋ −Jᵀ·v, so v̄ −= J·s; the pressure does not change their velocity.
    for (i, c, _) in &sys.kinematic {
        let js = c.force(&s);
        let vb: [f64; 6] = std::array::from_fn(|d| vbar[*i][d] - js[d]);
        out[*i].v = Vec3::new(vb[0], vb[1], vb[2]);
        out[*i].w = Vec3::new(vb[3], vb[4], vb[5]);
    }
    if mode == GradientMode::Full {
        let inputs = PoseAdjointInputs {
            sys: &sys.pressure,
            weights: &sys.geometry.weights,
            phi: &sys.phi,
            static_weights: &initial.statics().weights,
            u_hat: &u_hat,
            p: &rec.p,
            s: &s,
            dt,
        };
        // J's faces: the fractions, and on the faces a thin body crosses the static weight.
        let coupling_faces: Vec<[Vec<(usize, Dual<6>)>; 3]> = dual_faces
            .iter()
            .zip(&sys.geometry.seals)
            .map(|(d, seal)| if seal.is_empty() { d.clone() } else { seal.coupling_dual(d) })
            .collect();
        for (k, &i) in sys.coupled.iter().enumerate() {
            let ent = &sys.entrained[k];
            let mut gr = projection_pose_adjoint(
                &inputs,
                &bodies[i],
                &coupling_faces[i],
                k,
                &v_e[k],
                &adj_v[k],
                ent,
            );
            if !ent.is_empty() {
                let density = settings.fluid.density;
                let (v_hat, v_new) = (&rec.v_hat[k], &rec.v_after[i]);
                let b = &bodies[i];
                let ge = ent.pose_adjoint(
                    &grid,
                    b,
                    &dual_faces[i],
                    &ys[k],
                    v_hat,
                    v_new,
                    &u_hat,
                    density,
                );
                for d in 0..6 {
                    gr[d] += ge[d];
                }
            }
            // 2ᵀ for the torque, whose world inertia turns with the body.
            let gw = body_velocity_pose_adjoint(&bodies[i], dt, out[i].w);
            for d in 0..6 {
                pose_grad[i][d] += gr[d];
            }
            for d in 0..3 {
                pose_grad[i][3 + d] += crate::math::comp(gw, d);
            }
        }
        // Kinematic bodies: J and the fractions move with the prescribed pose.
        for (i, bc, v) in &sys.kinematic {
            let gr = kinematic_pose_adjoint(&inputs, &bodies[*i], &coupling_faces[*i], bc, v);
            for d in 0..6 {
                pose_grad[*i][d] += gr[d];
            }
        }
        for i in posed(&sys) {
            let gr = pose_grad[i];
            out[i].x += Vec3::new(gr[0], gr[1], gr[2]);
            let gq = so3::from_tangent_gradient(bodies[i].q, Vec3::new(gr[3], gr[4], gr[5]));
            let q = out[i].q;
            out[i].q = Rotation::from_xyzw(q.x + gq.x, q.y + gq.y, q.z + gq.z, q.w + gq.w);
        }
    }
    lap(&mut times.pressure);

    // 2ᵀ: gravity is the identity on the fluid. 1ᵀ: advection.
    // Into û's field, which nothing reads any more.
    let mut u0 = u_hat;
    advect_adjoint_into(&rec.u, &uhat_bar, &grid, dt, Some(&sys.needed), &mut u0);
    lap(&mut times.advect_velocity);

    // 0ᵀ: the marker particles, whose φ_L the step read.
    let mut particles = Vec::new();
    if let (Some(pr), Some(phi_bar)) = (rec.particles.as_ref(), phi_bar) {
        let ctx = ParticleAdjoint {
            initial,
            u: &rec.u,
            bodies: &bodies,
            geometry: &sys.geometry,
            dual_faces: &dual_faces,
        };
        let mut pose = vec![[0.0f64; 6]; bodies.len()];
        particles = ctx.run(pr, adj.particles, &phi_bar, &mut u0, &mut pose, step)?;
        if mode == GradientMode::Full {
            for i in posed(&sys) {
                let gr = pose[i];
                out[i].x += Vec3::new(gr[0], gr[1], gr[2]);
                let gq = so3::from_tangent_gradient(bodies[i].q, Vec3::new(gr[3], gr[4], gr[5]));
                let q = out[i].q;
                out[i].q = Rotation::from_xyzw(q.x + gq.x, q.y + gq.y, q.z + gq.z, q.w + gq.w);
            }
        }
    }
    lap(&mut times.advect_particles);
    initial.spare().keep_velocity(uhat_bar);
    initial.spare().keep_system(sys.geometry, sys.pressure);
    Ok(AdjointState { u: u0, bodies: out, particles, mass })
}

/// What the particle stage's adjoint (0ᵀ) reads besides the record.
struct ParticleAdjoint<'a> {
    initial: &'a Simulation,
    /// The fluid velocity at the start of the step (the particles' advecting field).
    u: &'a Mac,
    bodies: &'a [RigidBody],
    geometry: &'a Geometry,
    dual_faces: &'a [[Vec<(usize, Dual<6>)>; 3]],
}

impl ParticleAdjoint<'_> {
    /// From ∂L/∂(particles after the step) (`after`, empty for zero) and ∂L/∂φ_L of the step,
    /// ∂L/∂(particles at its start); adds ∂L/∂u of the start velocity into `ubar` and the
    /// bodies' ∂L/∂[δx; δθ] through the push-outs and the density system into `pose`. Replays
    /// the stage from the record: the advection (for the push's input), the density system
    /// and displacement, the positions after the step.
    fn run(
        &self,
        pr: &ParticleRecord,
        after: Vec<Vec3>,
        phi_bar: &[f64],
        ubar: &mut Mac,
        pose: &mut [[f64; 6]],
        step: usize,
    ) -> Result<Vec<Vec3>> {
        let sim = self.initial;
        let grid = *sim.grid();
        let dt = sim.dt();
        let margin = sim.push_margin();
        let fd = surface::jacobian_step(&grid);
        let add_pose = |pose: &mut [[f64; 6]], g: Vec<[f64; 6]>| {
            for (p, g) in pose.iter_mut().zip(g) {
                for d in 0..6 {
                    p[d] += g[d];
                }
            }
        };
        // The positions after the step, replayed from the advected ones: the first push-out,
        // the density projection's displacement and the second push-out.
        let mut advected = pr.moved.clone();
        surface::push_out_of_bodies(&mut advected, self.bodies, margin);
        // The density projection read the band of its own step.
        let band = pr.deep.as_ref().map(|deep| {
            let m = surface::per_axis(sim.settings().solver.particles_per_cell);
            Band::with_deep(&grid, deep.clone(), sim.surface_model().radius, m)
        });
        let inputs = sim.density_inputs(self.geometry).map(|mut g| {
            g.band = band.as_ref();
            g
        });
        let projection = match (&inputs, &pr.density) {
            (Some(g), Some(q)) => DensityProjection::build(&advected, g).map(|p| {
                let disp = p.displacement(q, g);
                (p, q, disp)
            }),
            _ => None,
        };
        let mut displaced = advected.clone();
        if let (Some((proj, _, disp)), Some(g)) = (&projection, &inputs) {
            proj.displace_by(&mut displaced, disp, g);
        }
        let mut end = displaced.clone();
        if inputs.is_some() {
            surface::push_out_of_bodies(&mut end, self.bodies, margin);
        }
        // ∂L/∂(positions after): what later steps and the loss ask, and φ_L of this step.
        let mut pbar = if after.is_empty() { vec![Vec3::ZERO; end.len()] } else { after };
        surface::liquid_sdf_adjoint(&end, &pr.nearest, &grid, phi_bar, &mut pbar);
        // The second push-out and the density projection.
        if let Some(g) = &inputs {
            add_pose(
                pose,
                surface::push_out_of_bodies_adjoint(&displaced, &mut pbar, self.bodies, margin, fd),
            );
            if let Some((proj, q, disp)) = &projection {
                let (s, stats) = proj.adjoint_with(&advected, q, disp, &mut pbar, g);
                if !stats.converged {
                    return Err(Error::NotConverged {
                        solve: Solve::DensityAdjoint,
                        step,
                        iterations: stats.iterations,
                        residual: stats.relative_residual,
                        tolerance: g.solve.tolerance,
                    });
                }
                self.density_weight_pose(proj, q, &s, g, pose);
            }
        }
        if let (Some((proj, _, disp)), Some(g)) = (projection, &inputs) {
            g.give_back(None, Some(disp.d));
            proj.give_back(g);
        }
        // The first push-out, from the advected positions before it, and the advection
        // through the start velocity.
        let node_sdf = &sim.statics().node_sdf;
        add_pose(
            pose,
            surface::push_out_of_bodies_adjoint(&pr.moved, &mut pbar, self.bodies, margin, fd),
        );
        surface::advect_adjoint(
            &pr.start,
            &mut pbar,
            self.u,
            &grid,
            dt,
            pr.substeps,
            node_sdf,
            ubar,
        );
        // The band's update before the advection: back to the particles' old indices.
        Ok(match &pr.change {
            Some(change) => change.adjoint(&pbar),
            None => pbar,
        })
    }

    /// The density system's part of the pose derivative: its weights lose what a body covers,
    /// so −sᵀ·δA·q = Σ_f ∂β_f/∂pose · Δt·dx/ρ·θ·(g·s)(g·q) over the faces the body covers in
    /// part (inside the clamp of w = w_static − β).
    fn density_weight_pose(
        &self,
        proj: &DensityProjection,
        q: &[f64],
        s: &[f64],
        g: &DensityInputs<'_>,
        pose: &mut [[f64; 6]],
    ) {
        let statics = &self.initial.statics().weights;
        // A face the projection closed at a deep cell does not see the body.
        let weights = proj.weights(g);
        for (i, faces) in self.dual_faces.iter().enumerate() {
            for (axis, list) in faces.iter().enumerate() {
                for (f, beta) in list {
                    let raw = statics.weight(axis, *f) - beta.v;
                    if !(raw > 0.0 && raw < 1.0 && weights.weight(axis, *f) > 0.0) {
                        continue;
                    }
                    let w = proj.sys.weight_adjoint(axis, *f, weights, &proj.phi, s, q);
                    for k in 0..6 {
                        pose[i][k] += beta.d[k] * w;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{GradientMode, SurfaceGradient};

    /// Each option reads back from its name, and a wrong name is an error naming the choices.
    #[test]
    fn options_parse_from_their_names() {
        for m in GradientMode::ALL {
            assert_eq!(m.name().parse::<GradientMode>(), Ok(m));
        }
        for s in SurfaceGradient::ALL {
            assert_eq!(s.name().parse::<SurfaceGradient>(), Ok(s));
        }
        let e = "Full".parse::<GradientMode>().unwrap_err();
        assert!(e.contains("\"full\" or \"paper\"") && e.contains("\"Full\""), "{e}");
        let e = "fixed".parse::<SurfaceGradient>().unwrap_err();
        assert!(e.contains("\"live\" or \"frozen\"") && e.contains("\"fixed\""), "{e}");
    }
}
