//! The backward pass (the paper's Algorithm 3): walks the taped steps in reverse and, per
//! step, rebuilds what the stages read with the forward pass's own functions
//! ([`StepSystem::assemble`], the predicted field), then runs the adjoints of the stages of
//! [`Stage::ALL`] in the reverse order, each the exact transpose of its forward
//! linearisation and each beside its forward function in `stages/`. The marker particles'
//! positions are part of the state: the adjoint carries ∂L/∂(particles) from step to step.
//!
//! [`SurfaceGradient::Live`] (the default) differentiates the surface's motion, so the
//! gradient is that of the forward map wherever no cell or face changes kind;
//! [`SurfaceGradient::Frozen`] holds the surface fixed in the backward pass, as the paper did
//! (exact only when `solver.freeze_surface` holds it fixed in the forward pass too).
//! [`GradientMode::Full`] carries the dependence of the geometry on the body poses (face
//! fractions, J, the world inertia, the rigid velocity set inside bodies, the push-outs);
//! [`GradientMode::Paper`] drops it, as the paper does.

use super::loss::{AdjointState, BodyGradient, Gradient};
use crate::error::{GradientError, Result};
use crate::geometry::body::{Motion, RigidBody};
use crate::geometry::fractions::DualFaces;
use crate::geometry::grid::Mac;
use crate::math::pool::{self, run_spread, Spread};
use crate::math::so3;
use crate::math::{add_twist, Twist, TwistParts, Vec3};
use crate::stages::advect::{
    advect_adjoint_into, advect_adjoint_traced, needed_faces, AdvectionTraces,
};
use crate::stages::band::Band;
use crate::stages::extrapolate::{
    correct_with_bodies_adjoint_planned, surface_faces, Correction, CorrectionPlan,
};
use crate::stages::forces::body_velocity_adjoint;
use crate::stages::particles::ParticleStage;
use crate::stages::pressure::Coupling;
use crate::stages::project::{project_adjoint_held, HeldContact, ProjectAdjointInputs};
use crate::stages::rigid::{integrate_adjoint, integrate_contact_adjoint, Tank};
use crate::stages::solid_phi::solidity_pose_adjoint;
use crate::stages::surface;
use crate::stages::system::{predicted_velocity, volume_source_derivative};
use crate::stages::{Stage, StageClock, StageSeconds};
use crate::world::tape::ParticleRecord;
use crate::world::{Simulation, StepRecord, StepSystem, Tape};

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
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GradientOptions {
    /// Full or the paper's approximation.
    pub mode: GradientMode,
    /// The moving surface, or the paper's fixed one.
    pub surface: SurfaceGradient,
    /// Go through taped steps in which rapier contact acted (default true): the gradient
    /// follows the step rapier took (its contact solve differenced, see
    /// [`contact_adjoint`](crate::stages::contact::contact_adjoint)), at 26 rapier steps a
    /// body and one adjoint solve per contact iteration in each such step. False makes such
    /// a tape an error, for a caller who wants to be told that contact acted.
    pub through_contact: bool,
}

impl Default for GradientOptions {
    /// The full gradient of the moving surface, through contact.
    fn default() -> Self {
        GradientOptions {
            mode: GradientMode::default(),
            surface: SurfaceGradient::default(),
            through_contact: true,
        }
    }
}

impl GradientOptions {
    /// The options for `mode`, the rest the defaults.
    pub fn new(mode: GradientMode) -> GradientOptions {
        GradientOptions { mode, ..Default::default() }
    }
}

