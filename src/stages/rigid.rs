//! Stage [`Rigid`](super::Stage::Rigid): the bodies integrated over the step (x += Δt·v, the
//! quaternion step, the dynamic bodies' angular momentum carried to their new orientation),
//! or moved by rapier when contact acts; and its adjoint.

use crate::error::{Error, Result};
use crate::geometry::body::{
    carry_angular_momentum_adjoint, quat_step, quat_step_adjoint, BodyState, Motion, RigidBody,
};
use crate::math::so3;
use crate::math::{add_twist, twist, Rotation, Twist, TwistParts, Vec3};
use crate::stages::contact::{contact_adjoint, ContactSettings};

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

    /// Adds ∂L/∂[δx; δθ] of the body's pose at orientation `q` (θ the world-frame tangent,
    /// q → exp(θ)·q) to ∂L/∂x and ∂L/∂q.
    pub fn add_pose(&mut self, q: Rotation, pose: &Twist) {
        self.x += pose.linear();
        self.q += so3::from_tangent_gradient(q, pose.angular());
    }
}

/// Where a body may be after the step.
#[derive(Clone, Copy, Debug)]
pub struct Tank {
    /// The tank's size, m.
    pub size: Vec3,
    /// How far an external body may sit in a wall, m.
    pub external_reach: f64,
}

/// Integrates the bodies over `dt`: through rapier with `contact` (its settings) when
/// contact acts, each body on its own otherwise. A body that leaves `tank` is an error
/// naming step `step`.
pub fn integrate(
    bodies: &mut [RigidBody],
    dt: f64,
    tank: Tank,
    contact: Option<&ContactSettings>,
    step: usize,
) -> Result<()> {
    #[cfg(feature = "contact")]
    if let Some(settings) = contact {
        // A fresh world per step: the fluid step changed every velocity, and rebuilding a
        // handful of colliders costs microseconds.
        let before: Vec<_> = bodies.iter().map(|b| b.q).collect();
        crate::stages::contact::ContactWorld::new(tank.size, bodies, settings).step(bodies, dt);
        // rapier's step keeps ω (its gyroscopic forces are off, see contact.rs): carry the
        // dynamic bodies' angular momentum to their new orientation, as our integrator does.
        for (b, q0) in bodies.iter_mut().zip(&before) {
            if b.motion == Motion::Dynamic {
                b.w =
                    crate::geometry::body::carry_angular_momentum(&b.local_inertia, *q0, b.q, b.w);
            }
        }
        // rapier holds kinematic bodies fixed at their pose; they move along their own
        // velocity.
        for b in bodies.iter_mut().filter(|b| b.motion == Motion::Kinematic) {
            b.integrate(dt);
        }
        return Ok(());
    }
    let _ = contact;
    for b in bodies.iter_mut() {
        b.integrate(dt);
        // An external body is where the caller's engine put it, and may sit a little into a
        // wall (rapier's contact leaves a few micrometres of overlap with the floor it rests
        // on).
        let reach = if b.motion == Motion::External { tank.external_reach } else { 0.0 };
        let (lo, hi) = b.bounds();
        if lo.min_element() < -reach || (hi - tank.size).max_element() > reach {
            return Err(Error::BodyLeftTank {
                step,
                body: b.name.clone(),
                bounds: (lo.to_array(), hi.to_array()),
            });
        }
    }
    Ok(())
}

/// Adjoint of [`integrate`] without contact (see [`integrate_contact_adjoint`] for rapier's):
/// from the adjoints `after` of the bodies' states after the step, with `start` their
/// states at its start and `v_after` their [v; ω] after the pressure solve (the
/// integration's input), the adjoints of the start poses (`x`, `q`; `v`, `w` zero) and
/// ∂L/∂[v; ω] after the solve.
pub fn integrate_adjoint(
    bodies: &[RigidBody],
    start: &[BodyState],
    v_after: &[Twist],
    after: &[BodyAdjoint],
    dt: f64,
) -> (Vec<BodyAdjoint>, Vec<Twist>) {
    let mut out = vec![BodyAdjoint::zero(); bodies.len()];
    let mut vbar: Vec<Twist> = vec![[0.0; 6]; bodies.len()];
    for (i, b) in bodies.iter().enumerate() {
        let a = &after[i];
        out[i].x = a.x;
        out[i].q = a.q;
        if !b.motion.integrated_here() {
            // Held still, or moved by the caller: its pose after the step is its pose before.
            vbar[i] = twist(a.v, a.w);
            continue;
        }
        let va = v_after[i];
        let (q0, w_after) = (start[i].q, va.angular());
        let q1 = quat_step(q0, w_after, dt);
        // A dynamic body carries its angular momentum to the new orientation.
        let (mut qbar1, mut w_carry, mut q0_carry) =
            (a.q, a.w, Rotation::from_xyzw(0.0, 0.0, 0.0, 0.0));
        if b.motion == Motion::Dynamic {
            let (t0, t1, wb) =
                carry_angular_momentum_adjoint(&b.local_inertia, q0, q1, w_after, a.w);
            qbar1 = a.q + so3::from_tangent_gradient(q1, t1);
            q0_carry = so3::from_tangent_gradient(q0, t0);
            w_carry = wb;
        }
        let (qbar, wbar) = quat_step_adjoint(q0, w_after, dt, qbar1);
        out[i].q = qbar + q0_carry;
        let vb = a.v + dt * a.x;
        let wb = w_carry + wbar;
        vbar[i] = twist(vb, wb);
    }
    (out, vbar)
}

