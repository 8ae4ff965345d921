//! Optimisation of a body's initial state: gradient descent (the paper's), Adam, or argmin's
//! L-BFGS over any of v, ω, x and the orientation q, with a checkpoint after every epoch
//! (written atomically) from which an interrupted run resumes exactly.
//!
//! Orientation steps are rotations: q ← exp(−s)·q for a step s in the world-frame tangent
//! space, so q stays a unit quaternion and its gradient is the tangent gradient of
//! [`crate::gradients`]. L-BFGS needs a vector space: it sees q as a rotation vector r with
//! q = exp(r)·q₀ (q₀ the scene's orientation), and the gradient in r is J_l(r)ᵀ·g, J_l the
//! left Jacobian of SO(3).
//!
//! L-BFGS is driven one iteration per epoch through argmin's `Solver` trait (`init`, then
//! `next_iter`), the loop argmin's `Executor` would run, so that each epoch is recorded,
//! checked and checkpointed like a gradient-descent epoch. Its state (correction pairs, line
//! search, iteration state) is saved with argmin's serde support.

use crate::error::{Error, Result};
use crate::experiments::scene::{OptimizerSpec, Scene};
use crate::gradients::{value_and_gradient, BodyTargetLoss, GradientMode, Loss};
use crate::math::{Rotation, Vec3};
use crate::world::Simulation;
use argmin::core::{CostFunction, Gradient, IterState, Problem, Solver, State, TerminationStatus};
use argmin::solver::linesearch::MoreThuenteLineSearch;
use argmin::solver::quasinewton::LBFGS;
use serde::{Deserialize, Serialize};
use std::cell::{Cell, RefCell};
use std::path::Path;

/// A body's initial state as the optimiser sees it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BodyParams {
    /// Linear velocity.
    pub v: [f64; 3],
    /// Angular velocity.
    pub w: [f64; 3],
    /// Centre of mass.
    pub x: [f64; 3],
    /// Orientation `[w, x, y, z]`.
    pub q: [f64; 4],
}

/// One epoch of the history.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpochRecord {
    /// Epoch, from 0.
    pub epoch: usize,
    /// Loss at this epoch's parameters.
    pub loss: f64,
    /// Norm of the gradient over the optimised parameters.
    pub grad_norm: f64,
    /// The parameters evaluated.
    pub params: BodyParams,
    /// Loss-and-gradient evaluations (forward + backward passes) so far, the one at these
    /// parameters included: epoch + 1 for gradient descent and Adam; for L-BFGS each epoch's
    /// line search may take several.
    #[serde(default)]
    pub evaluations: usize,
}

/// Optimiser state carried between epochs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum OptimizerState {
    /// Gradient descent has none.
    Gd,
    /// Adam's moments and step count.
    Adam {
        /// First moments.
        m: Vec<f64>,
        /// Second moments.
        v: Vec<f64>,
        /// Steps taken.
        t: u64,
    },
    /// L-BFGS: argmin's solver (correction pairs, line search) and its iteration state
    /// (parameters, loss, gradient, the previous loss), serialised by argmin's serde support
    /// as TOML text, since JSON has no infinity and argmin keeps some (the loss before the
    /// first iteration, unbounded step limits).
    Lbfgs {
        /// The solver.
        solver: String,
        /// The iteration state.
        state: String,
    },
}

/// Everything needed to continue a run: written after every epoch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Checkpoint {
    /// Scene name (a resume must use the same scene).
    pub scene: String,
    /// The next epoch to run.
    pub next_epoch: usize,
    /// Parameters to evaluate next.
    pub params: BodyParams,
    /// Optimiser state.
    pub optimizer: OptimizerState,
    /// Every epoch so far.
    pub history: Vec<EpochRecord>,
    /// Loss-and-gradient evaluations so far.
    #[serde(default)]
    pub evaluations: usize,
}

impl Checkpoint {
    /// Reads a checkpoint.
    pub fn load(path: &Path) -> Result<Checkpoint> {
        let text = std::fs::read_to_string(path)
            .map_err(|source| Error::ReadScene { path: path.to_path_buf(), source })?;
        serde_json::from_str(&text).map_err(|e| Error::InvalidScene {
            origin: path.display().to_string(),
            message: format!("not a diffluid checkpoint: {e}"),
        })
    }

