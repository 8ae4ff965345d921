//! Control through the water: actions at every step, losses on whole trajectories, and the
//! gradient of such a loss with respect to every action and the initial state in one
//! backward sweep.
//!
//! An action acts on one body for one step, held for `steps_per_action` steps:
//!
//! - on a dynamic body, an external force and torque `[f; τ]` (world frame, N and N·m): stage
//!   `forces` adds Δt·(g + f/m) to its velocity and Δt·I_w⁻¹·τ to its angular velocity, so
//!   ∂L/∂f = Δt/m·v̂̄ and ∂L/∂τ = Δt·I_w⁻¹·ω̂̄, with v̂̄ and ω̂̄ the adjoint of the velocities
//!   that stage hands to the pressure solve;
//! - on a kinematic body (`dynamic = false`, a moving boundary of the solve), its velocity
//!   and angular velocity `[v; ω]`, which replace the ones it had: the adjoint of its
//!   velocity at the start of the step is the action's gradient, and nothing of it flows to
//!   the steps before (they set a velocity the action overwrote).
//!
//! Both are read off the adjoint as the backward sweep passes the boundary before the step
//! ([`super::backward::backward_adjoint_hooked`]), where a trajectory loss also adds its
//! derivative with respect to that boundary's state: one sweep, whatever the number of
//! actions.

use super::backward::{to_gradient, AdjointSeconds};
use super::loss::{AdjointState, BodyAdjoint, Gradient};
use super::run::{GradientSettings, Rollout};
pub use super::schedule::{ActionKind, Actions, Schedule};
use crate::error::{Error, Result};
use crate::geometry::body::BodyState;
use crate::math::{Twist, Vec3};
use crate::world::{BodyHandle, Simulation};

/// A forward run under a schedule, as a trajectory loss sees it.
#[derive(Clone, Copy, Debug)]
pub struct Trajectory<'a> {
    /// Every body's state at every boundary, before that step's action: `states[b]` after
    /// b steps, b = 0 ..= steps.
    pub states: &'a [Vec<BodyState>],
    /// The simulation at the end (its liquid: velocity, particles).
    pub final_state: &'a Simulation,
    /// The actions.
    pub schedule: &'a Schedule,
}

/// What a trajectory loss's derivative holds.
#[derive(Clone, Debug)]
pub struct TrajectorySeed {
    /// ∂L/∂`states[b]`, per body.
    pub states: Vec<Vec<BodyAdjoint>>,
    /// ∂L/∂actions that the loss reads directly (an effort term).
    pub actions: Vec<Vec<Twist>>,
    /// ∂L/∂(the final liquid): its velocity and particles.
    pub liquid: Option<AdjointState>,
}

impl TrajectorySeed {
    /// A zero derivative for `t`'s shapes.
    pub fn zero(t: &Trajectory<'_>) -> TrajectorySeed {
        let bodies = t.states.first().map_or(0, Vec::len);
        TrajectorySeed {
            states: vec![vec![BodyAdjoint::zero(); bodies]; t.states.len()],
            actions: t.schedule.zeros_like(),
            liquid: None,
        }
    }
}

