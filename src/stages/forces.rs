//! Constant body forces on the liquid (stage 2). They only add an offset to the velocity,
//! so the adjoint of this stage is the identity (paper, eq. 3).

use crate::geometry::grid::Mac;
use rayon::prelude::*;

/// Adds `dt·g` to every face (stage 2, gravity). Its adjoint is the identity.
pub fn add_gravity(u: &mut Mac, gravity: [f64; 3], dt: f64) {
    for (axis, c) in u.c.iter_mut().enumerate() {
        let dv = gravity[axis] * dt;
        if dv != 0.0 {
            c.par_iter_mut().for_each(|x| *x += dv);
        }
    }
}