    /// Writes it atomically (write, then rename): a kill leaves the previous one intact.
    pub fn save(&self, path: &Path) -> Result<()> {
        crate::io::output::write_json(path, self)
    }
}

/// How a run ended.
#[derive(Clone, Debug)]
pub struct Outcome {
    /// Every epoch.
    pub history: Vec<EpochRecord>,
    /// The parameters after the last update.
    pub params: BodyParams,
    /// The loss at those parameters.
    pub final_loss: f64,
    /// Set when the run stopped early (non-finite or exploding gradient, a failed step, a
    /// failed line search): the reason. The parameters are then the last good ones.
    pub stopped: Option<String>,
    /// Set when L-BFGS met its convergence test before the last epoch: the reason. The run
    /// ended normally.
    pub converged: Option<String>,
    /// Loss-and-gradient evaluations in all (the final loss of gradient descent and Adam is
    /// one more forward pass, not counted).
    pub evaluations: usize,
}

/// An optimisation problem built from a scene's `[loss]` and `[optimize]` sections.
#[derive(Clone, Debug)]
pub struct Optimization {
    /// The scene.
    pub scene: Scene,
    /// The simulation before any step, with the scene's initial body state.
    pub initial: Simulation,
    /// The loss (with recovery targets filled in).
    pub loss: BodyTargetLoss,
    /// Which body.
    pub body: usize,
    /// Optimised parameters, each of "v", "w", "x", "q".
    pub params: Vec<String>,
    /// The optimiser.
    pub optimizer: OptimizerSpec,
    /// Epochs.
    pub epochs: usize,
    /// Exploding-gradient threshold.
    pub max_gradient_norm: f64,
}

fn arr(v: Vec3) -> [f64; 3] {
    v.to_array()
}

impl Optimization {
    /// Builds the problem; for a recovery scene, runs the forward pass from v* to make the
    /// targets.
    pub fn new(mut scene: Scene) -> Result<Optimization> {
        if scene.optimize.as_ref().is_some_and(|o| o.freeze_surface) {
            scene.solver.freeze_surface = true;
        }
        let invalid =
            |m: &str| Error::InvalidScene { origin: scene.name.clone(), message: m.into() };
        let spec = scene.optimize.clone().ok_or_else(|| invalid("no [optimize] section"))?;
        let mut loss =
            BodyTargetLoss::from_scene(&scene).ok_or_else(|| invalid("no [loss] section"))?;
        let initial = Simulation::new(scene.clone())?;
        let body = loss.body;
        if !initial.bodies[body].dynamic {
            return Err(invalid("the loss body is not dynamic"));
        }
        if let Some(vstar) = spec.recover_velocity {
            let mut s = initial.clone();
            s.bodies[body].v = crate::math::v3(vstar);
            for _ in 0..scene.time.steps {
                s.step()?;
            }
            let b = &s.bodies[body];
            loss.position = Some((b.x, loss.position.map(|p| p.1).unwrap_or(1.0)));
            loss.velocity = Some((b.v, loss.velocity.map(|p| p.1).unwrap_or(1.0)));
        }
        Ok(Optimization {
            loss,
            body,
            params: spec.params.clone(),
            optimizer: spec.optimizer.clone(),
            epochs: spec.epochs,
            max_gradient_norm: spec.max_gradient_norm,
            initial,
            scene,
        })
    }

    /// The scene's initial parameters.
    pub fn initial_params(&self) -> BodyParams {
        let b = &self.initial.bodies[self.body];
        BodyParams { v: arr(b.v), w: arr(b.w), x: arr(b.x), q: [b.q.w, b.q.x, b.q.y, b.q.z] }
    }

    /// A simulation with the body's initial state set to `p`.
    pub fn simulation(&self, p: &BodyParams) -> Simulation {
        let mut s = self.initial.clone();
        let b = &mut s.bodies[self.body];
        b.v = crate::math::v3(p.v);
        b.w = crate::math::v3(p.w);
        b.x = crate::math::v3(p.x);
        b.q = Rotation::from_xyzw(p.q[1], p.q[2], p.q[3], p.q[0]).normalize();
        s
    }

