//! Stage [`Forces`](super::Stage::Forces) and gravity in
//! [`AdvectVelocity`](super::Stage::AdvectVelocity): gravity on the liquid, and gravity plus each body's external
//! force and torque on the bodies. On the liquid they only add an offset to the velocity, so
//! the adjoint is the identity (paper, eq. 3); on a body the torque acts through the world
//! inertia, which turns with the body, so it has a pose derivative.

use crate::geometry::body::RigidBody;
use crate::geometry::grid::Mac;
use crate::math::{twist, Twist, TwistParts, Vec3};
use rayon::prelude::*;

/// Adds `dt·g` to every face (gravity). Its adjoint is the identity.
pub fn add_gravity(u: &mut Mac, gravity: [f64; 3], dt: f64) {
    for (axis, c) in u.c.iter_mut().enumerate() {
        let dv = gravity[axis] * dt;
        if dv != 0.0 {
            c.par_iter_mut().for_each(|x| *x += dv);
        }
    }
}

/// A body's [v; ω] after gravity `g` and its external force and torque act for `dt`:
/// v + Δt·(g + F/m), ω + Δt·I_w⁻¹·τ.
pub fn body_velocity(b: &RigidBody, g: Vec3, dt: f64) -> Twist {
    let v = b.v + dt * (g + b.force / b.mass);
    let mut w = b.w;
    if b.torque != Vec3::ZERO {
        w += dt * (b.world_inertia().inverse() * b.torque);
    }
    twist(v, w)
}

/// What a body's external force and torque alone add to its [v; ω] in `dt`:
/// Δt·[F/m; I_w⁻¹·τ]. Scaling the body's mass and inertia by s scales it by 1/s (the mass
/// gradient reads it).
pub fn load_velocity(b: &RigidBody, dt: f64) -> Twist {
    let v = dt * b.force / b.mass;
    let w = if b.torque == Vec3::ZERO {
        Vec3::ZERO
    } else {
        dt * (b.world_inertia().inverse() * b.torque)
    };
    twist(v, w)
}

/// The orientation part of [`body_velocity`]'s adjoint: given ∂L/∂ω after the stage, the
/// gradient ∂L/∂θ (world-frame tangent) of Δt·I_w(θ)⁻¹·τ. With I_w⁻¹ → I_w⁻¹ + \[δθ\]×I_w⁻¹ −
/// I_w⁻¹\[δθ\]× and y = I_w⁻¹τ: Δt·(y × ω̄ − τ × I_w⁻¹ω̄). (The v and ω parts are the identity.)
pub fn body_velocity_pose_adjoint(b: &RigidBody, dt: f64, w_bar: Vec3) -> Vec3 {
    if b.torque == Vec3::ZERO {
        return Vec3::ZERO;
    }
    let inv = b.world_inertia().inverse();
    let y = inv * b.torque;
    dt * (y.cross(w_bar) - b.torque.cross(inv * w_bar))
}

/// Adjoint of [`body_velocity`] for a body whose [v; ω] after the stage has the adjoint
/// `bar`: [v̄; ω̄] before it is `bar` itself (gravity and the loads add a constant); returns
/// ∂L/∂(mass scale) of the loads' part, −bar·Δt·[F/m; I_w⁻¹τ]/m (the inertia scales with
/// the mass), and ∂L/∂[δx; δθ] of the body's pose, the torque's through the world inertia.
pub fn body_velocity_adjoint(b: &RigidBody, dt: f64, bar: &Twist) -> (f64, Twist) {
    let dv = load_velocity(b, dt);
    let load: f64 = (0..6).map(|d| bar[d] * dv[d]).sum();
    let gw = body_velocity_pose_adjoint(b, dt, bar.angular());
    (-load / b.mass, twist(Vec3::ZERO, gw))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::{Pose, Rotation, SharedShape};

    /// ⟨ω̄, ∂(Δt·I_w⁻¹τ)/∂θ⟩ against central differences over world-frame rotations.
    #[test]
    fn torque_pose_adjoint_matches_central_differences() {
        let pose = Pose::from_parts(
            Vec3::new(0.2, 0.3, 0.1),
            Rotation::from_axis_angle(Vec3::new(0.4, 1.0, -0.3).normalize(), 0.8),
        );
        let mut b =
            RigidBody::with_density("b".into(), SharedShape::cuboid(0.3, 0.1, 0.2), pose, 700.0);
        b.torque = Vec3::new(0.7, -1.3, 0.4);
        let (dt, w_bar) = (0.01, Vec3::new(0.3, 0.5, -0.9));
        let g = body_velocity_pose_adjoint(&b, dt, w_bar);
        let q0 = b.q;
        let eps = 1e-6;
        for k in 0..3 {
            let mut at = |s: f64| {
                b.q = (Rotation::from_scaled_axis(s * eps * crate::math::unit(k)) * q0).normalize();
                let v = body_velocity(&b, Vec3::ZERO, dt);
                v.angular().dot(w_bar)
            };
            let fd = (at(1.0) - at(-1.0)) / (2.0 * eps);
            let ad = crate::math::comp(g, k);
            assert!((fd - ad).abs() <= 1e-9 * fd.abs().max(1e-6), "θ[{k}]: {ad} vs {fd}");
        }
    }
}
