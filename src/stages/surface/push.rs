//! Pushing particles out of the bodies, and its adjoint.

use super::*;
use crate::geometry::body::RigidBody;
use crate::math::{Pose, SharedShape, Vec3};
use parry3d_f64::query::Ray;
use rayon::prelude::*;

/// Which rule of [`push_one`] a point falls under.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Push {
    /// `margin` or more outside the shape (or beyond its bounds): it stays.
    Stay,
    /// Inside: out along the ray, to `margin` beyond where it leaves the shape.
    Inside,
    /// Outside but nearer than `margin`: out by what it lacks of `margin`.
    Near,
}

/// The rule of [`push_one`] for `x` against a body's shape at `pose` (bounds `lo`..`hi`).
#[inline]
fn push_rule(shape: &SharedShape, pose: &Pose, bounds: (Vec3, Vec3), x: Vec3, margin: f64) -> Push {
    let (lo, hi) = bounds;
    let reach = Vec3::splat(margin);
    if x.cmplt(lo - reach).any() || x.cmpgt(hi + reach).any() {
        return Push::Stay;
    }
    match crate::geometry::interior::signed_distance(shape, pose, x) {
        d if d >= margin => Push::Stay,
        d if d < 0.0 => Push::Inside,
        _ => Push::Near,
    }
}

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
    push_by(shape, pose, x, margin, push_rule(shape, pose, bounds, x, margin))
}

/// `x` pushed by `rule`, whichever rule its distance asks for: the adjoint differentiates
/// the rule a point fell under, so that a central difference across the edge of the
/// margin (where [`Push::Near`] meets [`Push::Stay`] with a kink) reads the slope of the
/// side the point is on.
#[inline]
fn push_by(shape: &SharedShape, pose: &Pose, x: Vec3, margin: f64, rule: Push) -> Vec3 {
    if rule == Push::Stay {
        return x;
    }
    let sdf = |p: Vec3| crate::geometry::interior::signed_distance(shape, pose, p);
    let d = sdf(x);
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
    if rule == Push::Inside {
        let ray = Ray::new(x, n);
        let exit = shape.cast_ray(pose, &ray, f64::MAX, false).unwrap_or(-d);
        x + (exit + margin) * n
    } else {
        x + (margin - d) * n
    }
}

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
/// ([`jacobian_t`]) and in the six pose directions, so it holds for any shape, of the rule
/// the point fell under: a point the density projection left within a step of the margin's
/// edge read the mean of the two sides' slopes (the floating box under a moving surface
/// with `density_face_ramp`: one particle's ∂/∂θ₁ off by 30%).
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
        let moved: Vec<(usize, Vec3, Vec3, Push)> = pos
            .par_iter()
            .enumerate()
            .filter_map(|(i, x)| {
                let rule = push_rule(&b.shape, &pose, bounds, *x, margin);
                let y = push_by(&b.shape, &pose, *x, margin, rule);
                (y != *x).then_some((i, *x, y, rule))
            })
            .collect();
        for (i, x, y, rule) in moved {
            pushes.push((bi, i, x, rule));
            pos[i] = y;
        }
    }
    let mut out = vec![[0.0; 6]; bodies.len()];
    // The poses ±step along each of the six directions, per body that pushed.
    let moved = |b: &RigidBody, k: usize, s: f64| -> Pose {
        let mut c = b.clone();
        let e = s * crate::math::unit(k % 3);
        if k < 3 {
            c.x += e;
        } else {
            c.q = (crate::math::Rotation::from_scaled_axis(e) * c.q).normalize();
        }
        c.pose()
    };
    let mut poses: Vec<Option<Vec<[Pose; 2]>>> = vec![None; bodies.len()];
    for &(bi, i, x, rule) in pushes.iter().rev() {
        let b = &bodies[bi];
        let bar = pbar[i];
        if bar == Vec3::ZERO {
            continue;
        }
        let pose = b.pose();
        let dirs = poses[bi].get_or_insert_with(|| {
            (0..6).map(|k| [moved(b, k, step), moved(b, k, -step)]).collect()
        });
        for (k, [pp, pm]) in dirs.iter().enumerate() {
            let d = push_by(&b.shape, pp, x, margin, rule) - push_by(&b.shape, pm, x, margin, rule);
            out[bi][k] += bar.dot(d) / (2.0 * step);
        }
        pbar[i] = jacobian_t(|p| push_by(&b.shape, &pose, p, margin, rule), x, step, bar);
    }
    out
}
