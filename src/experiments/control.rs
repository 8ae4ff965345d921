//! Steering bodies through the water (`diffluid control`): the `[control]` section's actions
//! optimised with gradients of the `[loss]` on the whole trajectory, against the same
//! problem solved without gradients (argmin's particle swarm) for the same number of
//! simulator calls.
//!
//! A call is a forward run; a gradient evaluation counts as two (its forward run and its
//! backward pass, which costs about as much).

use super::scene::{OptimizerSpec, Scene};
use crate::error::{Error, Result};
use crate::geometry::body::BodyState;
use crate::gradients::{
    value_and_gradient_controlled, Actions, GradientSettings, Schedule, Trajectory, TrajectoryLoss,
    TrajectoryTerms,
};
use crate::world::Simulation;
use serde::Serialize;

/// One epoch of [`optimise`].
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct ControlEpoch {
    /// The epoch, from 0 (the starting actions).
    pub epoch: usize,
    /// Simulator calls so far (two per gradient).
    pub calls: usize,
    /// L of this epoch's actions.
    pub loss: f64,
    /// |∂L/∂actions|.
    pub grad_norm: f64,
}

/// What [`optimise`] found.
#[derive(Clone, Debug)]
pub struct ControlOutcome {
    /// Every epoch.
    pub history: Vec<ControlEpoch>,
    /// The best actions met, and their loss.
    pub best: (Actions, f64),
    /// The bodies' states under the best actions, at every step.
    pub states: Vec<Vec<BodyState>>,
    /// The bodies' states under the starting actions.
    pub start_states: Vec<Vec<BodyState>>,
    /// Why the run stopped before its last epoch, if it did.
    pub stopped: Option<String>,
}

/// The problem a scene's `[control]` and `[loss]` sections pose.
#[derive(Debug)]
pub struct ControlProblem {
    /// The scene.
    pub scene: Scene,
    /// Its simulation at the start.
    pub sim: Simulation,
    /// The starting schedule.
    pub schedule: Schedule,
    /// The loss on the trajectory.
    pub loss: TrajectoryTerms,
    /// The optimiser, epochs and bound.
    optimizer: OptimizerSpec,
    /// Which of an action's six entries the optimiser changes.
    free: [bool; 6],
    /// Default epochs.
    pub epochs: usize,
    bound: Option<f64>,
    settings: GradientSettings,
}

impl ControlProblem {
    /// The problem of `scene` (an error without `[control]` and `[loss]`).
    pub fn new(scene: Scene) -> Result<ControlProblem> {
        let missing = |what: &str| Error::InvalidScene {
            origin: scene.name.clone(),
            message: format!("`diffluid control` needs a [{what}] section"),
        };
        let c = scene.control.clone().ok_or_else(|| missing("control"))?;
        let loss = scene.trajectory_loss().ok_or_else(|| missing("loss"))?;
        let sim = scene.build()?;
        let schedule = scene.schedule(&sim).ok_or_else(|| missing("control"))??;
        let options = crate::gradients::GradientOptions {
            surface: match scene.optimize.as_ref().map(|o| o.surface_gradient) {
                Some(super::scene::SurfaceGradientSpec::Frozen) => {
                    crate::gradients::backward::SurfaceGradient::Frozen
                }
                _ => crate::gradients::backward::SurfaceGradient::Live,
            },
            ..Default::default()
        };
        let mut free = [c.free.is_empty(); 6];
        for f in &c.free {
            if let Some(d) = super::scene::action_entry(f) {
                free[d] = true;
            }
        }
        Ok(ControlProblem {
            free,
            sim,
            schedule,
            loss,
            optimizer: c.optimizer,
            epochs: c.epochs,
            bound: c.bound,
            settings: GradientSettings { options, ..Default::default() },
            scene,
        })
    }

    /// The schedule with `actions`.
    fn with(&self, actions: &Actions) -> Schedule {
        Schedule { actions: actions.clone(), ..self.schedule.clone() }
    }

    /// L of `actions`, forward only, and the states.
    pub fn loss_of(&self, actions: &Actions) -> Result<(f64, Vec<Vec<BodyState>>)> {
        let schedule = self.with(actions);
        let mut sim = self.sim.clone();
        let mut states = Vec::with_capacity(schedule.steps() + 1);
        for t in 0..schedule.steps() {
            states.push(sim.bodies().iter().map(|b| b.state()).collect());
            schedule.apply(&mut sim, t);
            sim.step()?;
        }
        states.push(sim.bodies().iter().map(|b| b.state()).collect());
        let value = self.loss.value(&Trajectory {
            states: &states,
            final_state: &sim,
            schedule: &schedule,
        });
        Ok((value, states))
    }

    /// Clips every entry to the bound.
    fn clip(&self, a: &mut Actions) {
        if let Some(b) = self.bound {
            a.iter_mut().flatten().flatten().for_each(|x| *x = x.clamp(-b, b));
        }
    }

    /// Actions as one vector, and back.
    fn flat(a: &Actions) -> Vec<f64> {
        a.iter().flatten().flatten().copied().collect()
    }

    fn unflat(&self, x: &[f64]) -> Actions {
        let per = self.schedule.bodies.len();
        x.chunks(6 * per)
            .map(|row| row.chunks(6).map(|c| std::array::from_fn(|d| c[d])).collect())
            .collect()
    }
}

