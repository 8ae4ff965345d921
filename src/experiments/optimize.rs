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
use crate::experiments::scene::{OptimizerSpec, Scene, SurfaceGradientSpec};
use crate::geometry::body::{BodyState, Param};
use crate::gradients::backward::SurfaceGradient;
use crate::gradients::{
    value_and_gradient, value_and_smoothed_gradient, BodyTargetLoss, GradientOptions,
    GradientSettings, Smoothing,
};
use crate::math::{so3, Rotation, Vec3};
use crate::world::Simulation;
use serde::{Deserialize, Serialize};
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};

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
    pub params: BodyState,
    /// Loss-and-gradient evaluations (forward + backward passes) so far, the one at these
    /// parameters included: epoch + 1 for gradient descent and Adam; for L-BFGS each epoch's
    /// line search may take several.
    #[serde(default)]
    pub evaluations: usize,
    /// With `optimize.smoothing`: the loss L itself at these parameters (one forward run;
    /// `loss` is then L_σ's estimate). None without smoothing, where `loss` is L.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unsmoothed_loss: Option<f64>,
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

/// The optimiser of `spec`, in words.
fn spec_kind(spec: &OptimizerSpec) -> &'static str {
    match spec {
        OptimizerSpec::Gd { .. } => "gradient descent",
        OptimizerSpec::Adam { .. } => "Adam",
        OptimizerSpec::Lbfgs { .. } => "L-BFGS",
    }
}

impl OptimizerState {
    /// The optimiser that keeps this state, in words.
    fn kind(&self) -> &'static str {
        match self {
            OptimizerState::Gd => "gradient descent",
            OptimizerState::Adam { .. } => "Adam",
            OptimizerState::Lbfgs { .. } => "L-BFGS",
        }
    }
}

/// Everything needed to continue a run: written after every epoch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Checkpoint {
    /// Scene name (a resume must use the same scene).
    pub scene: String,
    /// The next epoch to run.
    pub next_epoch: usize,
    /// Parameters to evaluate next.
    pub params: BodyState,
    /// Optimiser state.
    pub optimizer: OptimizerState,
    /// Every epoch so far.
    pub history: Vec<EpochRecord>,
    /// Loss-and-gradient evaluations so far.
    #[serde(default)]
    pub evaluations: usize,
    /// The scene's settings the run was started with (everything a resumed run must share:
    /// see [`Optimization::fingerprint`]); absent in checkpoints of older versions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub settings: Option<serde_json::Value>,
    /// The file it was read from ([`Checkpoint::load`]), which errors name; not saved.
    #[serde(skip)]
    pub source: Option<PathBuf>,
}

/// [`Outcome::stopped`] of a run its caller ended after epoch `epoch`'s record.
pub(super) fn interrupted(epoch: usize) -> String {
    format!("epoch {epoch}: interrupted; kept its parameters")
}

/// The first dotted key at which two JSON values differ, with both values.
fn first_difference(
    path: &str,
    a: &serde_json::Value,
    b: &serde_json::Value,
) -> Option<(String, String, String)> {
    use serde_json::Value;
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let mut keys: Vec<&String> = x.keys().chain(y.keys()).collect();
            keys.sort();
            keys.dedup();
            keys.into_iter().find_map(|k| {
                let p = if path.is_empty() { k.clone() } else { format!("{path}.{k}") };
                let null = Value::Null;
                first_difference(&p, x.get(k).unwrap_or(&null), y.get(k).unwrap_or(&null))
            })
        }
        _ if a == b => None,
        _ => Some((path.to_string(), a.to_string(), b.to_string())),
    }
}

impl Checkpoint {
    /// Reads a checkpoint (a regular file of at most
    /// [`MAX_INPUT_BYTES`](crate::math::input::MAX_INPUT_BYTES)). Whether it fits the scene
    /// is checked when a run resumes from it ([`Optimization::check_checkpoint`]).
    pub fn load(path: &Path) -> Result<Checkpoint> {
        let fail = |message: String| Error::Checkpoint { path: path.to_path_buf(), message };
        let text = crate::math::input::read_text(path).map_err(|e| fail(e.to_string()))?;
        let mut ck: Checkpoint = serde_json::from_str(&text)
            .map_err(|e| fail(format!("not a diffluid checkpoint: {e}")))?;
        ck.source = Some(path.to_path_buf());
        Ok(ck)
    }

    /// Writes it atomically (write, then rename) and durably (fsync of the file and its
    /// folder): a kill or a power loss leaves the previous one intact.
    pub fn save(&self, path: &Path) -> Result<()> {
        let text = serde_json::to_vec_pretty(self).expect("serialisable");
        crate::io::output::write_durable(path, &text)
    }
}

