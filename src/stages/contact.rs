//! Rigid contact through rapier3d (feature `contact`; the settings, the "is contact
//! possible" test and the iteration that holds contact inside the projection,
//! [`hold_contact`], are always built).
//!
//! Given every body's velocity after the fluid's forces (pressure and gravity included),
//! `ContactWorld::step` hands the bodies to rapier for ONE step of length `Δt` with zero
//! gravity: rapier detects body–body and body–wall contact at the current poses, solves the
//! contact impulses (Coulomb friction and restitution from [`ContactSettings`]) and
//! integrates the positions. The new poses and velocities are written back.
//!
//! Rapier is configured so that, without contact, its step is our own stage-6 integrator:
//! the mass properties are set explicitly from [`RigidBody`] (the colliders carry no mass),
//! damping, gyroscopic forces, sleeping, the speed caps and (by default) CCD are all off.
//! The linear part is then `x + Δt·v` up to rounding. Rapier turns the orientation with
//! `normalise((1, h·ω/2)⊗q)` per solver substep (`h = Δt/4` with the default four substeps)
//! instead of our single `normalise(q + Δt/2·[0, ω]⊗q)`; both are first-order accurate
//! in `Δt` and differ by about `(|ω|Δt)³/12·(1 − 1/16)` radians per step (≈ 1e-8 rad at
//! `|ω| = 1`, `Δt = 0.005`; see `tests/physics/contact.rs`).
//!
//! Soft CCD (rapier's speculative contacts out to each pair's motion over the step) is on:
//! it only acts on a pair that would otherwise overlap at the end of the step, so a fast body
//! stops at a wall instead of sinking into it for a step, and free flight is untouched.
//!
//! The tank `[0, domain]` is closed by six fixed thick cuboids just outside it; their inner
//! faces are the planes `x = 0`, `x = domain.x`, `y = 0` (floor), `y = domain.y` (ceiling),
//! `z = 0` and `z = domain.z`. A kinematic body becomes a velocity-based kinematic rapier
//! body (contact sees its velocity, so it pushes the others at its speed), any other body
//! that is not dynamic a fixed one; neither is moved by contact nor written back.

use crate::error::Result;
#[cfg(feature = "contact")]
use crate::geometry::body::Motion;
use crate::geometry::body::RigidBody;
#[cfg(feature = "contact")]
use crate::math::Pose;
use crate::math::Twist;
use crate::math::Vec3;
#[cfg(feature = "contact")]
use rapier3d_f64::dynamics::{
    CoefficientCombineRule, MassProperties, RigidBodyBuilder, RigidBodyHandle,
};
#[cfg(feature = "contact")]
use rapier3d_f64::geometry::ColliderBuilder;
#[cfg(feature = "contact")]
use rapier3d_f64::pipeline::PhysicsWorld;
use serde::{Deserialize, Serialize};

/// Rigid contact settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ContactSettings {
    /// Resolve body–wall and body–body contact with rapier (inside the projection, see
    /// [`hold_contact`]). Default false: then a body that would leave the tank is an error.
    /// Needs the `contact` feature.
    pub enabled: bool,
    /// Coulomb friction coefficient. Default 0.5.
    pub friction: f64,
    /// Restitution. Default 0 (bodies in water do not bounce much).
    pub restitution: f64,
}

impl Default for ContactSettings {
    fn default() -> Self {
        ContactSettings { enabled: false, friction: 0.5, restitution: 0.0 }
    }
}

impl ContactSettings {
    /// Contact on, with the default friction and restitution:
    /// `Simulation::builder(..).contact(ContactSettings::on())`.
    pub fn on() -> Self {
        ContactSettings { enabled: true, ..ContactSettings::default() }
    }