/// A loss on a whole trajectory: its states at every step, its actions and its final liquid.
pub trait TrajectoryLoss: Sync {
    /// L of the trajectory.
    fn value(&self, t: &Trajectory<'_>) -> f64;
    /// ∂L of the trajectory ([`TrajectorySeed`]).
    fn gradient(&self, t: &Trajectory<'_>) -> TrajectorySeed;
}

/// A loss and its gradient with respect to every action and the initial state.
#[derive(Clone, Debug)]
pub struct ControlRun {
    /// L.
    pub loss: f64,
    /// ∂L/∂actions, shaped as the schedule's actions.
    pub actions: Vec<Vec<Twist>>,
    /// ∂L/∂(initial state).
    pub initial: Gradient,
    /// Every body's state at every boundary (see [`Trajectory::states`]).
    pub states: Vec<Vec<BodyState>>,
    /// The final state.
    pub final_state: Simulation,
    /// Wall time of the forward pass, s.
    pub forward_seconds: f64,
    /// Wall time of the backward pass, s.
    pub backward_seconds: f64,
    /// The backward pass's time per stage adjoint.
    pub adjoint_seconds: AdjointSeconds,
}

/// A forward run under a schedule, kept for its backward pass: what an autograd engine holds
/// between its forward and backward calls.
#[derive(Debug)]
pub struct ControlledRun {
    initial: Simulation,
    schedule: Schedule,
    rollout: Rollout,
}

impl ControlledRun {
    /// Runs `schedule` from `initial` (checkpointed as `settings` ask).
    pub fn run(
        initial: &Simulation,
        schedule: &Schedule,
        settings: &GradientSettings,
    ) -> Result<ControlledRun> {
        let rollout = Rollout::run_with(initial, 0, settings, Some(schedule))?;
        Ok(ControlledRun { initial: initial.clone(), schedule: schedule.clone(), rollout })
    }

    /// The trajectory, as a loss sees it.
    pub fn trajectory(&self) -> Trajectory<'_> {
        Trajectory {
            states: self.rollout.states(),
            final_state: self.rollout.final_state(),
            schedule: &self.schedule,
        }
    }

    /// From ∂L of the trajectory, the gradient with respect to every action and the initial
    /// state, and what each stage's adjoint cost. The run is kept: it can go backward again.
    pub fn backward(
        &self,
        seed: &TrajectorySeed,
        options: &super::backward::GradientOptions,
    ) -> Result<(Actions, Gradient, AdjointSeconds)> {
        let schedule = &self.schedule;
        let steps = schedule.steps();
        let check = |what: &str, got: usize, want: usize| {
            (got != want).then(|| Error::InvalidSettings {
                key: "control".into(),
                message: format!("the loss's derivative has {got} {what}, the run {want}"),
            })
        };
        let bodies = self.initial.bodies().len();
        if let Some(e) = check("boundaries", seed.states.len(), steps + 1)
            .or_else(|| check("actions", seed.actions.len(), schedule.actions.len()))
            .or_else(|| seed.states.iter().find_map(|s| check("bodies", s.len(), bodies)))
        {
            return Err(e);
        }
        let mut adj =
            seed.liquid.clone().unwrap_or_else(|| AdjointState::zero(self.initial.grid()));
        adj.bodies = seed.states[steps].clone();
        let mut actions = seed.actions.clone();
        let dt = self.initial.dt();
        let model = self.initial.bodies().to_vec();
        let states = self.rollout.states();
        let mut at_boundary = |b: usize, adj: &mut AdjointState| {
            let k = schedule.action_of(b);
            read_action_gradients(&schedule.bodies, &model, &states[b], dt, adj, &mut actions[k]);
            add_bodies(adj, &seed.states[b]);
        };
        let (adj, seconds) = self.rollout.backward_hooked(adj, options, &mut at_boundary)?;
        Ok((actions, to_gradient(&self.initial, adj), seconds))
    }
}

/// Runs `schedule` from `initial`, evaluates `loss` on the trajectory, and its gradient with
/// respect to every action and the initial state, in one backward sweep.
pub fn value_and_gradient_controlled(
    initial: &Simulation,
    schedule: &Schedule,
    loss: &dyn TrajectoryLoss,
    settings: &GradientSettings,
) -> Result<ControlRun> {
    let clock = std::time::Instant::now();
    let run = ControlledRun::run(initial, schedule, settings)?;
    let forward_seconds = clock.elapsed().as_secs_f64();
    let clock = std::time::Instant::now();
    let traj = run.trajectory();
    let value = loss.value(&traj);
    let seed = loss.gradient(&traj);
    let (actions, gradient, adjoint_seconds) = run.backward(&seed, &settings.options)?;
    Ok(ControlRun {
        loss: value,
        actions,
        initial: gradient,
        states: run.rollout.states().to_vec(),
        final_state: run.rollout.final_state().clone(),
        forward_seconds,
        backward_seconds: clock.elapsed().as_secs_f64(),
        adjoint_seconds,
    })
}

/// At a boundary before a step that an action acted on: adds that action's gradient, read
/// off `adj` (the adjoint of the state the step started from), into `grads` (one per
/// controlled body), and takes out of `adj` what the action overwrote (a kinematic body's
/// velocity). `model` gives each body's mass and inertia, `states` the bodies at the
/// boundary.
fn read_action_gradients(
    controlled: &[(usize, ActionKind)],
    model: &[crate::geometry::body::RigidBody],
    states: &[BodyState],
    dt: f64,
    adj: &mut AdjointState,
    grads: &mut [Twist],
) {
    for (&(i, kind), g) in controlled.iter().zip(grads) {
        let a = &mut adj.bodies[i];
        let (lin, ang) = match kind {
            ActionKind::Load => {
                let mut body = model[i].clone();
                body.set_state(&states[i]);
                (a.v * (dt / body.mass), body.world_inertia().inverse() * a.w * dt)
            }
            ActionKind::Velocity => {
                let out = (a.v, a.w);
                // The action replaced the velocity the state had.
                a.v = Vec3::ZERO;
                a.w = Vec3::ZERO;
                out
            }
        };
        for d in 0..3 {
            g[d] += lin.to_array()[d];
            g[3 + d] += ang.to_array()[d];
        }
    }
}

/// Adds `extra` to the bodies' part of `adj`.
fn add_bodies(adj: &mut AdjointState, extra: &[BodyAdjoint]) {
    for (a, s) in adj.bodies.iter_mut().zip(extra) {
        a.x += s.x;
        a.v += s.v;
        a.w += s.w;
        a.q = crate::math::Rotation::from_xyzw(
            a.q.x + s.q.x,
            a.q.y + s.q.y,
            a.q.z + s.q.z,
            a.q.w + s.q.w,
        );
    }
}

/// A run driven one action at a time, each held `steps_per_action` steps, and taken back
/// one action at a time: what a closed-loop policy trained through the simulator needs. The
/// caller sees the bodies' states only; the liquid's adjoint is carried from one action's
/// backward step to the one before, inside.
///
/// [`Stepper::backward`] must be called for the actions in reverse order (the last first),
/// as an autograd engine does.
#[derive(Debug)]
pub struct Stepper {
    /// The state the run started from (static data for the backward pass).
    start: Simulation,
    sim: Simulation,
    controlled: Vec<(usize, ActionKind)>,
    steps_per_action: usize,
    options: super::backward::GradientOptions,
    /// Per action taken and not yet taken back: its tape and its first step.
    blocks: Vec<(crate::world::Tape, usize)>,
    /// The liquid's adjoint at the start of the last action taken back.
    carried: Option<AdjointState>,
    /// Whether [`Stepper::backward`] has run since the start (or [`Stepper::reset`]): the
    /// run is being taken back and takes no more actions.
    taking_back: bool,
}

impl Stepper {
    /// A run from `sim` steering `controlled` (see [`Schedule::new`] for what is refused).
    pub fn new(
        sim: &Simulation,
        controlled: &[BodyHandle],
        steps_per_action: usize,
        options: super::backward::GradientOptions,
    ) -> Result<Stepper> {
        let probe = Schedule::new(
            sim,
            controlled,
            steps_per_action,
            vec![vec![[0.0; 6]; controlled.len()]],
        )?;
        Ok(Stepper {
            start: sim.clone(),
            sim: sim.clone(),
            controlled: probe.bodies,
            steps_per_action,
            options,
            blocks: Vec::new(),
            carried: None,
            taking_back: false,
        })
    }

