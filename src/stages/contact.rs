//! Rigid contact through rapier3d (feature `contact`).
//!
//! After the fluid step has updated every body's velocity (pressure and gravity included),
//! [`ContactWorld::step`] hands the bodies to rapier for ONE step of length `Δt` with zero
//! gravity: rapier detects body–body and body–wall contact at the current poses, solves the
//! contact impulses (Coulomb friction and restitution from the scene's [`Contact`]) and
//! integrates the positions. The new poses and velocities are written back.
//!
//! Rapier is configured so that, without contact, its step is our own stage-6 integrator:
//! the mass properties are set explicitly from [`RigidBody`] (the colliders carry no mass),
//! damping, gyroscopic forces, sleeping, the speed caps and (by default) CCD are all off.
//! The linear part is then `x + Δt·v` up to rounding. Rapier turns the orientation with
//! `normalise((1, h·ω/2)⊗q)` per solver substep (`h = Δt/4` with the default four substeps)
//! instead of our single `normalise(q + Δt/2·[0, ω]⊗q)`; both are first-order accurate
//! in `Δt` and differ by about `(|ω|Δt)³/12·(1 − 1/16)` radians per step (≈ 1e-8 rad at
//! `|ω| = 1`, `Δt = 0.005`; see `tests/contact.rs`).
//!
//! Soft CCD (rapier's speculative contacts out to each pair's motion over the step) is on:
//! it only acts on a pair that would otherwise overlap at the end of the step, so a fast body
//! stops at a wall instead of sinking into it for a step, and free flight is untouched.
//!
//! The tank `[0, domain]` is closed by six fixed thick cuboids just outside it; their inner
//! faces are the planes `x = 0`, `x = domain.x`, `y = 0` (floor), `y = domain.y` (ceiling),
//! `z = 0` and `z = domain.z`. A body that is not dynamic becomes a fixed rapier body: it
//! pushes the others but is never moved nor written back.

use crate::experiments::scene::Contact;
use crate::geometry::body::RigidBody;
use crate::math::{Pose, Vec3};
use rapier3d_f64::dynamics::{
    CoefficientCombineRule, MassProperties, RigidBodyBuilder, RigidBodyHandle,
};
use rapier3d_f64::geometry::ColliderBuilder;
use rapier3d_f64::pipeline::PhysicsWorld;

/// Resolves body–wall and body–body contact after the fluid step.
pub struct ContactWorld {
    /// Rapier's state: bodies, colliders, broad and narrow phases, solver parameters.
    world: PhysicsWorld,
    /// The rapier body of each [`RigidBody`], by index in the slice given to [`Self::new`].
    handles: Vec<RigidBodyHandle>,
    /// Whether each body is dynamic in rapier (the others are fixed and never written back).
    dynamic: Vec<bool>,
}

impl ContactWorld {
    /// A world with the tank walls and the bodies.
    pub fn new(domain: Vec3, bodies: &[RigidBody], settings: &Contact) -> ContactWorld {
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
            let builder = if b.dynamic {
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
            } else {
                RigidBodyBuilder::fixed()
            };
            let collider = ColliderBuilder::new(b.shape.clone()).density(0.0);
            let (handle, _) = world.insert(builder.pose(b.pose()), material(collider));
            handles.push(handle);
            dynamic.push(b.dynamic);
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
            if b.dynamic {
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
