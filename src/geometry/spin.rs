//! Which part of a body's rotation reaches the liquid: all of it, the part across an axis of
//! symmetry, or none. Pressure acts along the surface normal, so a shape that is round about
//! an axis (or a point) feels no torque about it, and its spin about it moves no liquid.

use crate::math::Vec3;

/// Which part of a body's rotation reaches the liquid (see
/// [`RigidBody::spin`](crate::geometry::body::RigidBody::spin)).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Spin {
    /// All of it.
    Whole,
    /// The part across this world axis (a capsule, cylinder or cone about its axis).
    AcrossAxis(Vec3),
    /// None (a ball about its centre).
    None,
}

impl Spin {
    /// The part of an angular vector (an angular velocity, or a torque arm r × e) that
    /// couples: P·x with P = 1, 1 − a·aᵀ or 0. P is symmetric, so the same projection maps
    /// a torque and an angular velocity.
    #[inline]
    pub fn project(&self, x: Vec3) -> Vec3 {
        match *self {
            Spin::Whole => x,
            Spin::AcrossAxis(a) => x - a * a.dot(x),
            Spin::None => Vec3::ZERO,
        }
    }

    /// δ(P·x) for a world rotation δθ of the body: with δa = δθ × a,
    /// −δa·(a·x) − a·(δa·x). Zero unless the spin is about an axis.
    #[inline]
    pub fn rotation_derivative(&self, x: Vec3, dtheta: Vec3) -> Vec3 {
        match *self {
            Spin::AcrossAxis(a) => {
                let da = dtheta.cross(a);
                -da * a.dot(x) - a * da.dot(x)
            }
            _ => Vec3::ZERO,
        }
    }

    /// ∂(P·x)/∂θ as it acts on a world rotation δθ of the body, given back as the gradient
    /// of `g·(P·x)`: with δa = δθ × a, δ(P·x) = −δa·(a·x) − a·(δa·x), and
    /// g·δ(P·x) = δθ·(−(a·x)·(a × g) − (g·a)·(a × x)). Zero unless the spin is about an axis.
    #[inline]
    pub fn rotation_gradient(&self, x: Vec3, g: Vec3) -> Vec3 {
        match *self {
            Spin::AcrossAxis(a) => -(a.dot(x)) * a.cross(g) - g.dot(a) * a.cross(x),
            _ => Vec3::ZERO,
        }
    }
}