    /// Back to the state the stepper started from, every action and adjoint dropped: a new
    /// run (the next episode of a policy's training, say).
    pub fn reset(&mut self) {
        self.sim = self.start.clone();
        self.blocks.clear();
        self.carried = None;
        self.taking_back = false;
    }

    /// The actions taken and not yet taken back.
    pub fn actions_taken(&self) -> usize {
        self.blocks.len()
    }

    /// ∂L/∂m of every body (see [`AdjointState::mass`]), summed over the actions taken back
    /// so far: the whole run's once every action is.
    pub fn mass_gradient(&self) -> Vec<f64> {
        let n = self.start.bodies().len();
        let mut m = self.carried.as_ref().map(|a| a.mass.clone()).unwrap_or_default();
        m.resize(n, 0.0);
        m
    }

    /// The simulation now.
    pub fn simulation(&self) -> &Simulation {
        &self.sim
    }

    /// The bodies' states now.
    pub fn states(&self) -> Vec<BodyState> {
        self.sim.bodies().iter().map(|b| b.state()).collect()
    }

    /// Takes `action` (one [f; τ] or [v; ω] per controlled body) for `steps_per_action` taped
    /// steps; returns the bodies' states after them.
    pub fn step(&mut self, action: &[Twist]) -> Result<Vec<BodyState>> {
        if self.taking_back {
            return Err(Error::InvalidSettings {
                key: "control".into(),
                message: "the run is being taken back (backward ran): it takes no more actions; \
                          reset() starts a new one"
                    .into(),
            });
        }
        let schedule = Schedule {
            bodies: self.controlled.clone(),
            steps_per_action: self.steps_per_action,
            actions: vec![action.to_vec()],
        };
        if action.len() != self.controlled.len() || action.iter().flatten().any(|x| !x.is_finite())
        {
            return Err(Error::InvalidSettings {
                key: "control.actions".into(),
                message: format!(
                    "an action takes {} finite entries of 6, got {action:?}",
                    self.controlled.len()
                ),
            });
        }
        let first = self.blocks.len() * self.steps_per_action;
        let mut tape = crate::world::Tape::default();
        for t in 0..self.steps_per_action {
            schedule.apply(&mut self.sim, t);
            self.sim.step_unreported(Some(&mut tape))?;
        }
        self.blocks.push((tape, first));
        Ok(self.states())
    }