    /// Loss and gradient (over the optimised parameters, 3 numbers each) at `p`.
    pub fn evaluate(&self, p: &BodyParams) -> Result<(f64, Vec<f64>)> {
        let sim = self.simulation(p);
        let run =
            value_and_gradient(&sim, self.scene.time.steps, &self.loss, GradientMode::Full, None)?;
        let g = run.gradient.bodies[self.body];
        let mut out = Vec::with_capacity(3 * self.params.len());
        for name in &self.params {
            let v = match name.as_str() {
                "v" => g.v,
                "w" => g.w,
                "x" => g.x,
                _ => g.q,
            };
            out.extend_from_slice(&v.to_array());
        }
        Ok((run.loss, out))
    }

    /// The loss at `p` (forward only).
    pub fn loss_at(&self, p: &BodyParams) -> Result<f64> {
        let mut s = self.simulation(p);
        for _ in 0..self.scene.time.steps {
            s.step()?;
        }
        Ok(self.loss.value(&s))
    }

    fn start_state(&self) -> OptimizerState {
        match self.optimizer {
            OptimizerSpec::Gd { .. } => OptimizerState::Gd,
            OptimizerSpec::Adam { .. } => {
                let n = 3 * self.params.len();
                OptimizerState::Adam { m: vec![0.0; n], v: vec![0.0; n], t: 0 }
            }
            // Made by the solver's `init`, which evaluates the starting point.
            OptimizerSpec::Lbfgs { .. } => OptimizerState::Gd,
        }
    }

    /// The step s (p ← p − s) the optimiser takes for gradient g.
    fn step(&self, state: &mut OptimizerState, g: &[f64]) -> Vec<f64> {
        match (&self.optimizer, state) {
            (OptimizerSpec::Gd { learning_rate }, _) => {
                g.iter().map(|x| learning_rate * x).collect()
            }
            (
                OptimizerSpec::Adam { learning_rate, beta1, beta2 },
                OptimizerState::Adam { m, v, t },
            ) => {
                *t += 1;
                let (b1t, b2t) = (1.0 - beta1.powi(*t as i32), 1.0 - beta2.powi(*t as i32));
                (0..g.len())
                    .map(|i| {
                        m[i] = beta1 * m[i] + (1.0 - beta1) * g[i];
                        v[i] = beta2 * v[i] + (1.0 - beta2) * g[i] * g[i];
                        learning_rate * (m[i] / b1t) / ((v[i] / b2t).sqrt() + 1e-12)
                    })
                    .collect()
            }
            _ => unreachable!("a first-order optimiser with its own state"),
        }
    }

    fn apply_step(&self, p: &BodyParams, s: &[f64]) -> BodyParams {
        let mut out = *p;
        for (k, name) in self.params.iter().enumerate() {
            let d = [s[3 * k], s[3 * k + 1], s[3 * k + 2]];
            let sub = |a: [f64; 3]| [a[0] - d[0], a[1] - d[1], a[2] - d[2]];
            match name.as_str() {
                "v" => out.v = sub(out.v),
                "w" => out.w = sub(out.w),
                "x" => out.x = sub(out.x),
                _ => {
                    let q = Rotation::from_xyzw(out.q[1], out.q[2], out.q[3], out.q[0]);
                    let r = Rotation::from_scaled_axis(-Vec3::new(d[0], d[1], d[2]));
                    let n = (r * q).normalize();
                    out.q = [n.w, n.x, n.y, n.z];
                }
            }
        }
        out
    }

    /// Runs the remaining epochs, from `resume` or from the start, writing a checkpoint to
    /// `checkpoint` after every epoch. `on_epoch` sees each record as it is made.
    pub fn run(
        &self,
        checkpoint: Option<&Path>,
        resume: Option<Checkpoint>,
        on_epoch: impl FnMut(&EpochRecord),
    ) -> Result<Outcome> {
        let ck = match resume {
            Some(c) => {
                if c.scene != self.scene.name {
                    return Err(Error::InvalidScene {
                        origin: self.scene.name.clone(),
                        message: format!("the checkpoint is for scene {:?}", c.scene),
                    });
                }
                let lbfgs_state = matches!(c.optimizer, OptimizerState::Lbfgs { .. });
                let lbfgs = matches!(self.optimizer, OptimizerSpec::Lbfgs { .. });
                let fresh = c.next_epoch == 0 && c.history.is_empty();
                if lbfgs_state != lbfgs && !fresh {
                    return Err(Error::InvalidScene {
                        origin: self.scene.name.clone(),
                        message: "the checkpoint was written by another optimiser".into(),
                    });
                }
                c
            }
            None => Checkpoint {
                scene: self.scene.name.clone(),
                next_epoch: 0,
                params: self.initial_params(),
                optimizer: self.start_state(),
                history: Vec::new(),
                evaluations: 0,
            },
        };
        match &self.optimizer {
            OptimizerSpec::Lbfgs { .. } => self.run_lbfgs(checkpoint, ck, on_epoch),
            _ => self.run_first_order(checkpoint, ck, on_epoch),
        }
    }