/// Wall time of each stage's adjoint over a backward pass, in seconds (summed over steps):
/// a field per [`Stage`].
pub type AdjointSeconds = StageSeconds;

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
        let steps = &tape.steps;
        let mut next = steps.last().map(|rec| rebuild(initial, rec, options));
        for (t, rec) in steps.iter().enumerate().rev() {
            let read = next.take().expect("rebuilt");
            // The step before's rebuild reads only its record: it runs beside this step's
            // adjoints when a second thread is free.
            let step = |adj| step_adjoint(initial, rec, read, adj, options, first + t + 1);
            let earlier = t.checked_sub(1).map(|e| &steps[e]);
            let (stepped, ahead) =
                pool::ahead(|| step(adj), || earlier.map(|e| rebuild(initial, e, options)));
            let (a, seconds) = stepped?;
            (adj, next) = (a, ahead);
            times += seconds;
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

/// What a step's adjoints read besides the adjoint state, rebuilt from its record as the
/// forward step built it, and what rebuilding it cost.
struct Rebuilt {
    /// The bodies as the step started.
    bodies: Vec<RigidBody>,
    /// The step's system, its preconditioner factored.
    sys: StepSystem,
    /// Each body's dual fractions (the full gradient; empty for the paper's).
    dual_faces: Vec<DualFaces>,
    /// û (advected, with gravity) on the faces where the adjoints of the correction and the
    /// projection read it.
    u_hat: Mac,
    /// The masks and extrapolation layers the correction's adjoint reads.
    correction: CorrectionPlan,
    /// What the advection's adjoint reads of the taped field, when the pass runs serially
    /// (then this rebuild may run beside the later steps' adjoints; on a grid large enough
    /// to spread its loops, the adjoint traces each face as it goes instead).
    traces: Option<AdvectionTraces>,
    seconds: AdjointSeconds,
}

/// What the adjoint of the step recorded as `rec` reads: the step's system (and the
/// preconditioner its adjoint solve takes), the fractions' pose derivatives and the predicted
/// field. It reads nothing of the adjoint state, so it may run before the later steps'
/// adjoints are done.
fn rebuild(initial: &Simulation, rec: &StepRecord, options: &GradientOptions) -> Rebuilt {
    let full = options.mode == GradientMode::Full;
    let (grid, dt, settings) = (*initial.grid(), initial.dt(), initial.settings());
    let mut seconds = AdjointSeconds::default();
    let times = &mut seconds;
    let mut clock = StageClock::new();
    let bodies = bodies_at(initial, rec);
    let geometry = initial.geometry_with(&bodies, rec.body_faces.clone());
    let phi = if rec.phi.is_empty() { initial.particle_phi() } else { rec.phi.clone() };
    let memory = initial.spare().systems().take();
    let sys = StepSystem::assemble(&grid, &bodies, geometry, phi, initial.step_params(dt), memory);
    clock.lap(Stage::Assemble, times);
    let dual_faces: Vec<DualFaces> = if full {
        bodies.iter().map(|b| b.face_fractions_dual(&grid)).collect()
    } else {
        Vec::new()
    };
    clock.lap(Stage::Geometry, times);
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
    clock.lap(Stage::AdvectVelocity, times);
    sys.pressure.prepare(&settings.solver.linear());
    clock.lap(Stage::Pressure, times);
    let faces = &sys.geometry.body_faces;
    let layers = settings.solver.extrapolation_layers;
    let mut correction = CorrectionPlan::new(sys.projected_mask(), faces, &grid, layers);
    let blend = settings.solver.blend();
    if blend.theta > 0.0 {
        // The blended layers' transpose reads the field they started from: the forward
        // step's, from û on every face it advected and the step's pressure.
        let (weights, statics) = (&sys.geometry.weights, &initial.statics().weights);
        let surface = surface_faces(&sys.pressure, &sys.phi, faces, weights, statics, blend);
        let mut updated =
            predicted_velocity(&rec.u, &grid, dt, gravity, &sys.needed, Mac::zeros(&grid));
        sys.pressure.update_velocity(&rec.p, &mut updated);
        let after = bodies_after(&bodies, rec);
        let step =
            Correction { bodies: &after, faces, weights, static_weights: statics, grid: &grid };
        correction = correction.blended(surface, updated, step);
    }
    clock.lap(Stage::CorrectVelocity, times);
    let traces = (initial.spread() == Spread::Serial)
        .then(|| AdvectionTraces::new(&rec.u, &grid, dt, Some(&sys.needed)));
    clock.lap(Stage::AdvectVelocity, times);
    Rebuilt { bodies, sys, dual_faces, u_hat, correction, traces, seconds }
}

/// The adjoint of one step: from the adjoint of the state after step `step` (recorded as
/// `rec`, what its stages read rebuilt as `read`), the adjoint of the state before it, and
/// what each stage's adjoint cost (the rebuild's included). The stages' adjoints in the
/// reverse order of [`Stage::ALL`].
fn step_adjoint(
    initial: &Simulation,
    rec: &StepRecord,
    read: Rebuilt,
    adj: AdjointState,
    options: &GradientOptions,
    step: usize,
) -> Result<(AdjointState, AdjointSeconds)> {
    let full = options.mode == GradientMode::Full;
    let (grid, dt, settings) = (*initial.grid(), initial.dt(), initial.settings());
    let Rebuilt { bodies, sys, dual_faces, u_hat, correction, traces, seconds } = read;
    let mut total = seconds;
    let times = &mut total;
    let mut clock = StageClock::new();

    let mut mass = adj.mass;
    mass.resize(bodies.len(), 0.0);
    let (mut out, mut vbar) = if rec.rigid_contact {
        // Through the step rapier took.
        let tank = Tank { size: grid.size(), external_reach: 0.0 };
        let (start, after) = (&rec.bodies, &adj.bodies);
        let contact = &settings.contact;
        let (out, vbar, m) =
            integrate_contact_adjoint(&bodies, start, &rec.v_after, after, dt, tank, contact);
        mass.iter_mut().zip(m).for_each(|(a, b)| *a += b);
        (out, vbar)
    } else {
        integrate_adjoint(&bodies, &rec.bodies, &rec.v_after, &adj.bodies, dt)
    };
    let mut pose = vec![[0.0f64; 6]; bodies.len()];
    clock.lap(Stage::Rigid, times);

    let mut ubar = adj.u;
    let dual = full.then_some(dual_faces.as_slice());
    let u_corr = |a: usize, f: usize| u_hat.c[a][f] - sys.pressure.velocity_update_at(a, f, &rec.p);
    let shares_phi = correct_velocity_adjoint(
        initial,
        rec,
        &sys,
        &correction,
        &bodies,
        dual,
        u_corr,
        &mut ubar,
        &mut vbar,
        &mut pose,
    );
    clock.lap(Stage::CorrectVelocity, times);

    let live_surface = options.surface == SurfaceGradient::Live && rec.particles.is_some();
    // φ_L in the cells a body's surface crosses moves with its pose (the solids' ramp), the
    // surface frozen or not; the paper's gradient holds it fixed.
    let solids_ramp =
        full && options.surface == SurfaceGradient::Live && !sys.geometry.partial.is_empty();
    let inputs = ProjectAdjointInputs {
        sys: &sys,
        bodies: &bodies,
        p: &rec.p,
        v_hat: &rec.v_hat,
        v_after: &rec.v_after,
        u_hat: &u_hat,
        static_weights: &initial.statics().weights,
        dual_faces: dual,
        surface: live_surface || solids_ramp,
        how: settings.solver.linear(),
        density: settings.fluid.density,
        dt,
        step,
    };
    // Back through the contact iteration held inside the projection, if any.
    let contact = HeldContact {
        bodies: &bodies,
        size: grid.size(),
        settings: &settings.contact,
        tolerance: 0.0,
    };
    let mut projected =
        project_adjoint_held(&inputs, &rec.held, contact, ubar, &mut vbar, &mut mass, &mut pose)?;
    // The blended faces' shares read φ_L as the projection's θ does.
    if let Some(g) = projected.phi.as_mut() {
        for (c, v) in shares_phi {
            g[c] += v;
        }
    }
    clock.lap(Stage::Pressure, times);

    for &i in &sys.coupled {
        let (m, g) = body_velocity_adjoint(&bodies[i], dt, &vbar[i]);
        mass[i] += m;
        if full {
            for d in 3..6 {
                pose[i][d] += g[d];
            }
        }
    }
    for i in posed(&sys) {
        let v = vbar[i];
        (out[i].v, out[i].w) = (v.linear(), v.angular());
    }
    clock.lap(Stage::Forces, times);

    // Gravity is the identity on the fluid; advection into û's field, which nothing reads
    // any more.
    let mut u0 = u_hat;
    let uhat_bar = projected.u_hat;
    match &traces {
        Some(traces) => advect_adjoint_traced(traces, &uhat_bar, &grid, &mut u0),
        None => advect_adjoint_into(&rec.u, &uhat_bar, &grid, dt, Some(&sys.needed), &mut u0),
    }
    clock.lap(Stage::AdvectVelocity, times);

    // ∂L/∂φ_L back out of the solids, to the cells the extension read and the bodies' poses
    // (through how deep their surfaces lie in the cells they cross).
    let phi_bar = projected.phi.map(|mut g| {
        let sbar = sys.extension.transpose(&sys.phi, &mut g);
        if full {
            solidity_pose_adjoint(&grid, &bodies, &sbar, &mut pose);
        }
        g
    });
    let phi_bar = phi_bar.filter(|_| live_surface);
    clock.lap(Stage::Assemble, times);

    let mut particles = Vec::new();
    if let (Some(pr), Some(mut phi_bar)) = (rec.particles.as_ref(), phi_bar) {
        // ∂L/∂φ_L before the closing of air pockets (the surface stage's last step).
        pr.pockets.adjoint(&mut phi_bar);
        let pieces =
            ParticlePieces { pr, phi_bar: &phi_bar, rhs: &projected.rhs, dual_faces: &dual_faces };
        let after = adj.particles;
        particles = particles_adjoint(
            initial, rec, &sys, &bodies, pieces, after, &mut u0, &mut pose, &mut clock, times, step,
        )?;
    }

    // The step's pose derivatives, of every stage, to the poses it started from.
    if full {
        for i in posed(&sys) {
            out[i].add_pose(bodies[i].q, &pose[i]);
        }
    }
    clock.lap(Stage::Geometry, times);
    initial.spare().keep_velocity(uhat_bar);
    initial.spare().keep_system(sys.geometry, sys.pressure);
    Ok((AdjointState { u: u0, bodies: out, particles, mass }, total))
}

/// The adjoint of [`Stage::CorrectVelocity`]: `ubar` (∂L/∂u after the step) becomes ∂L/∂u
/// after the projection (`u_corr` gives that field where it is read, `plan` the masks and
/// layers of the correction); the bodies' ∂L/∂[v; ω] after the solve are added to `vbar`,
/// and with `dual` (each body's dual fractions, the full gradient) their ∂L/∂[δx; δθ] to
/// `pose`. Returns (cell, ∂L/∂φ_L) through the shares of the faces blended into the
/// extrapolation (`solver.surface_blend`).
#[allow(clippy::too_many_arguments)]
fn correct_velocity_adjoint(
    initial: &Simulation,
    rec: &StepRecord,
    sys: &StepSystem,
    plan: &CorrectionPlan,
    bodies: &[RigidBody],
    dual: Option<&[DualFaces]>,
    u_corr: impl Fn(usize, usize) -> f64,
    ubar: &mut Mac,
    vbar: &mut [Twist],
    pose: &mut [Twist],
) -> Vec<(usize, f64)> {
    let after = bodies_after(bodies, rec);
    let grid = initial.grid();
    let step = Correction {
        bodies: &after,
        faces: &sys.geometry.body_faces,
        weights: &sys.geometry.weights,
        static_weights: &initial.statics().weights,
        grid,
    };
    let bva = correct_with_bodies_adjoint_planned(ubar, u_corr, &rec.air_body_faces, plan, step);
    for (i, r) in bva.bodies.iter().enumerate() {
        // A fixed body's pose and velocity are constants; a kinematic one's are the
        // prescribed motion's (a control's).
        if !(bodies[i].moves() || bodies[i].motion == Motion::Kinematic) {
            continue;
        }
        add_twist(&mut vbar[i], &r.vel);
        if let Some(dual) = dual {
            add_twist(&mut pose[i], &r.pose(&dual[i]));
        }
    }
    bva.phi
}

/// The bodies of a step as its velocity correction saw them: with their velocities after
/// the solve.
fn bodies_after(bodies: &[RigidBody], rec: &StepRecord) -> Vec<RigidBody> {
    let mut after = bodies.to_vec();
    for (b, va) in after.iter_mut().zip(&rec.v_after) {
        (b.v, b.w) = (va.linear(), va.angular());
    }
    after
}

/// What the particle stages' adjoints read of the step besides the record.
struct ParticlePieces<'a> {
    pr: &'a ParticleRecord,
    /// ∂L/∂φ_L of the step, carried back out of the solids.
    phi_bar: &'a [f64],
    /// ∂L/∂(the solve's right-hand side) per row (volume control's sources read it).
    rhs: &'a [f64],
    dual_faces: &'a [DualFaces],
}