    /// The settings' own checks: `(key, message)` of the first that fails.
    pub fn validate(&self) -> std::result::Result<(), (String, String)> {
        if !(self.friction.is_finite() && self.friction >= 0.0) {
            return Err((
                "contact.friction".into(),
                format!("must be a non-negative number, got {}", self.friction),
            ));
        }
        if !(self.restitution.is_finite() && (0.0..=1.0).contains(&self.restitution)) {
            return Err((
                "contact.restitution".into(),
                format!("must be in [0, 1], got {}", self.restitution),
            ));
        }
        if self.enabled && !cfg!(feature = "contact") {
            return Err((
                "contact.enabled".into(),
                "diffluid was built without the `contact` feature (rapier3d)".into(),
            ));
        }
        Ok(())
    }
}

/// Solves with contact impulses per step at most (see [`hold_contact`]); a contact that
/// still changes the velocities after them is left to the rigid stage. rapier's iterative,
/// soft contact solve answers each call with some noise (a few mm/s and mrad/s on a cube
/// resting flat), so the iteration seldom meets its tolerance exactly: a resting cube stirred
/// the liquid to 0.38 m/s with no extra solve, 0.06 with one, 0.018 with two, 0.0096 with four
/// and 0.0094 with eight.
pub const MAX_CONTACT_ITERATIONS: usize = 4;

/// What contact would do to the coupled bodies' velocities [v; ω] (one per body): the
/// velocity change.
pub type ContactChange<'a> = &'a dyn Fn(&[Twist]) -> Vec<Twist>;

/// What [`hold_contact`] did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ContactHold {
    /// The velocity change [Δv; Δω] per coupled body held as an impulse in the last solve.
    pub kick: Vec<Twist>,
    /// Extra solves made.
    pub iterations: usize,
    /// Largest velocity change contact still made after the last solve (0 when it converged).
    pub residual: f64,
}

/// Contact inside the projection. Resolving contact only after the projection would leave
/// the liquid divergence-free around a body velocity that contact then changes (a heavy body
/// resting on the floor pumped (1 − ρ/ρ_b)·g·Δt of flow into the liquid every step). So:
/// `solve(kick)` projects with the velocity change `kick` held as an impulse on the coupled
/// bodies and returns its result with the bodies' velocities after it; `change(velocities)`
/// says what contact would do to them; the two alternate until contact changes nothing by
/// more than `tolerance` (or [`MAX_CONTACT_ITERATIONS`] extra solves), so the liquid moves with
/// the body velocity that stands. With `change = None` (no contact possible) it is one solve.
pub fn hold_contact<T>(
    bodies: usize,
    mut solve: impl FnMut(&[Twist]) -> Result<(T, Vec<Twist>)>,
    change: Option<ContactChange<'_>>,
    tolerance: f64,
) -> Result<(T, ContactHold)> {
    let mut hold = ContactHold { kick: vec![[0.0; 6]; bodies], ..Default::default() };
    loop {
        let (out, velocities) = solve(&hold.kick)?;
        let Some(change) = change else { return Ok((out, hold)) };
        let c = change(&velocities);
        let largest = c.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs()));
        if largest <= tolerance {
            return Ok((out, hold));
        }
        if hold.iterations == MAX_CONTACT_ITERATIONS {
            hold.residual = largest;
            return Ok((out, hold));
        }
        for (k, c) in hold.kick.iter_mut().zip(&c) {
            for d in 0..6 {
                k[d] += c[d];
            }
        }
        hold.iterations += 1;
    }
}

/// Whether any body can touch a wall or another body within the next `dt`: each body's
/// bounding box, grown by the farthest any of its points can move (|v|·Δt + |ω|·Δt times
/// the box diagonal, which bounds the distance from the centre of mass) plus a margin of a
/// hundredth of the diagonal as a safety margin, reaches a wall or another grown box.
/// (rapier's predictive contacts start further out, but act only on bodies that would close
/// the gap within the step, which the reach covers.) When none can, contact
/// is no work: the bodies fly freely (the same integration as without contact), and rapier
/// is not called.
pub fn contact_possible(bodies: &[RigidBody], domain: Vec3, dt: f64) -> bool {
    let grown: Vec<(Vec3, Vec3, bool)> = bodies
        .iter()
        .map(|b| {
            let (lo, hi) = b.bounds();
            let diag = (hi - lo).length();
            let moving = b.motion != crate::geometry::body::Motion::Fixed;
            let reach = if moving { (b.v.length() + b.w.length() * diag) * dt } else { 0.0 };
            let pad = reach + 0.01 * diag;
            (lo - Vec3::splat(pad), hi + Vec3::splat(pad), moving)
        })
        .collect();
    let touches_wall = |(lo, hi, moving): &(Vec3, Vec3, bool)| {
        *moving && (lo.min_element() <= 0.0 || (*hi - domain).max_element() >= 0.0)
    };
    if grown.iter().any(touches_wall) {
        return true;
    }
    grown.iter().enumerate().any(|(i, a)| {
        grown[i + 1..].iter().any(|b| {
            (a.2 || b.2)
                && (0..3).all(|d| {
                    crate::math::comp(a.0, d) <= crate::math::comp(b.1, d)
                        && crate::math::comp(b.0, d) <= crate::math::comp(a.1, d)
                })
        })
    })
}

