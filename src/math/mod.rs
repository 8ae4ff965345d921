//! The one place where the geometry crates' types enter diffluid.
//!
//! parry3d (f64 build) works in glam types through `glamx`; nalgebra is used for the small
//! dense blocks (6×6 rigid mass matrices, direct solves in tests). A version bump of either
//! touches this file only.

pub mod buffer;
pub mod dual;
pub mod par;
pub mod so3;

pub use parry3d_f64::math::{Pose, Rotation, Vector as Vec3};
pub use parry3d_f64::query::PointQuery;
pub use parry3d_f64::shape::{Shape, SharedShape};

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

/// The unit vector along `axis`.
#[inline]
pub fn unit(axis: usize) -> Vec3 {
    let mut a = [0.0; 3];
    a[axis] = 1.0;
    v3(a)
}