    /// Takes back the last action not yet taken back: from ∂L/∂(the bodies' states after it)
    /// (with the liquid's adjoint carried from the action after it), the gradient of that
    /// action and ∂L/∂(the bodies' states before it).
    pub fn backward(&mut self, after: &[BodyAdjoint]) -> Result<(Vec<Twist>, Vec<BodyAdjoint>)> {
        // Checked before anything is taken: a refused call leaves the run as it was.
        if after.len() != self.start.bodies().len() {
            return Err(Error::InvalidSettings {
                key: "control".into(),
                message: format!(
                    "{} body adjoints for {} bodies",
                    after.len(),
                    self.start.bodies().len()
                ),
            });
        }
        let (tape, first) = self.blocks.pop().ok_or_else(|| Error::InvalidSettings {
            key: "control".into(),
            message: "backward asked for more actions than were taken".into(),
        })?;
        self.taking_back = true;
        let mut adj = self.carried.take().unwrap_or_else(|| AdjointState::zero(self.start.grid()));
        adj.bodies = after.to_vec();
        let mut grads = vec![[0.0; 6]; self.controlled.len()];
        let dt = self.start.dt();
        let model = self.start.bodies().to_vec();
        let states: Vec<Vec<BodyState>> = tape.steps.iter().map(|r| r.bodies.clone()).collect();
        let controlled = self.controlled.clone();
        let mut at_boundary = |b: usize, adj: &mut AdjointState| {
            read_action_gradients(&controlled, &model, &states[b - first], dt, adj, &mut grads);
        };
        let (adj, _) = super::backward::backward_adjoint_hooked(
            &self.start,
            &tape,
            adj,
            &self.options,
            first,
            &mut at_boundary,
        )?;
        let bodies = adj.bodies.clone();
        self.carried = Some(AdjointState { bodies: Vec::new(), ..adj });
        Ok((grads, bodies))
    }
}