/// Resolves body–wall and body–body contact after the fluid step.
#[cfg(feature = "contact")]
pub struct ContactWorld {
    /// Rapier's state: bodies, colliders, broad and narrow phases, solver parameters.
    world: PhysicsWorld,
    /// The rapier body of each [`RigidBody`], by index in the slice given to [`Self::new`].
    handles: Vec<RigidBodyHandle>,
    /// Whether each body is dynamic in rapier (the others are fixed and never written back).
    dynamic: Vec<bool>,
}

#[cfg(feature = "contact")]
impl ContactWorld {
    /// A world with the tank walls and the bodies.
    pub fn new(domain: Vec3, bodies: &[RigidBody], settings: &ContactSettings) -> ContactWorld {
        let mut world = PhysicsWorld::new();
        // Gravity was already applied by the fluid step.
        world.gravity = Vec3::ZERO;

        let params = &mut world.integration_parameters;
        // Rapier's tolerances (prediction distance, slop, corrective speed) scale with the
        // length unit; tie it to the smallest body instead of rapier's human-sized 1 m.
        params.length_unit = length_unit(domain, bodies);
        // No speed cap: the step must keep the velocities the fluid step produced.
        params.normalized_max_linear_velocity = f64::MAX;
        // CCD off unless asked for (see `set_ccd`): with it, rapier clamps the motion of a fast
        // body at its time of impact, which is no longer `x + Δt·v`.
        params.max_ccd_substeps = 0;

        let friction = settings.friction;
        let restitution = settings.restitution;
        // Walls and bodies carry the same coefficients, so any combine rule gives them back;
        // `Max` is explicit about it.
        let material = |c: ColliderBuilder| {
            c.friction(friction)
                .restitution(restitution)
                .friction_combine_rule(CoefficientCombineRule::Max)
                .restitution_combine_rule(CoefficientCombineRule::Max)
        };

        // The six walls: thick fixed cuboids overlapping at the edges and corners, so that
        // nothing slips out between them.
        let t = domain.max_element().max(f64::MIN_POSITIVE);
        let h = 0.5 * domain;
        let c = h;
        let walls = [
            // (half-extents, centre)
            (Vec3::new(h.x + t, 0.5 * t, h.z + t), Vec3::new(c.x, -0.5 * t, c.z)),
            (Vec3::new(h.x + t, 0.5 * t, h.z + t), Vec3::new(c.x, domain.y + 0.5 * t, c.z)),
            (Vec3::new(0.5 * t, h.y + t, h.z + t), Vec3::new(-0.5 * t, c.y, c.z)),
            (Vec3::new(0.5 * t, h.y + t, h.z + t), Vec3::new(domain.x + 0.5 * t, c.y, c.z)),
            (Vec3::new(h.x + t, h.y + t, 0.5 * t), Vec3::new(c.x, c.y, -0.5 * t)),
            (Vec3::new(h.x + t, h.y + t, 0.5 * t), Vec3::new(c.x, c.y, domain.z + 0.5 * t)),
        ];
        let walls_body = world.insert_body(RigidBodyBuilder::fixed());
        for (half, centre) in walls {
            let wall =
                ColliderBuilder::cuboid(half.x, half.y, half.z).translation(centre).density(0.0);
            world.insert_collider(material(wall), Some(walls_body));
        }

        let mut handles = Vec::with_capacity(bodies.len());
        let mut dynamic = Vec::with_capacity(bodies.len());
        for b in bodies {
            // Rapier's body frame is our shape frame: the collider sits at identity and the
            // centre of mass is the same local point.
            let builder = if b.motion == Motion::Dynamic {
                RigidBodyBuilder::dynamic()
                    .additional_mass_properties(MassProperties::with_inertia_matrix(
                        b.local_com,
                        b.mass,
                        b.local_inertia,
                    ))
                    .linear_damping(0.0)
                    .angular_damping(0.0)
                    // Our integrator keeps ω between fluid steps; so must rapier.
                    .gyroscopic_forces_enabled(false)
                    .allow_fast_rotation(true)
                    .can_sleep(false)
                    .ccd_enabled(false)
                    // Soft CCD: speculative contacts out to the relative motion over the
                    // step (capped at the tank size), so a fast body stops at a surface
                    // instead of sinking into it for a step. It leaves free flight alone.
                    .soft_ccd_prediction(t)
                    .linvel(b.v)
                    .angvel(b.w)
            } else if b.motion == Motion::Kinematic {
                // It moves along its own velocity, and contact sees that velocity: a paddle
                // pushes a ball at its speed instead of stepping into it and having the
                // overlap pushed out.
                RigidBodyBuilder::kinematic_velocity_based().linvel(b.v).angvel(b.w)
            } else {
                RigidBodyBuilder::fixed()
            };
            let collider = ColliderBuilder::new(b.shape.clone()).density(0.0);
            let (handle, _) = world.insert(builder.pose(b.pose()), material(collider));
            handles.push(handle);
            dynamic.push(b.motion == Motion::Dynamic);
        }

        ContactWorld { world, handles, dynamic }
    }

