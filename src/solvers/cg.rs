//! Preconditioned conjugate gradients, generic over the operator and the preconditioner.
//!
//! Both are passed as closures `y = f(x)`, so the same loop serves the stencil-only
//! operator, the coupled operator with rigid bodies, and the adjoint solve. Every reduction
//! is deterministic (see [`crate::geometry::grid::dot`]): the iterates do not depend on the number of
//! threads.
//!
//! A closed tank with no air has the constant pressure as a null space; with
//! `project_constant` the constant is removed from the right-hand side and from each
//! preconditioned residual, and the answer has zero mean.

use crate::geometry::grid::{dot, REDUCE_CHUNK};
use rayon::prelude::*;

/// Stopping rule and null-space handling.
#[derive(Clone, Copy, Debug)]
pub struct CgSettings {
    /// Stop when ‖b − A x‖₂ ≤ tolerance·‖b‖₂.
    pub tolerance: f64,
    /// Give up after this many iterations.
    pub max_iterations: usize,
    /// Remove the constant vector (a closed tank with no air).
    pub project_constant: bool,
}

/// What a solve did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CgStats {
    /// Iterations done.
    pub iterations: usize,
    /// True relative residual ‖b − A x‖₂ / ‖b‖₂ at the end (0 when b = 0).
    pub relative_residual: f64,
    /// Whether the tolerance was met.
    pub converged: bool,
}

fn remove_mean(x: &mut [f64]) {
    if x.is_empty() {
        return;
    }
    let m = x.iter().sum::<f64>() / x.len() as f64;
    x.par_iter_mut().for_each(|v| *v -= m);
}

/// A preconditioner `z = M·r` for [`pcg_from`]: any closure `Fn(&[f64], &mut [f64])`, or a
/// type that can also take `r·z` as it writes `z`, which saves CG a pass over both.
pub trait Precondition {
    /// z = M·r.
    fn precondition(&self, r: &[f64], z: &mut [f64]);

    /// z = M·r, and `r·z` with the bits of [`dot`]`(r, z)`.
    fn precondition_dot(&self, r: &[f64], z: &mut [f64]) -> f64 {
        self.precondition(r, z);
        dot(r, z)
    }
}

impl<F: Fn(&[f64], &mut [f64])> Precondition for F {
    fn precondition(&self, r: &[f64], z: &mut [f64]) {
        self(r, z)
    }
}

/// x += α·d and r −= α·q, and the new r·r, in one pass over the four vectors: in the chunks
/// of [`dot`], each chunk's sum taken as `dot` takes it, so the same bits as the two updates
/// followed by `dot(r, r)`, which read r a second time.
fn step_and_norm(x: &mut [f64], r: &mut [f64], d: &[f64], q: &[f64], alpha: f64) -> f64 {
    let parts: Vec<f64> = x
        .par_chunks_mut(REDUCE_CHUNK)
        .zip(r.par_chunks_mut(REDUCE_CHUNK))
        .zip(d.par_chunks(REDUCE_CHUNK).zip(q.par_chunks(REDUCE_CHUNK)))
        .map(|((x, r), (d, q))| {
            x.iter_mut().zip(d).for_each(|(xi, di)| *xi += alpha * di);
            r.iter_mut().zip(q).for_each(|(ri, qi)| *ri -= alpha * qi);
            r.iter().zip(r.iter()).map(|(p, q)| p * q).sum::<f64>()
        })
        .collect();
    parts.iter().sum()
}

/// z = M·r with the constant removed when `project_constant`, and r·z.
fn preconditioned_dot<M: Precondition>(
    m: &M,
    r: &[f64],
    z: &mut [f64],
    project_constant: bool,
) -> f64 {
    if project_constant {
        m.precondition(r, z);
        remove_mean(z);
        dot(r, z)
    } else {
        m.precondition_dot(r, z)
    }
}

/// Solves `A x = b` from `x = 0`. The convergence test uses the true residual: when the
/// recurrence says converged, the residual is recomputed, and CG restarts from it if the
/// two have drifted apart.
pub fn pcg<A, M>(apply: A, precondition: M, b: &[f64], x: &mut [f64], s: &CgSettings) -> CgStats
where
    A: Fn(&[f64], &mut [f64]),
    M: Precondition,
{
    x.iter_mut().for_each(|v| *v = 0.0);
    pcg_from(apply, precondition, b, x, s)
}