    fn stop_message(&self, epoch: usize, loss: f64, norm: f64) -> Option<String> {
        (!loss.is_finite() || !norm.is_finite() || norm > self.max_gradient_norm).then(|| {
            format!(
                "epoch {epoch}: the gradient is {} (norm {norm:e}, loss {loss:e}); kept the last good parameters",
                if norm.is_finite() && loss.is_finite() { "exploding" } else { "not finite" }
            )
        })
    }

    /// Gradient descent and Adam: evaluate, record, step, checkpoint.
    fn run_first_order(
        &self,
        checkpoint: Option<&Path>,
        mut ck: Checkpoint,
        mut on_epoch: impl FnMut(&EpochRecord),
    ) -> Result<Outcome> {
        let mut stopped = None;
        while ck.next_epoch < self.epochs {
            let (loss, g) = match self.evaluate(&ck.params) {
                Ok(x) => x,
                Err(e) => {
                    stopped = Some(format!("epoch {}: {e}", ck.next_epoch));
                    break;
                }
            };
            ck.evaluations += 1;
            let norm = g.iter().map(|x| x * x).sum::<f64>().sqrt();
            if let Some(m) = self.stop_message(ck.next_epoch, loss, norm) {
                stopped = Some(m);
                break;
            }
            let rec = EpochRecord {
                epoch: ck.next_epoch,
                loss,
                grad_norm: norm,
                params: ck.params,
                evaluations: ck.evaluations,
            };
            on_epoch(&rec);
            ck.history.push(rec);
            let s = self.step(&mut ck.optimizer, &g);
            ck.params = self.apply_step(&ck.params, &s);
            ck.next_epoch += 1;
            if let Some(path) = checkpoint {
                ck.save(path)?;
            }
        }
        let final_loss = if stopped.is_none() {
            self.loss_at(&ck.params)?
        } else {
            ck.history.last().map(|r| r.loss).unwrap_or(f64::NAN)
        };
        let params = if stopped.is_some() {
            ck.history.last().map(|r| r.params).unwrap_or(ck.params)
        } else {
            ck.params
        };
        Ok(Outcome {
            history: ck.history,
            params,
            final_loss,
            stopped,
            converged: None,
            evaluations: ck.evaluations,
        })
    }

    /// The parameters as L-BFGS sees them: 3 numbers per optimised parameter, q as the
    /// rotation vector r with q = exp(r)·q₀.
    pub fn to_vector(&self, p: &BodyParams) -> Vec<f64> {
        let q0 = self.initial_params().q;
        let mut out = Vec::with_capacity(3 * self.params.len());
        for name in &self.params {
            let a = match name.as_str() {
                "v" => p.v,
                "w" => p.w,
                "x" => p.x,
                _ => {
                    let q = Rotation::from_xyzw(p.q[1], p.q[2], p.q[3], p.q[0]);
                    let q0 = Rotation::from_xyzw(q0[1], q0[2], q0[3], q0[0]);
                    let mut r = q * q0.inverse();
                    if r.w < 0.0 {
                        r = -r;
                    }
                    r.to_scaled_axis().to_array()
                }
            };
            out.extend_from_slice(&a);
        }
        out
    }

    /// The inverse of [`Optimization::to_vector`]: unoptimised parameters are the scene's.
    pub fn from_vector(&self, x: &[f64]) -> BodyParams {
        let mut p = self.initial_params();
        let q0 = Rotation::from_xyzw(p.q[1], p.q[2], p.q[3], p.q[0]);
        for (k, name) in self.params.iter().enumerate() {
            let a = [x[3 * k], x[3 * k + 1], x[3 * k + 2]];
            match name.as_str() {
                "v" => p.v = a,
                "w" => p.w = a,
                "x" => p.x = a,
                _ => {
                    let q = (Rotation::from_scaled_axis(crate::math::v3(a)) * q0).normalize();
                    p.q = [q.w, q.x, q.y, q.z];
                }
            }
        }
        p
    }