    /// Turns continuous collision detection on or off (off by default). With it, a dynamic
    /// body fast enough to tunnel is swept against the walls and the other bodies, and its
    /// motion is clamped at the first time of impact.
    pub fn set_ccd(&mut self, on: bool) {
        self.world.integration_parameters.max_ccd_substeps = usize::from(on);
        for (&h, &dynamic) in self.handles.iter().zip(&self.dynamic) {
            if dynamic {
                self.world.bodies[h].enable_ccd(on);
            }
        }
    }

    /// Moves the bodies over `dt` from their current state, resolving contact.
    pub fn step(&mut self, bodies: &mut [RigidBody], dt: f64) {
        assert_eq!(bodies.len(), self.handles.len(), "ContactWorld built for other bodies");
        for (b, &h) in bodies.iter().zip(&self.handles) {
            let rb = &mut self.world.bodies[h];
            // `set_position` only flags a change when the pose differs.
            rb.set_position(b.pose(), true);
            if matches!(b.motion, Motion::Dynamic | Motion::Kinematic) {
                rb.set_linvel(b.v, true);
                rb.set_angvel(b.w, true);
            }
        }

        self.world.integration_parameters.dt = dt;
        self.world.step();

        for ((b, &h), &dynamic) in bodies.iter_mut().zip(&self.handles).zip(&self.dynamic) {
            if !dynamic {
                continue;
            }
            let rb = &self.world.bodies[h];
            let pose: Pose = *rb.position();
            b.q = pose.rotation;
            b.x = pose.transform_point(b.local_com);
            b.v = rb.linvel();
            b.w = rb.angvel();
        }
    }
}

/// Rapier's length unit: the smallest body's bounding diameter, at most 1 m and at most the
/// smallest side of the tank.
#[cfg(feature = "contact")]
fn length_unit(domain: Vec3, bodies: &[RigidBody]) -> f64 {
    let smallest = bodies
        .iter()
        .map(|b| 2.0 * b.shape.compute_local_bounding_sphere().radius())
        .filter(|d| d.is_finite() && *d > 0.0)
        .fold(f64::INFINITY, f64::min);
    let side = domain.min_element();
    let unit = smallest.min(1.0);
    if side > 0.0 {
        unit.min(side)
    } else {
        unit
    }
}

