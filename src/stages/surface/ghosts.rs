//! The liquid a body displaced, counted by the soft minimum of φ_L.
//!
//! A soft minimum of the particles' distances counts the particles about as near as the
//! nearest one: eight particles of a freshly seeded cell are equally near its centre, and φ
//! there is their distance less τ·ln 8. Beside a body, the particles its volume displaced are
//! missing, the count falls, and φ rises: the surface dips around a floating body and a body
//! at rest stirs still water (the floating ball gave the liquid 6.7e-4 J in 1.5 s at
//! τ = 0.35 cells). The nearest particle's distance does not count, so it does not see this.
//!
//! So each body keeps the seeding sites it took from the liquid when it was placed, in its
//! own frame (its *ghosts*): the sites inside it that [`super::seed`] filled, which the
//! builder (or [`crate::world::Simulation::add_body`]) then removed. Each step they ride with
//! the body's pose, and the soft minimum counts them as particles. A body at rest in still
//! water then sees the full seeding lattice around it, as if it were not there, and still
//! water stays still to rounding; a moving body carries them smoothly (φ is C∞ in its pose),
//! and the backward pass carries their adjoint to the pose.
//!
//! What they do not know: where the liquid is now. A body lifted clear of the water keeps
//! them, and a cell beside its once-wetted part reads liquid (a ball lifted 0.15 m out of
//! still water: 12 liquid cells above the water against 5 with the nearest particle; a ball
//! thrown up at 1.5 m/s rose 0.4202 m with them, 0.4195 m without). Weighing each ghost by how
//! near the real liquid is changed that by 0.1 mm and was not kept. The nearest particle's
//! distance ignores them.

use crate::geometry::body::RigidBody;
use crate::math::{Twist, Vec3};
use std::sync::Arc;

/// The seeding sites a body displaced, in its frame: relative to its centre of mass, turned
/// back by its orientation. Shared between clones.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Displaced {
    local: Arc<[Vec3]>,
}

impl Displaced {
    /// The sites of `particles` that `body`, where it is now, covers (within `margin` outside
    /// it: what the builder removes).
    pub fn of(body: &RigidBody, particles: &[Vec3], margin: f64) -> Displaced {
        let back = body.q.inverse();
        let local: Vec<Vec3> = particles
            .iter()
            .filter(|x| body.sdf(**x) <= margin)
            .map(|x| back * (*x - body.x))
            .collect();
        Displaced { local: local.into() }
    }

    /// How many sites.
    pub fn len(&self) -> usize {
        self.local.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.local.is_empty()
    }
}

/// The ghosts of `bodies` (each with its `displaced` sites) where the bodies are now, body by
/// body.
pub fn ghost_sites(bodies: &[RigidBody], displaced: &[Displaced]) -> Vec<Vec3> {
    let mut out = Vec::with_capacity(displaced.iter().map(Displaced::len).sum());
    for (b, d) in bodies.iter().zip(displaced) {
        out.extend(d.local.iter().map(|l| b.x + b.q * *l));
    }
    out
}

/// What φ_L of surface model `model` counts of the ghosts of `bodies`: their
/// [`ghost_sites`] for a soft minimum, none for the nearest particle's distance.
pub fn counted_ghosts(
    model: &super::SurfaceModel,
    bodies: &[RigidBody],
    displaced: &[Displaced],
) -> Vec<Vec3> {
    if model.softness > 0.0 {
        ghost_sites(bodies, displaced)
    } else {
        Vec::new()
    }
}

/// Adjoint of [`ghost_sites`]: adds ∂L/∂pose of each body, [δx; δθ] (world frame, about its
/// centre of mass, as [`RigidBody::sdf_pose_dual`]), from ∂L/∂(each ghost's position)
/// `gbar` into `pose`. A ghost at x_g moves by δx + δθ × (x_g − x). Nothing when `gbar` is
/// empty (φ_L the nearest particle's distance, which counts no ghosts).
pub fn ghost_pose_adjoint(
    bodies: &[RigidBody],
    displaced: &[Displaced],
    gbar: &[Vec3],
    pose: &mut [Twist],
) {
    if gbar.is_empty() {
        return;
    }
    let mut at = 0;
    for ((b, d), p) in bodies.iter().zip(displaced).zip(pose.iter_mut()) {
        let (mut force, mut torque) = (Vec3::ZERO, Vec3::ZERO);
        for (l, g) in d.local.iter().zip(&gbar[at..at + d.len()]) {
            force += *g;
            torque += (b.q * *l).cross(*g);
        }
        at += d.len();
        for k in 0..3 {
            p[k] += force[k];
            p[3 + k] += torque[k];
        }
    }
}