/// How a run ended.
#[derive(Clone, Debug)]
pub struct Outcome {
    /// Every epoch.
    pub history: Vec<EpochRecord>,
    /// The parameters after the last update.
    pub params: BodyState,
    /// The loss at those parameters.
    pub final_loss: f64,
    /// Set when the run stopped early (non-finite or exploding gradient, a failed step, a
    /// failed line search, the caller's interrupt): the reason. The parameters are then the
    /// last good ones.
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
    /// Optimised parameters.
    pub params: Vec<Param>,
    /// The optimiser.
    pub optimizer: OptimizerSpec,
    /// Epochs.
    pub epochs: usize,
    /// Exploding-gradient threshold.
    pub max_gradient_norm: f64,
    /// The backward pass's options (through rapier's contact when the scene asks).
    pub gradient: GradientOptions,
    /// Optimise the smoothed loss instead (`optimize.smoothing`): each epoch's loss and
    /// gradient are the mean over the perturbed runs, the same perturbations every epoch
    /// (so a line search sees one deterministic function).
    pub smoothing: Option<Smoothing>,
}

impl Optimization {
    /// Builds the problem; for a recovery scene, runs the forward pass from v* to make the
    /// targets.
    pub fn new(mut scene: Scene) -> Result<Optimization> {
        if scene.optimize.as_ref().is_some_and(|o| o.freeze_surface) {
            scene = scene.with_frozen_surface();
        }
        let invalid =
            |m: &str| Error::InvalidScene { origin: scene.name.clone(), message: m.into() };
        let spec = scene.optimize.clone().ok_or_else(|| invalid("no [optimize] section"))?;
        let mut loss = scene.loss().ok_or_else(|| invalid("no [loss] section"))?;
        let initial = scene.build()?;
        let body = loss.body;
        if !initial.bodies()[body].moves() {
            return Err(invalid("the loss body is not dynamic"));
        }
        if let Some(vstar) = spec.recover_velocity {
            let mut s = initial.clone();
            s.set_report_measures(false);
            s.bodies_mut()[body].v = crate::math::v3(vstar);
            for _ in 0..scene.time.steps {
                s.step()?;
            }
            let b = &s.bodies()[body];
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
            gradient: GradientOptions {
                through_contact: spec.through_contact,
                surface: match spec.surface_gradient {
                    SurfaceGradientSpec::Live => SurfaceGradient::Live,
                    SurfaceGradientSpec::Frozen => SurfaceGradient::Frozen,
                },
                ..Default::default()
            },
            smoothing: spec.smoothing,
            initial,
            scene,
        })
    }

    /// What a resumed run must share with the one that wrote the checkpoint: the whole
    /// scene as it was parsed (domain, time, fluid, liquid, obstacles, solver, bodies, contact,
    /// loss, optimizer and its settings), but for the number of epochs (`--epochs` may extend a
    /// run), the description and the outputs.
    pub fn fingerprint(&self) -> serde_json::Value {
        let mut v = serde_json::to_value(&self.scene).expect("a scene serialises");
        if let Some(o) = v.get_mut("optimize").and_then(|o| o.as_object_mut()) {
            o.remove("epochs");
        }
        if let Some(m) = v.as_object_mut() {
            m.remove("description");
            m.remove("output");
        }
        v
    }

    /// The scene's initial parameters.
    pub fn initial_params(&self) -> BodyState {
        self.initial.bodies()[self.body].state()
    }

    /// A simulation with the body's initial state set to `p`.
    pub fn simulation(&self, p: &BodyState) -> Simulation {
        let mut s = self.initial.clone();
        s.bodies_mut()[self.body].set_state(p);
        s
    }

    /// Loss and gradient (over the optimised parameters, 3 numbers each) at `p`, in epoch
    /// `epoch` (which sets the smoothing's σ, see [`Smoothing::at_epoch`]).
    pub fn evaluate(&self, p: &BodyState, epoch: usize) -> Result<(f64, Vec<f64>)> {
        let sim = self.simulation(p);
        let settings = GradientSettings::from(self.gradient);
        let steps = self.scene.time.steps;
        let (loss, g) = match &self.smoothing {
            None => {
                let run = value_and_gradient(&sim, steps, &self.loss, &settings)?;
                (run.loss, run.gradient.bodies[self.body])
            }
            Some(s) => {
                let s = s.at_epoch(epoch);
                let run = value_and_smoothed_gradient(&sim, steps, &self.loss, &settings, &s)?;
                (run.loss, run.gradient.bodies[self.body])
            }
        };
        let out: Vec<f64> = self.params.iter().flat_map(|&p| g.get(p).to_array()).collect();
        Ok((loss, out))
    }

    /// Records the epoch `ck` is at, with its loss and gradient norm (`loss_norm`) at
    /// `params`, after the checks every optimiser makes, into `ck`'s history and to
    /// `on_epoch`: a loss or gradient that is not finite or explodes, the loss itself with
    /// smoothing (a failed run), and `on_epoch` asking to stop. What stops the run, in words
    /// (None to go on).
    pub(super) fn record_epoch(
        &self,
        ck: &mut Checkpoint,
        (loss, norm): (f64, f64),
        params: BodyState,
        on_epoch: &mut impl FnMut(&EpochRecord) -> ControlFlow<()>,
    ) -> Option<String> {
        let epoch = ck.next_epoch;
        if let Some(m) = self.stop_message(epoch, loss, norm) {
            return Some(m);
        }
        let unsmoothed_loss = match self.unsmoothed_loss(&params) {
            Ok(x) => x,
            Err(e) => return Some(format!("epoch {epoch}: {e}")),
        };
        let evaluations = ck.evaluations;
        let rec =
            EpochRecord { epoch, loss, grad_norm: norm, params, evaluations, unsmoothed_loss };
        let flow = on_epoch(&rec);
        ck.history.push(rec);
        flow.is_break().then(|| interrupted(epoch))
    }

    /// With smoothing, the loss L itself at `p` for the epoch's record (None without).
    pub(super) fn unsmoothed_loss(&self, p: &BodyState) -> Result<Option<f64>> {
        self.smoothing.as_ref().map(|_| self.loss_at(p)).transpose()
    }

    /// The loss at `p` (forward only).
    pub fn loss_at(&self, p: &BodyState) -> Result<f64> {
        crate::gradients::run::value(self.simulation(p), self.scene.time.steps, &self.loss)
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
    fn step(&self, state: &mut OptimizerState, g: &[f64], epoch: usize) -> Vec<f64> {
        let learning_rate = self.optimizer.rate(epoch).unwrap_or(0.0);
        match (&self.optimizer, state) {
            (OptimizerSpec::Gd { .. }, _) => g.iter().map(|x| learning_rate * x).collect(),
            (OptimizerSpec::Adam { beta1, beta2, .. }, OptimizerState::Adam { m, v, t }) => {
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

    fn apply_step(&self, p: &BodyState, s: &[f64]) -> BodyState {
        let mut out = *p;
        for (k, param) in self.params.iter().enumerate() {
            let d = Vec3::new(s[3 * k], s[3 * k + 1], s[3 * k + 2]);
            match param {
                Param::V => out.v -= d,
                Param::W => out.w -= d,
                Param::X => out.x -= d,
                Param::Q => out.q = (Rotation::from_scaled_axis(-d) * out.q).normalize(),
            }
        }
        out
    }

    /// Whether `c` is a checkpoint of this problem that a run can resume from: the same scene
    /// and settings (when the checkpoint holds them: older ones do not), a history of
    /// `next_epoch` epochs numbered in order, finite parameters that differ from the scene's
    /// only where they are optimised, and the optimiser's own state, of the right size (for
    /// L-BFGS, argmin's solver and iteration state, configured as the scene says). The error
    /// names the checkpoint's key.
    pub fn check_checkpoint(&self, c: &Checkpoint) -> std::result::Result<(), String> {
        if c.scene != self.scene.name {
            return Err(format!(
                "written for scene {:?}, not {:?}: resume the scene that wrote it",
                c.scene, self.scene.name
            ));
        }
        if let Some(saved) = &c.settings {
            if let Some((key, was, now)) = first_difference("", saved, &self.fingerprint()) {
                return Err(format!(
                    "cannot resume: {key} was {was} when the checkpoint was written and is \
                     {now} now"
                ));
            }
        }
        if c.history.len() != c.next_epoch {
            return Err(format!(
                "next_epoch is {} but the history holds {} epochs",
                c.next_epoch,
                c.history.len()
            ));
        }
        let mut evaluations = 0;
        for (i, r) in c.history.iter().enumerate() {
            if r.epoch != i {
                return Err(format!("history[{i}].epoch is {}, not {i}", r.epoch));
            }
            if !(r.loss.is_finite() && r.grad_norm.is_finite() && r.grad_norm >= 0.0) {
                return Err(format!(
                    "history[{i}]: loss {} and grad_norm {} must be finite",
                    r.loss, r.grad_norm
                ));
            }
            if r.evaluations < evaluations || r.evaluations > c.evaluations {
                return Err(format!(
                    "history[{i}].evaluations is {}: the counts must grow and end at most at \
                     evaluations ({})",
                    r.evaluations, c.evaluations
                ));
            }
            evaluations = r.evaluations;
            self.check_params(&r.params, &format!("history[{i}].params"))?;
        }
        self.check_params(&c.params, "params")?;
        let lbfgs = matches!(self.optimizer, OptimizerSpec::Lbfgs { .. });
        // L-BFGS before its first iteration has no state of its own.
        let unstarted = lbfgs && c.next_epoch == 0 && c.optimizer == OptimizerState::Gd;
        if c.optimizer.kind() != spec_kind(&self.optimizer) && !unstarted {
            return Err(format!(
                "it holds {} state, but the scene optimises with {}",
                c.optimizer.kind(),
                spec_kind(&self.optimizer)
            ));
        }
        // Gradient descent and Adam evaluate once an epoch (older checkpoints count none).
        if !lbfgs && c.evaluations != 0 && c.evaluations != c.next_epoch {
            return Err(format!(
                "evaluations is {}, but {} epochs took one each",
                c.evaluations, c.next_epoch
            ));
        }
        let n = 3 * self.params.len();
        match &c.optimizer {
            OptimizerState::Gd => Ok(()),
            OptimizerState::Adam { m, v, t } => {
                for (key, x) in [("m", m), ("v", v)] {
                    if x.len() != n {
                        return Err(format!(
                            "optimizer.Adam.{key} has {} numbers; the scene optimises {n}",
                            x.len()
                        ));
                    }
                    let bad = |a: &&f64| !a.is_finite() || (key == "v" && **a < 0.0);
                    if let Some(a) = x.iter().find(bad) {
                        return Err(format!("optimizer.Adam.{key} holds {a}"));
                    }
                }
                if *t != c.next_epoch as u64 {
                    return Err(format!(
                        "optimizer.Adam.t is {t}, but {} steps were taken",
                        c.next_epoch
                    ));
                }
                Ok(())
            }
            #[cfg(feature = "lbfgs")]
            OptimizerState::Lbfgs { solver, state } => self.check_lbfgs(solver, state, c),
            #[cfg(not(feature = "lbfgs"))]
            OptimizerState::Lbfgs { .. } => {
                Err("L-BFGS state needs diffluid's `lbfgs` feature (argmin)".into())
            }
        }
    }

    /// Parameters `key` of a checkpoint: finite, and the scene's initial values where they
    /// are not optimised (to round-off: 1e-12 relative, an orientation within 3e-6 rad).
    fn check_params(&self, p: &BodyState, key: &str) -> std::result::Result<(), String> {
        let initial = self.initial_params();
        let wxyz = |q: Rotation| vec![q.w, q.x, q.y, q.z];
        for param in Param::ALL {
            let (value, scene) = match param {
                Param::V => (p.v.to_array().to_vec(), initial.v.to_array().to_vec()),
                Param::W => (p.w.to_array().to_vec(), initial.w.to_array().to_vec()),
                Param::X => (p.x.to_array().to_vec(), initial.x.to_array().to_vec()),
                Param::Q => (wxyz(p.q), wxyz(initial.q)),
            };
            if !value.iter().all(|x| x.is_finite()) {
                return Err(format!("{key}.{param} is {value:?}: not finite"));
            }
            let same = match param {
                Param::Q => p.q.dot(initial.q).abs() >= 1.0 - 1e-12,
                _ => {
                    value.iter().zip(&scene).all(|(a, b)| (a - b).abs() <= 1e-12 * b.abs().max(1.0))
                }
            };
            if !self.params.contains(&param) && !same {
                return Err(format!(
                    "{key}.{param} is {value:?}, not the scene's {scene:?} ({param} is not \
                     optimised)"
                ));
            }
        }
        Ok(())
    }

    /// Runs the remaining epochs, from `resume` or from the start, writing a checkpoint to
    /// `checkpoint` after every epoch. `on_epoch` sees each record as it is made.
    pub fn run(
        &self,
        checkpoint: Option<&Path>,
        resume: Option<Checkpoint>,
        mut on_epoch: impl FnMut(&EpochRecord),
    ) -> Result<Outcome> {
        self.run_while(checkpoint, resume, |r| {
            on_epoch(r);
            ControlFlow::Continue(())
        })
    }

    /// [`Optimization::run`], where `on_epoch` may end the run after any epoch's record (an
    /// interrupt): a [`ControlFlow::Break`] stops it there, [`Outcome::stopped`] saying so,
    /// with that epoch's parameters and loss (not stepped from) and every record so far.
    pub fn run_while(
        &self,
        checkpoint: Option<&Path>,
        resume: Option<Checkpoint>,
        on_epoch: impl FnMut(&EpochRecord) -> ControlFlow<()>,
    ) -> Result<Outcome> {
        let ck = match resume {
            Some(c) => {
                self.check_checkpoint(&c).map_err(|message| Error::Checkpoint {
                    path: c.source.clone().unwrap_or_else(|| "(not read from a file)".into()),
                    message,
                })?;
                c
            }
            None => Checkpoint {
                scene: self.scene.name.clone(),
                next_epoch: 0,
                params: self.initial_params(),
                optimizer: self.start_state(),
                history: Vec::new(),
                evaluations: 0,
                settings: Some(self.fingerprint()),
                source: None,
            },
        };
        match &self.optimizer {
            #[cfg(feature = "lbfgs")]
            OptimizerSpec::Lbfgs { .. } => self.run_lbfgs(checkpoint, ck, on_epoch),
            #[cfg(not(feature = "lbfgs"))]
            OptimizerSpec::Lbfgs { .. } => Err(Error::InvalidScene {
                origin: self.scene.name.clone(),
                message: "optimize.optimizer: L-BFGS needs diffluid's `lbfgs` feature (argmin)"
                    .into(),
            }),
            _ => self.run_first_order(checkpoint, ck, on_epoch),
        }
    }

    pub(super) fn stop_message(&self, epoch: usize, loss: f64, norm: f64) -> Option<String> {
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
        mut on_epoch: impl FnMut(&EpochRecord) -> ControlFlow<()>,
    ) -> Result<Outcome> {
        let mut stopped = None;
        while ck.next_epoch < self.epochs {
            let (loss, g) = match self.evaluate(&ck.params, ck.next_epoch) {
                Ok(x) => x,
                Err(e) => {
                    stopped = Some(format!("epoch {}: {e}", ck.next_epoch));
                    break;
                }
            };
            ck.evaluations += 1;
            let norm = g.iter().map(|x| x * x).sum::<f64>().sqrt();
            let params = ck.params;
            if let Some(m) = self.record_epoch(&mut ck, (loss, norm), params, &mut on_epoch) {
                stopped = Some(m);
                break;
            }
            let s = self.step(&mut ck.optimizer, &g, ck.next_epoch);
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
    pub fn to_vector(&self, p: &BodyState) -> Vec<f64> {
        let q0 = self.initial_params().q;
        let part = |param: &Param| match param {
            Param::V => p.v,
            Param::W => p.w,
            Param::X => p.x,
            Param::Q => so3::log_chart(p.q, q0),
        };
        self.params.iter().flat_map(|param| part(param).to_array()).collect()
    }

    /// The inverse of [`Optimization::to_vector`]: unoptimised parameters are the scene's.
    pub fn from_vector(&self, x: &[f64]) -> BodyState {
        let mut p = self.initial_params();
        let q0 = p.q;
        for (k, param) in self.params.iter().enumerate() {
            let a = Vec3::new(x[3 * k], x[3 * k + 1], x[3 * k + 2]);
            match param {
                Param::V => p.v = a,
                Param::W => p.w = a,
                Param::X => p.x = a,
                Param::Q => p.q = so3::exp_chart(a, q0),
            }
        }
        p
    }

    /// Loss and gradient in the coordinates of [`Optimization::to_vector`].
    pub fn evaluate_vector(&self, x: &[f64]) -> Result<(f64, Vec<f64>)> {
        // L-BFGS keeps one σ (the scene's check refuses a sigma_decay with it).
        let (loss, mut g) = self.evaluate(&self.from_vector(x), 0)?;
        for (k, param) in self.params.iter().enumerate() {
            if *param == Param::Q {
                let r = Vec3::new(x[3 * k], x[3 * k + 1], x[3 * k + 2]);
                let t = Vec3::new(g[3 * k], g[3 * k + 1], g[3 * k + 2]);
                g[3 * k..3 * k + 3].copy_from_slice(&so3::chart_gradient(r, t).to_array());
            }
        }
        Ok((loss, g))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// L-BFGS's coordinates: the rotation vector round-trips, and the gradient in them (the
    /// tangent gradient through J_l(r)ᵀ) agrees with central differences of the loss along a
    /// direction, at a point away from r = 0.
    #[test]
    fn vector_gradient_matches_central_differences() {
        let mut scene = Scene::builtin("recover_box").unwrap();
        scene.optimize.as_mut().unwrap().params = vec![Param::V, Param::Q];
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
