//! Stage [`Pressure`](super::Stage::Pressure): the coupled solve of the step's system with
//! contact held inside it, the velocity update, and the bodies' velocities and pressure
//! forces after it; and its adjoint (one more solve with the same operator, the surface's
//! part through the ghost-fluid θ, the carried liquid, the masses, the pose derivative).

use crate::error::{Error, Result, Solve};
use crate::geometry::body::RigidBody;
use crate::geometry::fractions::DualFaces;
use crate::geometry::grid::Mac;
use crate::geometry::weights::FaceWeights;
use crate::math::{add_twist, Twist, Vec3};
use crate::solvers::cg::CgStats;
use crate::solvers::LinearSolve;
use crate::stages::contact::{hold_contact, ContactChange, ContactHold, ContactSettings};
use crate::stages::pressure::{kinematic_pose_adjoint, projection_pose_adjoint, PoseAdjointInputs};
use crate::stages::system::StepSystem;

/// What the projection leaves.
#[derive(Debug)]
pub struct Projection {
    /// The pressure per liquid cell.
    pub p: Vec<f64>,
    /// The solve's statistics.
    pub stats: CgStats,
    /// Per coupled body: [v; ω] the solve started from (with the contact kick).
    pub v_hat: Vec<Twist>,
    /// Per coupled body: [v; ω] after the solve.
    pub v_after: Vec<Twist>,
    /// Per coupled body: the pressure force and torque J·p (less the weight and momentum of
    /// the liquid a thin body carries).
    pub forces: Vec<Twist>,
    /// What holding contact took.
    pub hold: ContactHold,
    /// The solves of the contact iteration before the one that stands, in order (none
    /// without contact): the backward pass differentiates through each.
    pub held: Vec<HeldSolve>,
}

/// One solve of the contact iteration that a later one replaced (see [`hold_contact`]): what
/// its adjoint reads. Per coupled body.
#[derive(Clone, Debug, Default)]
pub struct HeldSolve {
    /// [v; ω] the solve started from (with the contact kick held so far).
    pub v_hat: Vec<Twist>,
    /// [v; ω] after it: what contact was then asked to change.
    pub v_after: Vec<Twist>,
    /// Its pressure.
    pub p: Vec<f64>,
}

/// A pressure solve: from the predicted field û, the coupled bodies' velocities (with the
/// liquid they carry) and a warm start (the previous contact iteration's pressure, or None
/// for the caller's own), the pressure and its statistics. The caller's, so that a solve
/// can be recorded or replayed.
pub type PressureSolve<'a> =
    &'a mut dyn FnMut(&Mac, &[Twist], Option<Vec<f64>>) -> Result<(Vec<f64>, CgStats)>;

/// Contact held inside the projection: the bodies as they are, rapier's settings, and the
/// velocity change below which contact counts as done.
#[derive(Clone, Copy)]
pub struct HeldContact<'a> {
    /// Every body (the coupled ones' velocities are replaced by the solve's).
    pub bodies: &'a [RigidBody],
    /// The tank's size, m.
    pub size: Vec3,
    /// rapier's settings.
    pub settings: &'a ContactSettings,
    /// The largest velocity change, m/s, that counts as none.
    pub tolerance: f64,
}