    /// Loss and gradient in the coordinates of [`Optimization::to_vector`].
    pub fn evaluate_vector(&self, x: &[f64]) -> Result<(f64, Vec<f64>)> {
        let (loss, mut g) = self.evaluate(&self.from_vector(x))?;
        for (k, name) in self.params.iter().enumerate() {
            if name == "q" {
                let r = [x[3 * k], x[3 * k + 1], x[3 * k + 2]];
                let t = [g[3 * k], g[3 * k + 1], g[3 * k + 2]];
                let j = left_jacobian(r);
                for c in 0..3 {
                    g[3 * k + c] = (0..3).map(|rr| j[rr][c] * t[rr]).sum();
                }
            }
        }
        Ok((loss, g))
    }

    /// L-BFGS: one argmin iteration per epoch, the state checkpointed after each.
    fn run_lbfgs(
        &self,
        checkpoint: Option<&Path>,
        mut ck: Checkpoint,
        mut on_epoch: impl FnMut(&EpochRecord),
    ) -> Result<Outcome> {
        let evaluations = Cell::new(ck.evaluations);
        let failure = RefCell::new(None);
        let mut problem = Problem::new(Objective {
            problem: self,
            evaluations: &evaluations,
            failure: &failure,
            cache: RefCell::new(Vec::new()),
            epoch: Cell::new(ck.next_epoch),
        });
        let restored = match &ck.optimizer {
            OptimizerState::Lbfgs { solver, state } => {
                Some((from_toml::<LbfgsSolver>(solver)?, from_toml::<LbfgsState>(state)?))
            }
            _ => None,
        };
        let (mut solver, mut state) = match restored {
            Some(x) => x,
            None => {
                let mut solver = new_lbfgs(&self.optimizer)?;
                let start = IterState::new()
                    .param(self.to_vector(&ck.params))
                    .max_iters(self.epochs as u64);
                match solver.init(&mut problem, start) {
                    Ok((mut state, _)) => {
                        state.update();
                        (solver, state)
                    }
                    Err(e) => {
                        let reason = failure.borrow().clone().unwrap_or_else(|| e.to_string());
                        return Ok(Outcome {
                            history: ck.history,
                            params: ck.params,
                            final_loss: f64::NAN,
                            stopped: Some(reason),
                            converged: None,
                            evaluations: evaluations.get(),
                        });
                    }
                }
            }
        };
        ck.evaluations = evaluations.get();
        let mut stopped = None;
        let mut converged = None;
        while ck.next_epoch < self.epochs {
            // The state holds this epoch's parameters, loss and gradient.
            if ck.next_epoch > 0 {
                let status =
                    <_ as Solver<Objective<'_>, LbfgsState>>::terminate(&mut solver, &state);
                if let TerminationStatus::Terminated(reason) = status {
                    converged = Some(format!("epoch {}: {reason}", ck.next_epoch));
                    break;
                }
            }
            let x = state.get_param().expect("L-BFGS keeps its parameters").clone();
            let loss = state.get_cost();
            let g = state.get_gradient().expect("L-BFGS keeps its gradient");
            let norm = g.iter().map(|x| x * x).sum::<f64>().sqrt();
            if let Some(m) = self.stop_message(ck.next_epoch, loss, norm) {
                stopped = Some(m);
                break;
            }
            let rec = EpochRecord {
                epoch: ck.next_epoch,
                loss,
                grad_norm: norm,
                params: self.from_vector(&x),
                evaluations: ck.evaluations,
            };
            on_epoch(&rec);
            ck.history.push(rec);
            problem.problem.as_ref().expect("the objective").epoch.set(ck.next_epoch);
            // argmin ends an iteration whose line search failed with a termination reason; an
            // error of the gradient after it comes back as an error.
            let (next, error) = match solver.next_iter(&mut problem, state) {
                Ok((next, _)) => (next, None),
                Err(e) => (IterState::new(), Some(e.to_string())),
            };
            state = next;
            ck.evaluations = evaluations.get();
            if error.is_some() || state.terminated() {
                let argmin_reason = error.unwrap_or_else(|| {
                    state.get_termination_reason().map(|r| r.to_string()).unwrap_or_default()
                });
                let reason = failure
                    .borrow()
                    .clone()
                    .unwrap_or_else(|| format!("epoch {}: {argmin_reason}", ck.next_epoch));
                stopped = Some(if reason.contains("kept the last good parameters") {
                    reason
                } else {
                    format!("{reason}; kept the last good parameters")
                });
                break;
            }
            state.update();
            state.increment_iter();
            ck.next_epoch += 1;
            ck.params = self.from_vector(state.get_param().expect("L-BFGS keeps its parameters"));
            ck.optimizer =
                OptimizerState::Lbfgs { solver: to_toml(&solver), state: to_toml(&state) };
            if let Some(path) = checkpoint {
                ck.save(path)?;
            }
        }
        let (params, final_loss) = match (&stopped, &converged) {
            (Some(_), _) => {
                let last = ck.history.last();
                (
                    last.map(|r| r.params).unwrap_or(ck.params),
                    last.map(|r| r.loss).unwrap_or(f64::NAN),
                )
            }
            _ => (ck.params, state.get_cost()),
        };
        Ok(Outcome {
            history: ck.history,
            params,
            final_loss,
            stopped,
            converged,
            evaluations: ck.evaluations,
        })
    }
}