/// Adjoint of [`integrate`] through rapier's contact step (`contact` its settings): as
/// [`integrate_adjoint`], with the dynamic bodies' poses, velocities and masses
/// differentiated through the step rapier took (by central differences of it, see
/// [`contact_adjoint`]) instead of free flight, and the velocities and poses of the kinematic
/// and external bodies through what they do to the dynamic ones. Returns the adjoints
/// of the start poses, ∂L/∂[v; ω] after the solve, and ∂L/∂m per body.
pub fn integrate_contact_adjoint(
    bodies: &[RigidBody],
    start: &[BodyState],
    v_after: &[Twist],
    after: &[BodyAdjoint],
    dt: f64,
    tank: Tank,
    contact: &ContactSettings,
) -> (Vec<BodyAdjoint>, Vec<Twist>, Vec<f64>) {
    let (mut out, mut vbar) = integrate_adjoint(bodies, start, v_after, after, dt);
    let mut mass = vec![0.0; bodies.len()];
    let dynamic: Vec<usize> =
        (0..bodies.len()).filter(|&i| bodies[i].motion == Motion::Dynamic).collect();
    if dynamic.is_empty() {
        return (out, vbar, mass);
    }
    let mut at_start = bodies.to_vec();
    for ((b, s), v) in at_start.iter_mut().zip(start).zip(v_after) {
        b.set_state(s);
        (b.v, b.w) = (v.linear(), v.angular());
    }
    let velocities: Vec<Twist> = dynamic.iter().map(|&i| v_after[i]).collect();
    // The dynamic bodies' states after the step: x, q (the quaternion embedding the adjoint
    // is given in), v, ω.
    let seed: Vec<f64> = dynamic
        .iter()
        .flat_map(|&i| state_entries(after[i].x, after[i].q, after[i].v, after[i].w))
        .collect();
    let step = |bs: &[RigidBody], _: &[Twist]| {
        let mut bs = bs.to_vec();
        // rapier's step never fails; a body it leaves outside the tank is the forward
        // pass's error, not the adjoint's.
        let _ = integrate(&mut bs, dt, tank, Some(contact), 0);
        dynamic.iter().flat_map(|&i| state_entries(bs[i].x, bs[i].q, bs[i].v, bs[i].w)).collect()
    };
    // The bodies contact does not move: kinematic ones (rapier sees their velocity) and
    // external ones (held fixed at their pose).
    let posed: Vec<usize> = (0..bodies.len())
        .filter(|&i| matches!(bodies[i].motion, Motion::Kinematic | Motion::External))
        .collect();
    let (adjoints, poses) = contact_adjoint(&at_start, &dynamic, &velocities, &posed, &seed, &step);
    for (&i, a) in dynamic.iter().zip(&adjoints) {
        out[i] = BodyAdjoint::zero();
        out[i].add_pose(start[i].q, &a.pose);
        vbar[i] = a.velocity;
        mass[i] = a.mass;
    }
    for (&i, g) in posed.iter().zip(&poses) {
        out[i].add_pose(start[i].q, &g.pose);
        add_twist(&mut vbar[i], &g.velocity);
    }
    (out, vbar, mass)
}

/// A body's state, or its adjoint, as 13 numbers: x, q (the quaternion embedding), v, ω.
fn state_entries(x: Vec3, q: Rotation, v: Vec3, w: Vec3) -> impl Iterator<Item = f64> {
    x.to_array().into_iter().chain(q.to_array()).chain(v.to_array()).chain(w.to_array())
}