/// The projection from the fluid velocity `u_hat` and the coupled bodies' velocities
/// `v_hat` over `dt`, each solve made by `solve`, with contact held inside it when given
/// (see [`hold_contact`]). Returns the projection and `u_hat` updated by its pressure.
pub fn project(
    sys: &StepSystem,
    u_hat: Mac,
    v_hat: &[Twist],
    dt: f64,
    contact: Option<HeldContact<'_>>,
    solve: PressureSolve<'_>,
) -> Result<(Projection, Mac)> {
    let mut last_p: Option<Vec<f64>> = None;
    let mut held: Vec<HeldSolve> = Vec::new();
    let one = |kick: &[Twist]| {
        let vel: Vec<Twist> =
            v_hat.iter().zip(kick).map(|(v, k)| std::array::from_fn(|d| v[d] + k[d])).collect();
        // With the liquid the thin bodies carry (`vel` where they carry none).
        let vel_e = sys.entrained_velocities(&vel, &u_hat);
        let (p, stats) = solve(&u_hat, &vel_e, last_p.take())?;
        let mut forces: Vec<Twist> = sys.couplings().iter().map(|c| c.force(&p)).collect();
        let after: Vec<Twist> = sys
            .couplings()
            .iter()
            .zip(&vel_e)
            .zip(&forces)
            .map(|((c, v), f)| {
                let dv = c.dt_minv_times(f);
                std::array::from_fn(|d| v[d] + dv[d])
            })
            .collect();
        // A body carrying liquid feels M·(V' − V̂)/Δt of it: J·p less the weight and the
        // momentum of the liquid it carries.
        for (k, ent) in sys.entrained.iter().enumerate().filter(|(_, e)| !e.is_empty()) {
            let dv: Twist = std::array::from_fn(|d| (after[k][d] - vel[k][d]) / dt);
            forces[k] = std::array::from_fn(|r| (0..6).map(|c| ent.mass[r][c] * dv[c]).sum());
        }
        last_p = Some(p.clone());
        if contact.is_some() {
            held.push(HeldSolve { v_hat: vel.clone(), v_after: after.clone(), p: p.clone() });
        }
        let proj = Projection {
            p,
            stats,
            v_hat: vel,
            v_after: after.clone(),
            forces,
            hold: ContactHold::default(),
            held: Vec::new(),
        };
        Ok((proj, after))
    };
    let change = |after: &[Twist]| match contact {
        Some(c) => contact_change(c, &sys.coupled, after, dt),
        None => Vec::new(),
    };
    let change_fn: Option<ContactChange<'_>> = contact.map(|_| &change as ContactChange<'_>);
    let tolerance = contact.map_or(0.0, |c| c.tolerance);
    let (mut proj, hold) = hold_contact(sys.coupled.len(), one, change_fn, tolerance)?;
    proj.hold = hold;
    // The last solve is the one that stands.
    held.pop();
    proj.held = held;
    // The velocity update of the solve that stands (the field is not copied per contact
    // iteration).
    let mut u = u_hat;
    sys.pressure.subtract_pressure_gradient(&proj.p, &mut u);
    Ok((proj, u))
}

/// What rapier's contact step would do to each coupled body's [v; ω] if the bodies had the
/// velocities `after`: its velocity after the step minus before.
fn contact_change(
    contact: HeldContact<'_>,
    coupled: &[usize],
    after: &[Twist],
    dt: f64,
) -> Vec<Twist> {
    #[cfg(feature = "contact")]
    {
        use crate::math::TwistParts;
        use crate::stages::system::generalized_velocity;
        let mut bodies = contact.bodies.to_vec();
        for (&i, v) in coupled.iter().zip(after) {
            (bodies[i].v, bodies[i].w) = (v.linear(), v.angular());
        }
        let before = bodies.clone();
        crate::stages::contact::ContactWorld::new(contact.size, &bodies, contact.settings)
            .step(&mut bodies, dt);
        coupled
            .iter()
            .map(|&i| {
                let (a, b) = (generalized_velocity(&bodies[i]), generalized_velocity(&before[i]));
                std::array::from_fn(|d| a[d] - b[d])
            })
            .collect()
    }
    #[cfg(not(feature = "contact"))]
    {
        let _ = (contact, after, dt);
        vec![[0.0; 6]; coupled.len()]
    }
}

/// What the projection's adjoint reads besides the adjoints it is given.
pub struct ProjectAdjointInputs<'a> {
    /// The step's system, as the forward step assembled it.
    pub sys: &'a StepSystem,
    /// The bodies at the start of the step.
    pub bodies: &'a [RigidBody],
    /// The step's pressure.
    pub p: &'a [f64],
    /// Per coupled body, [v; ω] the solve started from ([`Projection::v_hat`]).
    pub v_hat: &'a [Twist],
    /// Per body, [v; ω] after the solve (the coupled ones' [`Projection::v_after`]).
    pub v_after: &'a [Twist],
    /// The predicted field û on the faces the bodies cover (at least).
    pub u_hat: &'a Mac,
    /// The static solids' weights.
    pub static_weights: &'a FaceWeights,
    /// Each body's dual face fractions: the pose derivative is taken when given.
    pub dual_faces: Option<&'a [DualFaces]>,
    /// Whether ∂L/∂φ_L through θ and the carried liquid is wanted (the moving surface).
    pub surface: bool,
    /// The adjoint solve's settings.
    pub how: LinearSolve,
    /// The liquid's density, kg/m³.
    pub density: f64,
    /// The step's Δt.
    pub dt: f64,
    /// The step's number (for the error of a solve that fails).
    pub step: usize,
}

/// What the projection's adjoint gives.
#[derive(Debug)]
pub struct ProjectAdjoint {
    /// ∂L/∂û, the predicted field.
    pub u_hat: Mac,
    /// ∂L/∂φ_L per cell, of φ_L extended into the solids (with the surface moving).
    pub phi: Option<Vec<f64>>,
    /// ∂L/∂b, the solve's right-hand side, per row: the adjoint solve's solution (what a
    /// source added to a row's right-hand side, [`StepSystem::volume_source`], is
    /// differentiated by).
    pub rhs: Vec<f64>,
}