/// The left Jacobian of SO(3) at r: exp(r + δ) ≈ exp(J_l(r)·δ)·exp(r) (Barfoot, State
/// Estimation for Robotics, eq. 7.77a).
pub fn left_jacobian(r: [f64; 3]) -> [[f64; 3]; 3] {
    let t2 = r.iter().map(|x| x * x).sum::<f64>();
    let t = t2.sqrt();
    // (1 − cos θ)/θ² and (θ − sin θ)/θ³, by their series near 0.
    let (a, b) = if t < 1e-4 {
        (0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0)
    } else {
        ((1.0 - t.cos()) / t2, (t - t.sin()) / (t2 * t))
    };
    let k = [[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]];
    let mut j = [[0.0; 3]; 3];
    for (i, row) in j.iter_mut().enumerate() {
        for (c, e) in row.iter_mut().enumerate() {
            let k2: f64 = (0..3).map(|m| k[i][m] * k[m][c]).sum();
            *e = f64::from(u8::from(i == c)) + a * k[i][c] + b * k2;
        }
    }
    j
}

type Vector = Vec<f64>;
type LbfgsState = IterState<Vector, Vector, (), (), (), f64>;

/// argmin's L-BFGS with its Moré–Thuente line search.
type LbfgsSolver = LBFGS<MoreThuenteLineSearch<Vector, Vector, f64>, Vector, Vector, f64>;

type ArgminResult<T> = std::result::Result<T, argmin::core::Error>;

fn new_lbfgs(spec: &OptimizerSpec) -> Result<LbfgsSolver> {
    let OptimizerSpec::Lbfgs { memory, tolerance_grad, tolerance_cost } = spec else {
        unreachable!("an L-BFGS spec")
    };
    LBFGS::new(MoreThuenteLineSearch::new(), *memory)
        .with_tolerance_grad(*tolerance_grad)
        .and_then(|s| s.with_tolerance_cost(*tolerance_cost))
        .map_err(|e| Error::InvalidScene {
            origin: "optimize.optimizer".into(),
            message: e.to_string(),
        })
}

fn to_toml<T: Serialize>(x: &T) -> String {
    toml::to_string(x).expect("argmin's state serialises")
}

fn from_toml<T: serde::de::DeserializeOwned>(text: &str) -> Result<T> {
    toml::from_str(text).map_err(|e| Error::InvalidScene {
        origin: "checkpoint".into(),
        message: format!("L-BFGS state unreadable: {e}"),
    })
}

/// The loss as argmin sees it. The line searches ask for the loss and then the gradient at
/// the same point, and L-BFGS asks again for the gradient at the point it accepts: one
/// adjoint run gives both, so the last few are kept and a repeated point costs nothing.
struct Objective<'a> {
    problem: &'a Optimization,
    evaluations: &'a Cell<usize>,
    /// Why the last evaluation failed (argmin turns a failed line search into a reason of
    /// its own; this keeps ours).
    failure: &'a RefCell<Option<String>>,
    cache: RefCell<Vec<(Vector, f64, Vector)>>,
    epoch: Cell<usize>,
}

