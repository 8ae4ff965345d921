//! Pushing particles out of the bodies, and its adjoint.

use super::*;
use crate::geometry::body::RigidBody;
use crate::math::{Pose, SharedShape, Vec3};
use parry3d_f64::query::Ray;
use rayon::prelude::*;

/// One point pushed out of a body's shape at `pose` (bounds `lo`..`hi`) along the direction
/// `n` the shape's signed distance d rises in: a point inside (d < 0) to where the ray from
/// it along `n` leaves the shape and `margin` beyond, a point outside nearer than `margin`
/// (0 ≤ d < `margin`) by `margin` − d along `n`; any other point stays. `n` is the
/// distance's central difference over h = max(|d|/2, `margin`), normalised: it turns
/// continuously from one face's normal to the next where two faces are equally near, where
/// the closest surface point (the rule before) jumps from one face to the other (inside a
/// box, across its diagonal planes: a particle a millimetre inside a box's edge was pushed
/// to one face or the other, and the step jumped by the gap between them).
#[inline]
fn push_one(shape: &SharedShape, pose: &Pose, bounds: (Vec3, Vec3), x: Vec3, margin: f64) -> Vec3 {
    let (lo, hi) = bounds;
    let reach = Vec3::splat(margin);
    if x.cmplt(lo - reach).any() || x.cmpgt(hi + reach).any() {
        return x;
    }
    let sdf = |p: Vec3| crate::geometry::interior::signed_distance(shape, pose, p);
    let d = sdf(x);
    if d >= margin {
        return x;
    }
    let h = (0.5 * d.abs()).max(margin);
    let grad = Vec3::new(
        sdf(x + Vec3::X * h) - sdf(x - Vec3::X * h),
        sdf(x + Vec3::Y * h) - sdf(x - Vec3::Y * h),
        sdf(x + Vec3::Z * h) - sdf(x - Vec3::Z * h),
    );
    let len = grad.length();
    if len == 0.0 {
        return x;
    }
    let n = grad / len;
    if d < 0.0 {
        let ray = Ray::new(x, n);
        let exit = shape.cast_ray(pose, &ray, f64::MAX, false).unwrap_or(-d);
        x + (exit + margin) * n
    } else {
        x + (margin - d) * n
    }
}

/// A body's pose and bounds.
type PlacedShape = (Pose, (Vec3, Vec3));

/// Moves particles that ended inside a rigid body to its surface, `margin` outside (the
/// bodies in order).
pub fn push_out_of_bodies(pos: &mut [Vec3], bodies: &[RigidBody], margin: f64) {
    for b in bodies {
        let (bounds, pose) = (b.bounds(), b.pose());
        pos.par_iter_mut().for_each(|x| *x = push_one(&b.shape, &pose, bounds, *x, margin));
    }
}

/// Adjoint of [`push_out_of_bodies`] from the positions before it, `pos0`: given ∂L/∂(pushed
/// positions) in `pbar`, leaves ∂L/∂(positions before) there and returns each body's
/// ∂L/∂[δx; δθ] (translation, and rotation about its centre of mass in the world frame).
/// Only pushed particles carry a Jacobian; it is taken by central differences in the point
/// ([`jacobian_t`]) and in the six pose directions, so it holds for any shape.
pub fn push_out_of_bodies_adjoint(
    pos0: &[Vec3],
    pbar: &mut [Vec3],
    bodies: &[RigidBody],
    margin: f64,
    step: f64,
) -> Vec<[f64; 6]> {
    // Replay, keeping (body, particle, position before) of every push.
    let mut pos = pos0.to_vec();
    let mut pushes = Vec::new();
    for (bi, b) in bodies.iter().enumerate() {
        let (bounds, pose) = (b.bounds(), b.pose());
        let moved: Vec<(usize, Vec3, Vec3)> = pos
            .par_iter()
            .enumerate()
            .filter_map(|(i, x)| {
                let y = push_one(&b.shape, &pose, bounds, *x, margin);
                (y != *x).then_some((i, *x, y))
            })
            .collect();
        for (i, x, y) in moved {
            pushes.push((bi, i, x));
            pos[i] = y;
        }
    }
    let mut out = vec![[0.0; 6]; bodies.len()];
    // The poses ±step along each of the six directions, per body that pushed.
    let moved = |b: &RigidBody, k: usize, s: f64| -> PlacedShape {
        let mut c = b.clone();
        let e = s * crate::math::unit(k % 3);
        if k < 3 {
            c.x += e;
        } else {
            c.q = (crate::math::Rotation::from_scaled_axis(e) * c.q).normalize();
        }
        (c.pose(), c.bounds())
    };
    let mut poses: Vec<Option<Vec<[PlacedShape; 2]>>> = vec![None; bodies.len()];
    for &(bi, i, x) in pushes.iter().rev() {
        let b = &bodies[bi];
        let bar = pbar[i];
        if bar == Vec3::ZERO {
            continue;
        }
        let (bounds, pose) = (b.bounds(), b.pose());
        let dirs = poses[bi].get_or_insert_with(|| {
            (0..6).map(|k| [moved(b, k, step), moved(b, k, -step)]).collect()
        });
        for (k, [(pp, bp), (pm, bm)]) in dirs.iter().enumerate() {
            let d = push_one(&b.shape, pp, *bp, x, margin) - push_one(&b.shape, pm, *bm, x, margin);
            out[bi][k] += bar.dot(d) / (2.0 * step);
        }
        pbar[i] = jacobian_t(|p| push_one(&b.shape, &pose, bounds, p, margin), x, step, bar);
    }
    out
}