/// Adjoint of [`project`]'s solve that stood (the kick held constant; see
/// [`project_adjoint_held`] for the contact iteration before it): from
/// ∂L/∂u after the update (`ubar`) and ∂L/∂[v; ω] after the solve per body (`vbar`), ∂L/∂û
/// and ∂L/∂φ_L (returned); `vbar` becomes ∂L/∂[v; ω] before the solve for the coupled and
/// the kinematic bodies; the masses' adjoints are added to `mass` and the poses' ∂L/∂[δx;
/// δθ] to `pose` (one per body).
pub fn project_adjoint(
    g: &ProjectAdjointInputs<'_>,
    mut ubar: Mac,
    vbar: &mut [Twist],
    mass: &mut [f64],
    pose: &mut [Twist],
) -> Result<ProjectAdjoint> {
    let sys = g.sys;
    let adj_v: Vec<Twist> = sys.coupled.iter().map(|&i| vbar[i]).collect();
    let phi = g.surface.then_some(sys.phi.as_slice());
    let solved = sys.pressure.projection_adjoint(
        &mut ubar,
        &adj_v,
        &sys.geometry.weights,
        &g.how,
        phi.map(|phi| (phi, g.p)),
    );
    if !solved.stats.converged {
        return Err(Error::NotConverged {
            solve: Solve::PressureAdjoint,
            step: g.step,
            iterations: solved.stats.iterations,
            residual: solved.stats.relative_residual,
            tolerance: g.how.tolerance,
        });
    }
    let (s, mut vhat_bar, mut phi_bar) = (solved.s, solved.v_hat, solved.phi);
    let mut uhat_bar = ubar;
    // The liquid a thin body carries: V_e = M_e⁻¹·(M·V̂ + Σ m_f·û_f·a_f) back to V̂ and û,
    // and through its masses' liquid fractions to φ_L. y = M_e⁻¹·V̄_e per coupled body.
    let v_e = sys.entrained_velocities(g.v_hat, g.u_hat);
    let mut ys = vec![[0.0; 6]; sys.coupled.len()];
    for (k, ent) in sys.entrained.iter().enumerate().filter(|(_, e)| !e.is_empty()) {
        let (vb, y) = ent.velocity_adjoint(&vhat_bar[k], &mut uhat_bar);
        vhat_bar[k] = vb;
        ys[k] = y;
        if let Some(out) = phi_bar.as_mut() {
            let v_new = &g.v_after[sys.coupled[k]];
            ent.phi_adjoint(&y, v_new, g.u_hat, &sys.phi, sys.pressure.params.ghost, out);
        }
    }
    // The masses, the inertias scaling with them (M → s·M): −V̂̄·(V′ − V̂)/m (the pressure's
    // impulse M·(V′ − V̂) held, ∂L/∂M⁻¹ = V̂̄ ⊗ impulse).
    for (k, &i) in sys.coupled.iter().enumerate() {
        let (vh, va, vb) = (g.v_hat[k], g.v_after[i], vhat_bar[k]);
        let impulse: f64 = (0..6).map(|d| vb[d] * (va[d] - vh[d])).sum();
        mass[i] -= impulse / g.bodies[i].mass;
    }
    if let Some(dual_faces) = g.dual_faces {
        let inputs = PoseAdjointInputs {
            sys: &sys.pressure,
            weights: &sys.geometry.weights,
            phi: &sys.phi,
            static_weights: g.static_weights,
            u_hat: g.u_hat,
            p: g.p,
            s: &s,
            dt: g.dt,
        };
        // J's faces: the fractions, and on the faces a thin body crosses the static weight.
        let coupling_faces: Vec<DualFaces> = dual_faces
            .iter()
            .zip(&sys.geometry.seals)
            .map(|(d, seal)| if seal.is_empty() { d.clone() } else { seal.coupling_dual(d) })
            .collect();
        for (k, &i) in sys.coupled.iter().enumerate() {
            let (b, ent) = (&g.bodies[i], &sys.entrained[k]);
            let mut gr =
                projection_pose_adjoint(&inputs, b, &coupling_faces[i], k, &v_e[k], &adj_v[k], ent);
            if !ent.is_empty() {
                let (v_hat, v_new) = (&g.v_hat[k], &g.v_after[i]);
                let grid = &sys.pressure.grid;
                let ge = ent.pose_adjoint(
                    grid,
                    b,
                    &dual_faces[i],
                    &ys[k],
                    v_hat,
                    v_new,
                    g.u_hat,
                    g.density,
                );
                add_twist(&mut gr, &ge);
            }
            add_twist(&mut pose[i], &gr);
        }
        // Kinematic bodies: J and the fractions move with the prescribed pose.
        for (i, bc, v) in &sys.kinematic {
            let gr = kinematic_pose_adjoint(&inputs, &g.bodies[*i], &coupling_faces[*i], bc, v);
            add_twist(&mut pose[*i], &gr);
        }
    }
    for (k, &i) in sys.coupled.iter().enumerate() {
        vbar[i] = vhat_bar[k];
    }
    // Kinematic bodies: b ∋ −Jᵀ·v, so v̄ −= J·s; the pressure does not change their velocity.
    for (i, c, _) in &sys.kinematic {
        let js = c.force(&s);
        vbar[*i] = std::array::from_fn(|d| vbar[*i][d] - js[d]);
    }
    Ok(ProjectAdjoint { u_hat: uhat_bar, phi: phi_bar.take(), rhs: s })
}

