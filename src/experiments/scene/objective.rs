//! What a scene asks to minimise: the loss on the final state, the loss on a whole
//! trajectory, and the schedule of actions `[control]` steers.

use super::spec::Scene;
use crate::error::Result;
use crate::gradients::{
    BodyTargetLoss, FinalTarget, LiquidInBox, Schedule, TrajectoryTerms, Waypoint,
};
use crate::math::{v3, Rotation};
use crate::world::Simulation;

impl Scene {
    /// The loss the `[loss]` section describes (None when there is none).
    pub fn loss(&self) -> Option<BodyTargetLoss> {
        let l = self.loss.as_ref()?;
        let body = self.body_index(&l.body)?;
        Some(BodyTargetLoss {
            body,
            position: l.position.as_ref().map(|t| (v3(t.target), t.weight)),
            orientation: l.orientation.as_ref().map(|t| {
                let q = t.target;
                (Rotation::from_xyzw(q[1], q[2], q[3], q[0]).normalize(), t.weight)
            }),
            velocity: l.velocity.as_ref().map(|t| (v3(t.target), t.weight)),
        })
    }

    /// Whether gradients go through rapier's contact: unless the `[optimize]` section refuses
    /// it (`through_contact = false`).
    pub fn through_contact(&self) -> bool {
        self.optimize.as_ref().is_none_or(|o| o.through_contact)
    }

    /// The index of the body named `name`.
    pub fn body_index(&self, name: &str) -> Option<usize> {
        (0..self.body.len()).find(|&i| self.body[i].name_or_default(i) == name)
    }

    /// The loss of the `[loss]` section on a whole trajectory (its final target, waypoints,
    /// effort, speed and liquid box); None without one.
    pub fn trajectory_loss(&self) -> Option<TrajectoryTerms> {
        let l = self.loss.as_ref()?;
        let target = self.loss()?;
        let body = target.body;
        let final_target = (target.position.is_some()
            || target.orientation.is_some()
            || target.velocity.is_some())
        .then_some(FinalTarget {
            body,
            position: target.position,
            orientation: target.orientation,
            velocity: target.velocity,
        });
        Some(TrajectoryTerms {
            waypoints: l
                .waypoint
                .iter()
                .map(|w| Waypoint {
                    body,
                    step: w.step,
                    position: v3(w.position),
                    weight: w.weight,
                })
                .collect(),
            target: final_target,
            effort: l.effort,
            speed: (l.speed != 0.0).then_some((body, l.speed)),
            liquid_in_box: l.liquid_in_box.as_ref().map(|b| LiquidInBox {
                min: v3(b.min),
                max: v3(b.max),
                target: b.target,
                weight: b.weight,
            }),
        })
    }

    /// The schedule of the `[control]` section on `sim` (built from this scene), its actions
    /// at their starting values; None without one.
    pub fn schedule(&self, sim: &Simulation) -> Option<Result<Schedule>> {
        let c = self.control.as_ref()?;
        let handles: Vec<_> =
            c.bodies.iter().filter_map(|n| self.body_index(n)).map(|i| sim.handles()[i]).collect();
        let row: Vec<[f64; 6]> =
            if c.initial.is_empty() { vec![[0.0; 6]; c.bodies.len()] } else { c.initial.clone() };
        let actions = vec![row; self.time.steps / c.steps_per_action.max(1)];
        Some(Schedule::new(sim, &handles, c.steps_per_action, actions))
    }
}
