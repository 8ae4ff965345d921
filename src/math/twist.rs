//! Six numbers that are two 3-vectors: a body's [v; ω], a force and torque [f; τ], or a
//! pose gradient ∂L/∂[δx; δθ]. The coupling's algebra (J's columns, Δt·M⁻¹, the adjoints)
//! works on the six numbers as they are; [`TwistParts`] names the halves wherever they meet
//! a body's [`Vec3`]s.

use super::Vec3;

/// [linear; angular]: [v; ω], [f; τ] or ∂L/∂[δx; δθ].
pub type Twist = [f64; 6];

/// The two halves of a [`Twist`].
pub trait TwistParts {
    /// The first three: v, f or ∂L/∂x.
    fn linear(&self) -> Vec3;
    /// The last three: ω, τ or ∂L/∂θ.
    fn angular(&self) -> Vec3;
}

impl TwistParts for Twist {
    fn linear(&self) -> Vec3 {
        Vec3::new(self[0], self[1], self[2])
    }

    fn angular(&self) -> Vec3 {
        Vec3::new(self[3], self[4], self[5])
    }
}

/// The twist of two halves.
pub fn twist(linear: Vec3, angular: Vec3) -> Twist {
    [linear.x, linear.y, linear.z, angular.x, angular.y, angular.z]
}

/// a += b.
pub fn add_twist(a: &mut Twist, b: &Twist) {
    for d in 0..6 {
        a[d] += b[d];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn halves_round_trip() {
        let (v, w) = (Vec3::new(1.0, -2.0, 3.5), Vec3::new(-0.25, 0.5, 7.0));
        let t = twist(v, w);
        assert_eq!((t.linear(), t.angular()), (v, w));
        let mut s = t;
        add_twist(&mut s, &t);
        assert_eq!(s, twist(2.0 * v, 2.0 * w));
    }
}