/// Adjoint of [`project`] with contact held inside it: [`project_adjoint`] of the solve that
/// stood, then back through the contact iteration that led to it. Each kick was the last
/// plus what rapier's contact step would do to the bodies after the solve before,
/// k_{j+1} = k_j + C(V_j); so ∂L/∂k_j sums ∂L/∂V̂ of every later solve, rapier's step
/// takes it to ∂L/∂V_j, the solve's pose and mass (by central differences of the step,
/// [`contact_adjoint`](crate::stages::contact::contact_adjoint)), and one more adjoint
/// solve per held solve takes ∂L/∂V_j to the solve's inputs. `held` are the solves before
/// the one that stood ([`Projection::held`]), `contact` what the forward pass held contact
/// with. Without held solves it is [`project_adjoint`].
pub fn project_adjoint_held(
    g: &ProjectAdjointInputs<'_>,
    held: &[HeldSolve],
    contact: HeldContact<'_>,
    ubar: Mac,
    vbar: &mut [Twist],
    mass: &mut [f64],
    pose: &mut [Twist],
) -> Result<ProjectAdjoint> {
    let mut total = project_adjoint(g, ubar, vbar, mass, pose)?;
    let coupled = &g.sys.coupled;
    if held.is_empty() || coupled.is_empty() {
        return Ok(total);
    }
    // ∂L/∂k of the kick the latest solve reached, per coupled body.
    let mut kick_bar: Vec<Twist> = coupled.iter().map(|&i| vbar[i]).collect();
    let grid = g.sys.pressure.grid;
    // The kinematic bodies, which contact does not move.
    let posed: Vec<usize> = g.sys.kinematic.iter().map(|k| k.0).collect();
    for solve in held.iter().rev() {
        let seed: Vec<f64> = kick_bar.iter().flatten().copied().collect();
        let change = |bodies: &[RigidBody], velocities: &[Twist]| -> Vec<f64> {
            let c = HeldContact { bodies, ..contact };
            contact_change(c, coupled, velocities, g.dt).into_iter().flatten().collect()
        };
        let (through, kinematic) = crate::stages::contact::contact_adjoint(
            contact.bodies,
            coupled,
            &solve.v_after,
            &posed,
            &seed,
            &change,
        );
        for (&i, k) in posed.iter().zip(&kinematic) {
            add_twist(&mut pose[i], &k.pose);
            add_twist(&mut vbar[i], &k.velocity);
        }
        let mut v_after = g.v_after.to_vec();
        let mut seed_v = vec![[0.0; 6]; vbar.len()];
        for ((&i, t), v) in coupled.iter().zip(&through).zip(&solve.v_after) {
            seed_v[i] = t.velocity;
            add_twist(&mut pose[i], &t.pose);
            mass[i] += t.mass;
            v_after[i] = *v;
        }
        let inputs =
            ProjectAdjointInputs { p: &solve.p, v_hat: &solve.v_hat, v_after: &v_after, ..*g };
        let part = project_adjoint(&inputs, Mac::zeros(&grid), &mut seed_v, mass, pose)?;
        for (a, b) in total.u_hat.c.iter_mut().zip(&part.u_hat.c) {
            a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
        }
        if let (Some(a), Some(b)) = (total.phi.as_mut(), &part.phi) {
            a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
        }
        total.rhs.iter_mut().zip(&part.rhs).for_each(|(x, y)| *x += y);
        for (k, &i) in coupled.iter().enumerate() {
            add_twist(&mut kick_bar[k], &seed_v[i]);
        }
        // Every solve's ∂L/∂V̂ reaches the velocity before the kicks; a kinematic body's
        // velocity enters every solve's right-hand side.
        for (a, b) in vbar.iter_mut().zip(&seed_v) {
            add_twist(a, b);
        }
    }
    Ok(total)
}