/// What each differentiated body's inputs to a contact map contribute: ∂L/∂[v; ω] (the
/// velocity the map starts from), ∂L/∂[δx; δθ] of the pose (θ the world-frame tangent,
/// q → exp(θ)·q) and ∂L/∂m (the inertia scaling with the mass, as
/// [`RigidBody::set_mass`] does).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ContactInputAdjoint {
    /// ∂L/∂[v; ω].
    pub velocity: Twist,
    /// ∂L/∂[δx; δθ].
    pub pose: Twist,
    /// ∂L/∂m.
    pub mass: f64,
}

/// A map through rapier's contact step, from the bodies and the velocities of the moved
/// ones (see [`contact_adjoint`]) to a vector of outputs.
pub type ContactMap<'a> = dyn Fn(&[RigidBody], &[Twist]) -> Vec<f64> + Sync + 'a;

/// Inputs per body contact does not move (a kinematic or external one): [v; ω], [δx; δθ].
const POSED_INPUTS: usize = 12;

/// Inputs per body a contact map is differentiated in: [v; ω], [δx; δθ], then m.
const CONTACT_INPUTS: usize = POSED_INPUTS + 1;

/// The central differences' first step in [`contact_adjoint`]: m/s, rad/s, m and rad, and a
/// fraction of the mass. rapier's solve is a fixed sequence of substeps and iterations, so
/// its step is smooth in its inputs wherever no contact starts, ends or changes between
/// sticking and sliding; but a body resting on a surface settles at the depth where rapier
/// stops correcting penetration, within a hair of that kink. A ball pushed along the floor
/// under water (8 steps) had its gradient 10% off with a step of 1e-7 and 50% off with 1e-6,
/// against 3e-7 with 1e-8 (and 4e-6 with 1e-9, where rounding, of order 1e-8 relative at
/// 1e-8, takes over).
const CONTACT_STEP: f64 = 1e-8;

/// How many steps [`contact_adjoint`] tries, each a tenth of the last: it takes a smaller one
/// while the one-sided slopes of the seeded map disagree (a kink within the step) and come
/// closer at the smaller step (where they part further, the smaller step is rounding). A
/// ball resting on the floor under water pushed by control forces (10 steps) had its
/// gradient 3% off on the vertical force, 14% on v_y and 13% on the mass with the step
/// fixed at 1e-8, and within 2e-5 with it refined.
const CONTACT_REFINEMENTS: usize = 3;