impl Objective<'_> {
    fn eval(&self, x: &Vector) -> ArgminResult<(f64, Vector)> {
        if let Some((_, f, g)) = self.cache.borrow().iter().find(|(p, _, _)| p == x) {
            return Ok((*f, g.clone()));
        }
        self.evaluations.set(self.evaluations.get() + 1);
        let epoch = self.epoch.get();
        let fail = |m: String| {
            *self.failure.borrow_mut() = Some(m.clone());
            argmin::core::Error::msg(m)
        };
        let (f, g) =
            self.problem.evaluate_vector(x).map_err(|e| fail(format!("epoch {epoch}: {e}")))?;
        let norm = g.iter().map(|v| v * v).sum::<f64>().sqrt();
        if let Some(m) = self.problem.stop_message(epoch, f, norm) {
            return Err(fail(m));
        }
        let mut cache = self.cache.borrow_mut();
        if cache.len() == 4 {
            cache.remove(0);
        }
        cache.push((x.clone(), f, g.clone()));
        Ok((f, g))
    }
}

impl CostFunction for Objective<'_> {
    type Param = Vector;
    type Output = f64;
    fn cost(&self, x: &Vector) -> ArgminResult<f64> {
        Ok(self.eval(x)?.0)
    }
}

impl Gradient for Objective<'_> {
    type Param = Vector;
    type Gradient = Vector;
    fn gradient(&self, x: &Vector) -> ArgminResult<Vector> {
        Ok(self.eval(x)?.1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// exp(r + δ) = exp(J_l(r)·δ)·exp(r) to first order, checked by central differences.
    #[test]
    fn left_jacobian_matches_finite_differences() {
        let r = [0.3, -0.7, 0.4];
        let j = left_jacobian(r);
        let exp = |a: [f64; 3]| Rotation::from_scaled_axis(crate::math::v3(a));
        let h = 1e-6;
        for c in 0..3 {
            let mut rp = r;
            let mut rm = r;
            rp[c] += h;
            rm[c] -= h;
            // The world-frame rotation between exp(r ± h e_c) and exp(r).
            let dp = (exp(rp) * exp(r).inverse()).to_scaled_axis();
            let dm = (exp(rm) * exp(r).inverse()).to_scaled_axis();
            let col = (dp - dm) / (2.0 * h);
            for (i, row) in j.iter().enumerate() {
                let err = (row[c] - crate::math::comp(col, i)).abs();
                assert!(err < 1e-8, "J[{i}][{c}] = {} vs {}", row[c], crate::math::comp(col, i));
            }
        }
        assert_eq!(left_jacobian([0.0; 3]), [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
    }

    /// L-BFGS's coordinates: the rotation vector round-trips, and the gradient in them (the
    /// tangent gradient through J_l(r)ᵀ) agrees with central differences of the loss along a
    /// direction, at a point away from r = 0.
    #[test]
    fn vector_gradient_matches_central_differences() {
        let mut scene = Scene::builtin("recover_box").unwrap();
        scene.optimize.as_mut().unwrap().params = vec!["v".into(), "q".into()];
        scene.time.steps = 6;
        let problem = Optimization::new(scene).unwrap();
        let x = vec![0.2, -0.3, 0.1, 0.15, -0.25, 0.3];
        let back = problem.to_vector(&problem.from_vector(&x));
        assert!(x.iter().zip(&back).all(|(a, b)| (a - b).abs() < 1e-14), "{back:?}");
        let (_, g) = problem.evaluate_vector(&x).unwrap();
        let d = [0.3, 0.1, -0.2, 0.5, -0.4, 0.6];
        let h = 1e-5;
        let at = |s: f64| -> f64 {
            let y: Vec<f64> = x.iter().zip(&d).map(|(a, b)| a + s * b).collect();
            problem.loss_at(&problem.from_vector(&y)).unwrap()
        };
        let fd = (at(h) - at(-h)) / (2.0 * h);
        let ad: f64 = g.iter().zip(&d).map(|(a, b)| a * b).sum();
        // Measured: 1e-10 relative (the orientation part of the directional derivative is 6%).
        assert!((ad - fd).abs() <= 1e-12 + 1e-6 * fd.abs(), "adjoint {ad:e}, central {fd:e}");
    }
}