/// [`pcg`] from the initial guess in `x` (a warm start: the last step's pressure is close to
/// this one's). The stopping rule is the same, relative to ‖b‖, so the answer meets the same
/// tolerance from any start.
pub fn pcg_from<A, M>(
    apply: A,
    precondition: M,
    b: &[f64],
    x: &mut [f64],
    s: &CgSettings,
) -> CgStats
where
    A: Fn(&[f64], &mut [f64]),
    M: Precondition,
{
    let n = b.len();
    // ‖b‖ with the constant removed (a copy of b only when there is one to remove).
    let bnorm = if s.project_constant {
        let mut b0 = b.to_vec();
        remove_mean(&mut b0);
        dot(&b0, &b0).sqrt()
    } else {
        dot(b, b).sqrt()
    };
    if bnorm == 0.0 || n == 0 {
        x.iter_mut().for_each(|v| *v = 0.0);
        return CgStats { iterations: 0, relative_residual: 0.0, converged: true };
    }
    if !bnorm.is_finite() {
        // An infinite or NaN right-hand side (‖b‖² overflows past 1e154 a component): no
        // residual can be measured against it, and nothing is solved. It used to pass the
        // test below (‖r‖ ≤ tol·∞) as converged, with a NaN residual.
        return CgStats { iterations: 0, relative_residual: f64::NAN, converged: false };
    }
    if s.project_constant {
        remove_mean(x);
    }
    let mut r = vec![0.0; n];
    apply(x, &mut r);
    r.par_iter_mut().zip(b.par_iter()).for_each(|(ri, bi)| *ri = bi - *ri);
    if s.project_constant {
        remove_mean(&mut r);
    }
    let target = s.tolerance * bnorm;
    if dot(&r, &r).sqrt() <= target {
        return CgStats {
            iterations: 0,
            relative_residual: dot(&r, &r).sqrt() / bnorm,
            converged: true,
        };
    }
    // q = A·d and z = M·r are never needed at once (q is spent on x and r before z is
    // made, and z on d before the next q), so they share one vector: four of the system's
    // length instead of five.
    let mut d = vec![0.0; n];
    let mut q = vec![0.0; n];
    let mut it = 0;
    // Whether r holds the true residual of x (b − A·x, the constant removed) as the loop
    // leaves it: then the final check below would only compute it again.
    let mut confirmed = false;
    'restart: loop {
        let z = &mut q;
        let mut rho = preconditioned_dot(&precondition, &r, z, s.project_constant);
        d.copy_from_slice(z);
        while it < s.max_iterations {
            it += 1;
            apply(&d, &mut q);
            let dq = dot(&d, &q);
            if dq <= 0.0 || !dq.is_finite() {
                break 'restart;
            }
            let alpha = rho / dq;
            if step_and_norm(x, &mut r, &d, &q, alpha).sqrt() <= target {
                // Confirm with the true residual.
                apply(x, &mut q);
                r.par_iter_mut().zip(b.par_iter().zip(q.par_iter())).for_each(|(ri, (bi, qi))| {
                    *ri = bi - qi;
                });
                if s.project_constant {
                    remove_mean(&mut r);
                }
                if dot(&r, &r).sqrt() <= target {
                    confirmed = true;
                    break 'restart;
                }
                continue 'restart;
            }
            let z = &mut q;
            let rho_new = preconditioned_dot(&precondition, &r, z, s.project_constant);
            let beta = rho_new / rho;
            rho = rho_new;
            d.par_iter_mut().zip(z.par_iter()).for_each(|(di, zi)| *di = zi + beta * *di);
        }
        break;
    }
    // The true residual at the end, unless the convergence check just computed it for the x
    // returned (with the constant removed from x, x changes: computed again).
    if s.project_constant {
        remove_mean(x);
    }
    let res = &mut r;
    if !confirmed || s.project_constant {
        apply(x, &mut q);
        res.par_iter_mut()
            .zip(b.par_iter().zip(q.par_iter()))
            .with_min_len(crate::math::par::MIN_LEN)
            .for_each(|(ri, (bi, qi))| *ri = bi - qi);
        if s.project_constant {
            remove_mean(res);
        }
    }
    let rel = dot(res, res).sqrt() / bnorm;
    CgStats { iterations: it, relative_residual: rel, converged: rel <= s.tolerance }
}