/// The adjoint of a map through rapier's contact step, `f(bodies, velocities)` (the
/// `bodies` with the velocities `velocities` of the bodies `moved`, one per entry, replacing
/// theirs), seeded with `seed` on its outputs: per body of `moved`, `seed · ∂f/∂input` for
/// each of its 13 inputs ([`ContactInputAdjoint`]), and per body of `posed` (bodies that
/// contact does not move, a kinematic paddle say) for its velocity and pose (their own, in
/// `bodies`; no mass); by central differences of `f` itself. rapier's contact solve (its
/// substeps, the soft constraints, Coulomb friction sticking or sliding) has no adjoint of
/// its own; differencing it gives the derivative of the very step the forward pass took, at 26 calls of `f` per moved body and 24 per posed
/// one (run in parallel), more where the one-sided slopes disagree (the step is then cut
/// tenfold, twice at most). Where a contact starts or ends within the smallest step the map
/// has a kink and this is the mean of its two sides.
pub fn contact_adjoint(
    bodies: &[RigidBody],
    moved: &[usize],
    velocities: &[Twist],
    posed: &[usize],
    seed: &[f64],
    f: &ContactMap<'_>,
) -> (Vec<ContactInputAdjoint>, Vec<ContactInputAdjoint>) {
    use crate::math::TwistParts;
    use rayon::prelude::*;
    // The map of `bodies` with the moved ones at `velocities` (it reads those, not theirs).
    let run = |mut bodies: Vec<RigidBody>, velocities: &[Twist]| {
        for (&i, v) in moved.iter().zip(velocities) {
            (bodies[i].v, bodies[i].w) = (v.linear(), v.angular());
        }
        f(&bodies, velocities)
    };
    // Input `input` of body `i` (`slot` its place in `velocities` if moved) moved by h.
    let at = |i: usize, slot: Option<usize>, input: usize, h: f64| {
        let (mut bodies, mut velocities) = (bodies.to_vec(), velocities.to_vec());
        let b = &mut bodies[i];
        match (input, slot) {
            (0..=5, Some(k)) => velocities[k][input] += h,
            (0..=2, None) => b.v[input] += h,
            (3..=5, None) => b.w[input - 3] += h,
            (6..=8, _) => b.x[input - 6] += h,
            (9..=11, _) => {
                let mut axis = Vec3::ZERO;
                axis[input - 9] = h;
                b.q = (crate::math::Rotation::from_scaled_axis(axis) * b.q).normalize();
            }
            _ => b.set_mass(b.mass + h),
        }
        run(bodies, &velocities)
    };
    let moved_jobs = moved
        .iter()
        .enumerate()
        .flat_map(|(k, &i)| (0..CONTACT_INPUTS).map(move |input| (i, Some(k), input)));
    let posed_jobs =
        posed.iter().flat_map(|&i| (0..POSED_INPUTS).map(move |input| (i, None, input)));
    let jobs: Vec<(usize, Option<usize>, usize)> = moved_jobs.chain(posed_jobs).collect();
    // The map where it is, for the one-sided slopes.
    let at_base = run(bodies.to_vec(), velocities);
    let dot = |a: &[f64], b: &[f64]| -> f64 {
        seed.iter().zip(a.iter().zip(b)).map(|(s, (x, y))| s * (x - y)).sum()
    };
    // The one-sided slopes of the seeded map at step h for input `input` of body `i`.
    let sides = |i: usize, slot: Option<usize>, input: usize, h: f64| {
        let (plus, minus) = (at(i, slot, input, h), at(i, slot, input, -h));
        (dot(&plus, &at_base) / h, dot(&at_base, &minus) / h)
    };
    let unit = |i: usize, input: usize| if input == POSED_INPUTS { bodies[i].mass } else { 1.0 };
    let first: Vec<(f64, f64)> = jobs
        .par_iter()
        .map(|&(i, slot, input)| sides(i, slot, input, CONTACT_STEP * unit(i, input)))
        .collect();
    // Slopes this far under the largest are the differences' rounding.
    let largest = first.iter().fold(0.0f64, |m, (r, l)| m.max(r.abs()).max(l.abs()));
    let kinked = |(r, l): (f64, f64)| (r - l).abs() > 1e-2 * r.abs().max(l.abs()) + 1e-7 * largest;
    let slopes: Vec<f64> = jobs
        .par_iter()
        .zip(&first)
        .map(|(&(i, slot, input), &(r, l))| {
            // A kink within the step: a tenth of it, at most twice, kept where the two sides
            // come closer (where they part further, the finer step is rounding).
            let (mut best, mut h) = ((r, l), CONTACT_STEP * unit(i, input));
            for _ in 1..CONTACT_REFINEMENTS {
                if !kinked(best) {
                    break;
                }
                h *= 0.1;
                let finer = sides(i, slot, input, h);
                if (finer.0 - finer.1).abs() >= (best.0 - best.1).abs() {
                    break;
                }
                best = finer;
            }
            0.5 * (best.0 + best.1)
        })
        .collect();
    let (of_moved, of_posed) = slopes.split_at(moved.len() * CONTACT_INPUTS);
    let adjoint = |s: &[f64]| ContactInputAdjoint {
        velocity: std::array::from_fn(|d| s[d]),
        pose: std::array::from_fn(|d| s[6 + d]),
        mass: s.get(POSED_INPUTS).copied().unwrap_or(0.0),
    };
    let moved_adjoints = of_moved.chunks(CONTACT_INPUTS).map(adjoint).collect();
    let posed_adjoints = of_posed.chunks(POSED_INPUTS).map(adjoint).collect();
    (moved_adjoints, posed_adjoints)
}
