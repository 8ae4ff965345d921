//! A schedule of actions: what each step sets on the controlled bodies (a force and torque
//! on a dynamic body, a velocity on a kinematic one), held `steps_per_action` steps. The
//! forward run ([`super::run::Rollout`]) applies it before each step; the control gradient
//! ([`super::control`]) reads each action's gradient off the backward sweep.

use crate::error::{Error, Result};
use crate::geometry::body::Motion;
use crate::math::{Twist, TwistParts};
use crate::world::{BodyHandle, Simulation};

/// Actions (or their gradients): `[k][j]` the k-th action on the j-th controlled body.
pub type Actions = Vec<Vec<Twist>>;

/// What an action sets on a body, from its motion.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ActionKind {
    /// External force and torque `[f; τ]` (a dynamic body).
    Load,
    /// Velocity and angular velocity `[v; ω]` (a kinematic body).
    Velocity,
}

/// Actions on some bodies, one per `steps_per_action` steps.
#[derive(Clone, Debug, PartialEq)]
pub struct Schedule {
    /// The controlled bodies (indices into [`Simulation::bodies`]) and what their actions set.
    pub bodies: Vec<(usize, ActionKind)>,
    /// How many steps each action is held.
    pub steps_per_action: usize,
    /// `actions[k][j]`: the action on `bodies[j]` for steps `k·steps_per_action` to
    /// `(k + 1)·steps_per_action − 1`.
    pub actions: Vec<Vec<Twist>>,
}

impl Schedule {
    /// Actions on the bodies `controlled` of `sim` (a dynamic body takes a force and torque,
    /// a kinematic one a velocity), each held `steps_per_action` steps. An error names what
    /// is wrong: a handle of no body, a body that is fixed or moved by the caller, a
    /// `steps_per_action` of 0, no actions, a row of the wrong length, a NaN or infinity.
    pub fn new(
        sim: &Simulation,
        controlled: &[BodyHandle],
        steps_per_action: usize,
        actions: Vec<Vec<Twist>>,
    ) -> Result<Schedule> {
        let bad = |key: &str, message: String| Error::InvalidSettings {
            key: format!("control.{key}"),
            message,
        };
        if steps_per_action == 0 {
            return Err(bad("steps_per_action", "must be at least 1".into()));
        }
        let mut bodies = Vec::with_capacity(controlled.len());
        for &h in controlled {
            let i = sim.index_of(h).ok_or(Error::UnknownBody { handle: h.id() })?;
            let b = &sim.bodies()[i];
            let kind = match b.motion {
                Motion::Dynamic => ActionKind::Load,
                Motion::Kinematic => ActionKind::Velocity,
                Motion::Fixed => {
                    return Err(bad(
                        "bodies",
                        format!("body {} is fixed: it cannot be steered", b.name),
                    ))
                }
                Motion::External => {
                    return Err(bad(
                        "bodies",
                        format!("body {} is moved by the caller's engine: steer it there", b.name),
                    ))
                }
            };
            if bodies.iter().any(|&(j, _)| j == i) {
                return Err(bad("bodies", format!("body {} is controlled twice", b.name)));
            }
            bodies.push((i, kind));
        }
        if bodies.is_empty() {
            return Err(bad("bodies", "no body is controlled".into()));
        }
        if actions.is_empty() {
            return Err(bad("actions", "there are no actions".into()));
        }
        for (k, row) in actions.iter().enumerate() {
            if row.len() != bodies.len() {
                return Err(bad(
                    "actions",
                    format!("action {k} has {} entries for {} bodies", row.len(), bodies.len()),
                ));
            }
            if row.iter().flatten().any(|x| !x.is_finite()) {
                return Err(bad("actions", format!("action {k} is not finite: {row:?}")));
            }
        }
        Ok(Schedule { bodies, steps_per_action, actions })
    }

    /// The steps the schedule covers.
    pub fn steps(&self) -> usize {
        self.actions.len() * self.steps_per_action
    }

    /// The action index of step `t` (from 0).
    pub fn action_of(&self, t: usize) -> usize {
        t / self.steps_per_action
    }

    /// Sets step `t`'s actions (from 0) on `sim`'s bodies.
    pub fn apply(&self, sim: &mut Simulation, t: usize) {
        let row = &self.actions[self.action_of(t).min(self.actions.len() - 1)];
        let bodies = sim.bodies_mut();
        for (&(i, kind), a) in self.bodies.iter().zip(row) {
            let b = &mut bodies[i];
            match kind {
                ActionKind::Load => b.set_load(a),
                ActionKind::Velocity => {
                    (b.v, b.w) = (a.linear(), a.angular());
                }
            }
        }
    }

    /// Zero actions of the same shape.
    pub fn zeros_like(&self) -> Vec<Vec<Twist>> {
        vec![vec![[0.0; 6]; self.bodies.len()]; self.actions.len()]
    }
}
