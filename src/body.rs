//! Rigid bodies: parry shape, mass properties, pose, and the quaternion update (stage 6).
//!
//! A body's state is the world position of its centre of mass `x`, the orientation `q` of
//! its shape frame, its linear velocity `v` and angular velocity `ω` (world frame). The
//! shape's local origin sits at `x − q·c` where `c` is the centre of mass in the shape frame.
//! Mass and inertia come from parry's mass properties; the world inertia is `R·I·Rᵀ`.

use crate::math::{Pose, Rotation, SharedShape, Vec3};
use parry3d_f64::math::Matrix as Mat3;

/// A rigid body with its state.
#[derive(Clone)]
pub struct RigidBody {
    /// Name from the scene (for outputs).
    pub name: String,
    /// Geometry in the shape frame.
    pub shape: SharedShape,
    /// Centre of mass in the shape frame.
    pub local_com: Vec3,
    /// Mass, kg.
    pub mass: f64,
    /// Inertia tensor about the centre of mass, in the shape frame, kg·m².
    pub local_inertia: Mat3,
    /// False for a body that does not move (an obstacle that still couples through J with
    /// zero velocity).
    pub dynamic: bool,
    /// World position of the centre of mass.
    pub x: Vec3,
    /// Orientation of the shape frame (unit quaternion).
    pub q: Rotation,
    /// Linear velocity.
    pub v: Vec3,
    /// Angular velocity, world frame.
    pub w: Vec3,
}

impl std::fmt::Debug for RigidBody {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RigidBody")
            .field("name", &self.name)
            .field("mass", &self.mass)
            .field("x", &self.x)
            .field("q", &self.q)
            .field("v", &self.v)
            .field("w", &self.w)
            .finish_non_exhaustive()
    }
}

impl RigidBody {
    /// A body from a shape at a pose, with mass properties at `density` (kg/m³).
    pub fn new(name: String, shape: SharedShape, pose: Pose, density: f64) -> RigidBody {
        let mp = shape.mass_properties(density);
        let r = Mat3::from_quat(mp.principal_inertia_local_frame);
        let local_inertia = r * Mat3::from_diagonal(mp.principal_inertia()) * r.transpose();
        RigidBody {
            name,
            x: pose.transform_point(mp.local_com),
            q: pose.rotation,
            local_com: mp.local_com,
            mass: mp.mass(),
            local_inertia,
            shape,
            dynamic: true,
            v: Vec3::ZERO,
            w: Vec3::ZERO,
        }
    }

    /// Scales mass and inertia so the body weighs `mass` kg.
    pub fn set_mass(&mut self, mass: f64) {
        let s = mass / self.mass;
        self.mass = mass;
        self.local_inertia *= s;
    }

    /// Volume of the shape, m³.
    pub fn volume(&self) -> f64 {
        self.shape.mass_properties(1.0).mass()
    }

    /// Pose of the shape frame.
    pub fn pose(&self) -> Pose {
        Pose::from_parts(self.x - self.q * self.local_com, self.q)
    }

    /// Signed distance at a world point (negative inside).
    #[inline]
    pub fn sdf(&self, p: Vec3) -> f64 {
        self.shape.distance_to_point(&self.pose(), p, false)
    }

    /// World inertia tensor R·I·Rᵀ about the centre of mass.
    pub fn world_inertia(&self) -> Mat3 {
        let r = Mat3::from_quat(self.q);
        r * self.local_inertia * r.transpose()
    }

    /// Rigid velocity at a world point.
    #[inline]
    pub fn velocity_at(&self, p: Vec3) -> Vec3 {
        self.v + self.w.cross(p - self.x)
    }

    /// World bounds of the shape.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let aabb = self.shape.compute_aabb(&self.pose());
        (aabb.mins, aabb.maxs)
    }

    /// Stage 6: x += Δt·v; q += Δt/2·[0, ω]⊗q, then normalised (the paper's f_x).
    pub fn integrate(&mut self, dt: f64) {
        if !self.dynamic {
            return;
        }
        self.x += dt * self.v;
        self.q = quat_step(self.q, self.w, dt);
    }
}

/// `normalise(q + Δt/2·[0, ω]⊗q)`.
#[inline]
pub fn quat_step(q: Rotation, w: Vec3, dt: f64) -> Rotation {
    let wq = Rotation::from_xyzw(w.x, w.y, w.z, 0.0) * q;
    let raw = Rotation::from_xyzw(
        q.x + 0.5 * dt * wq.x,
        q.y + 0.5 * dt * wq.y,
        q.z + 0.5 * dt * wq.z,
        q.w + 0.5 * dt * wq.w,
    );
    raw.normalize()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cube_mass_properties() {
        let b =
            RigidBody::new("c".into(), SharedShape::cuboid(0.1, 0.1, 0.1), Pose::IDENTITY, 2000.0);
        assert!((b.mass - 16.0).abs() < 1e-12);
        // I = m (a² + a²)/12 with a = 0.2.
        let i = 16.0 * (0.04 + 0.04) / 12.0;
        assert!((b.world_inertia().x_axis.x - i).abs() < 1e-12);
    }

    #[test]
    fn quaternion_step_turns_at_omega() {
        // Many small steps about z at 1 rad/s for 1 s turn by about 1 rad.
        let mut q = Rotation::IDENTITY;
        for _ in 0..1000 {
            q = quat_step(q, Vec3::new(0.0, 0.0, 1.0), 1e-3);
        }
        let (axis, angle) = q.to_axis_angle();
        assert!((angle - 1.0).abs() < 1e-6 && (axis.z - 1.0).abs() < 1e-9, "{axis} {angle}");
    }
}