/// The adjoints of [`Stage::Surface`], [`Stage::Density`], [`Stage::AdvectParticles`] and
/// [`Stage::Band`], in that order, timed: from ∂L/∂(particles after the step) (`after`, empty
/// for zero), ∂L/∂(particles at its start); ∂L/∂u of the start velocity is added to `ubar` and
/// the bodies' ∂L/∂[δx; δθ] to `pose`.
#[allow(clippy::too_many_arguments)]
fn particles_adjoint(
    initial: &Simulation,
    rec: &StepRecord,
    sys: &StepSystem,
    bodies: &[RigidBody],
    pieces: ParticlePieces<'_>,
    after: Vec<Vec3>,
    ubar: &mut Mac,
    pose: &mut [Twist],
    clock: &mut StageClock,
    times: &mut AdjointSeconds,
    step: usize,
) -> Result<Vec<Vec3>> {
    let ParticlePieces { pr, phi_bar, rhs, dual_faces } = pieces;
    let (grid, dt, settings) = (*initial.grid(), initial.dt(), initial.settings());
    // The density projection read the band of its own step.
    let model = initial.surface_model();
    let band = pr.deep.as_ref().map(|deep| Band::with_deep(&grid, deep.clone(), &model));
    let stage = ParticleStage {
        grid: &grid,
        dt,
        u: &rec.u,
        bodies,
        node_sdf: &initial.statics().node_sdf,
        margin: initial.push_margin(),
        density: initial.density_inputs(&sys.geometry, bodies).map(|mut g| {
            g.band = band.as_ref();
            g
        }),
        step,
    };
    let replayed = stage.replay(pr)?;
    let mut pbar = after;
    if pbar.is_empty() {
        pbar = vec![Vec3::ZERO; replayed.end.len()];
    }
    let deep = band.as_ref().map(|b| b.deep.as_slice());
    let ghosts = initial.ghosts_at(bodies);
    let mut gbar = vec![Vec3::ZERO; ghosts.len()];
    // The step's φ_L as taped (the soft sums are read from it where φ̄ is left; the cells the
    // closing of air pockets changed have passed theirs on). Without it, summed again.
    surface::liquid_sdf_adjoint(
        &replayed.end,
        &ghosts,
        &pr.nearest,
        (!rec.phi.is_empty()).then_some(rec.phi.as_slice()),
        &grid,
        &model,
        deep,
        phi_bar,
        &mut pbar,
        &mut gbar,
    );
    surface::ghost_pose_adjoint(bodies, initial.displaced(), &gbar, pose);
    // Volume control: the solve's sources read the particles' density here.
    if rec.volume_control {
        let rate = settings.solver.volume_rate();
        let cell = grid.dx.powi(3);
        let base = band.as_ref().map(|b| b.density.as_slice());
        let ppc = settings.solver.particles_per_cell;
        let density = surface::particle_density(&replayed.end, &grid, ppc, base);
        let mut density_bar = vec![0.0; density.len()];
        for (&c, s) in sys.pressure.cell_of_row.iter().zip(rhs) {
            let c = c as usize;
            density_bar[c] = s * volume_source_derivative(rate, density[c], cell, dt);
        }
        surface::particle_density_adjoint(&replayed.end, &grid, ppc, &density_bar, &mut pbar);
    }
    clock.lap(Stage::Surface, times);
    let statics = &initial.statics().weights;
    stage.settle_adjoint(replayed, &mut pbar, pose, dual_faces, statics)?;
    clock.lap(Stage::Density, times);
    stage.advect_adjoint(pr, &mut pbar, ubar, pose);
    clock.lap(Stage::AdvectParticles, times);
    // The band's update before the advection: back to the particles' old indices.
    let start = match &pr.change {
        Some(change) => change.adjoint(&pbar),
        None => pbar,
    };
    clock.lap(Stage::Band, times);
    Ok(start)
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
