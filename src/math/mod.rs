//! The one place where the geometry crates' types enter diffluid.
//!
//! parry3d (f64 build) works in glam types through `glamx`; nalgebra is used for the small
//! dense blocks (6×6 rigid mass matrices, direct solves in tests). A version bump of either
//! touches this file only.

pub mod buffer;
pub mod dual;
pub mod input;
pub mod memory;
pub mod par;
pub mod pool;
pub mod runs;
pub mod so3;
pub mod twist;

pub use parry3d_f64::math::{Pose, Rotation, Vector as Vec3};
pub use parry3d_f64::query::PointQuery;
pub use parry3d_f64::shape::{Shape, SharedShape};
pub use twist::{add_twist, twist, Twist, TwistParts};

/// A 3-vector as a plain array, used in scene files and outputs.
pub type Arr3 = [f64; 3];

/// Converts a plain array to a vector.
#[inline]
pub fn v3(a: Arr3) -> Vec3 {
    Vec3::new(a[0], a[1], a[2])
}

/// Component `axis` (0, 1, 2) of a vector.
#[inline]
pub fn comp(v: Vec3, axis: usize) -> f64 {
    v.to_array()[axis]
}

/// ⌊x⌋ without a library call, for the per-particle hot paths: the baseline x86-64 target
/// has no rounding instruction, so `f64::floor` is a call into libm. Truncate, then step
/// down where truncation rounded a negative value up. The same value as `x.floor()` for
/// |x| < 2⁶³, except −0 (gives +0); NaN gives 0.
#[inline]
pub fn floor(x: f64) -> f64 {
    let t = x as i64 as f64;
    if t > x {
        t - 1.0
    } else {
        t
    }
}

/// The unit vector along `axis`.
#[inline]
pub fn unit(axis: usize) -> Vec3 {
    let mut a = [0.0; 3];
    a[axis] = 1.0;
    v3(a)
}

#[cfg(test)]
mod tests {
    /// The same as `f64::floor` on integers, values just off them on either side, halves,
    /// negatives and large magnitudes.
    #[test]
    fn floor_is_the_floor() {
        let mut xs = vec![0.0, 1.0, -1.0, 0.5, -0.5, 1e15 + 0.5, -1e15 - 0.5, 4e18, -4e18];
        for i in -300..300 {
            let x = i as f64 * 0.37;
            xs.extend([x, x.next_up(), x.next_down(), i as f64, (i as f64).next_down()]);
        }
        for x in xs {
            assert_eq!(super::floor(x), x.floor(), "{x}");
        }
    }
}