/// Optimises the actions for `epochs` epochs with the scene's optimiser (Adam or gradient
/// descent on every entry, clipped to `control.bound`), calling `progress` after each.
pub fn optimise(
    problem: &ControlProblem,
    epochs: usize,
    mut progress: impl FnMut(&ControlEpoch),
) -> Result<ControlOutcome> {
    let mut actions = problem.schedule.actions.clone();
    let n = ControlProblem::flat(&actions).len();
    let (mut m, mut v) = (vec![0.0; n], vec![0.0; n]);
    let mut history = Vec::with_capacity(epochs + 1);
    let mut best: Option<(Actions, f64)> = None;
    let mut start_states = Vec::new();
    let mut stopped = None;
    for epoch in 0..=epochs {
        let run = match value_and_gradient_controlled(
            &problem.sim,
            &problem.with(&actions),
            &problem.loss,
            &problem.settings,
        ) {
            Ok(run) => run,
            // A step the actions made fail (a body out of the tank): the run stops there
            // with what it found.
            Err(e) if epoch > 0 => {
                stopped = Some(format!("epoch {epoch}: {e}"));
                break;
            }
            Err(e) => return Err(e),
        };
        if epoch == 0 {
            start_states = run.states.clone();
        }
        // Entries held at their starting value take no step.
        let g: Vec<f64> = ControlProblem::flat(&run.actions)
            .iter()
            .enumerate()
            .map(|(i, &g)| if problem.free[i % 6] { g } else { 0.0 })
            .collect();
        let grad_norm = g.iter().map(|x| x * x).sum::<f64>().sqrt();
        if !grad_norm.is_finite() {
            return Err(Error::InvalidSettings {
                key: "control".into(),
                message: format!("the gradient is not finite at epoch {epoch}"),
            });
        }
        let row = ControlEpoch { epoch, calls: 2 * (epoch + 1), loss: run.loss, grad_norm };
        progress(&row);
        history.push(row);
        if best.as_ref().is_none_or(|b| run.loss < b.1) {
            best = Some((actions.clone(), run.loss));
        }
        if epoch == epochs {
            break;
        }
        let mut x = ControlProblem::flat(&actions);
        let learning_rate = problem.optimizer.rate(epoch).unwrap_or(0.0);
        match problem.optimizer {
            OptimizerSpec::Gd { .. } => {
                for (x, g) in x.iter_mut().zip(&g) {
                    *x -= learning_rate * g;
                }
            }
            OptimizerSpec::Adam { beta1, beta2, .. } => {
                let t = (epoch + 1) as i32;
                for i in 0..n {
                    m[i] = beta1 * m[i] + (1.0 - beta1) * g[i];
                    v[i] = beta2 * v[i] + (1.0 - beta2) * g[i] * g[i];
                    let mh = m[i] / (1.0 - beta1.powi(t));
                    let vh = v[i] / (1.0 - beta2.powi(t));
                    x[i] -= learning_rate * mh / (vh.sqrt() + 1e-12);
                }
            }
            OptimizerSpec::Lbfgs { .. } => {
                unreachable!("the scene check refuses L-BFGS for control")
            }
        }
        actions = problem.unflat(&x);
        problem.clip(&mut actions);
    }
    let best = best.expect("at least one epoch");
    let (_, states) = problem.loss_of(&best.0)?;
    Ok(ControlOutcome { history, best, states, start_states, stopped })
}

/// The same problem without gradients: argmin's particle swarm over the free entries of the
/// actions in `[−bound, bound]` (10 particles), for `calls` forward runs (a run that fails,
/// a body out of the tank, costs an infinite loss); the best loss after each iteration,
/// against the calls made.
#[cfg(feature = "lbfgs")]
pub fn particle_swarm(problem: &ControlProblem, calls: usize) -> Result<Vec<(usize, f64)>> {
    use argmin::core::{CostFunction, Executor};
    use argmin::solver::particleswarm::ParticleSwarm;
    /// The loss of the free entries `x` (the others at their starting values), each call
    /// kept.
    struct Cost<'a>(&'a ControlProblem, Vec<f64>, Vec<usize>, std::sync::Mutex<Vec<f64>>);
    impl CostFunction for Cost<'_> {
        type Param = Vec<f64>;
        type Output = f64;
        fn cost(&self, x: &Vec<f64>) -> std::result::Result<f64, argmin::core::Error> {
            let mut full = self.1.clone();
            for (&i, &v) in self.2.iter().zip(x) {
                full[i] = v;
            }
            let l = self.0.loss_of(&self.0.unflat(&full)).map(|r| r.0).unwrap_or(f64::INFINITY);
            if let Ok(mut all) = self.3.lock() {
                all.push(l);
            }
            Ok(l)
        }
    }
    let bound = problem.bound.ok_or_else(|| Error::InvalidSettings {
        key: "control.bound".into(),
        message: "the particle swarm searches a box: give control.bound".into(),
    })?;
    let start = ControlProblem::flat(&problem.schedule.actions);
    let free: Vec<usize> = (0..start.len()).filter(|i| problem.free[i % 6]).collect();
    let particles = 10;
    let iterations = (calls / particles).max(1) as u64;
    let solver = ParticleSwarm::new((vec![-bound; free.len()], vec![bound; free.len()]), particles);
    let cost = Cost(problem, start, free, std::sync::Mutex::new(Vec::new()));
    let res = Executor::new(cost, solver)
        .configure(|s| s.max_iters(iterations))
        .run()
        .map_err(|e| Error::InvalidSettings { key: "control".into(), message: e.to_string() })?;
    let all = res.problem.problem.map(|c| c.3.into_inner().unwrap_or_default()).unwrap_or_default();
    let mut best = f64::INFINITY;
    Ok(all
        .iter()
        .enumerate()
        .filter_map(|(i, &l)| {
            best = best.min(l);
            ((i + 1) % particles == 0 || i + 1 == all.len()).then_some((i + 1, best))
        })
        .collect())
}
