//! Optimisation of a body's initial state: gradient descent (the paper's) or Adam over any of
//! v, ω, x and the orientation q, with a checkpoint after every epoch (written atomically) from
//! which an interrupted run resumes exactly.
//!
//! Orientation steps are rotations: q ← exp(−s)·q for a step s in the world-frame tangent
//! space, so q stays a unit quaternion and its gradient is the tangent gradient of
//! [`crate::adjoint`].

use crate::adjoint::{value_and_gradient, BodyTargetLoss, GradientMode, Loss};
use crate::error::{Error, Result};
use crate::math::{Rotation, Vec3};
use crate::scene::{OptimizerSpec, Scene};
use crate::sim::Simulation;
use serde::{Deserialize, Serialize};
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
        crate::output::write_json(path, self)
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
    /// Set when the run stopped early (non-finite or exploding gradient): the reason. The
    /// parameters are then the last good ones.
    pub stopped: Option<String>,
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
            _ => unreachable!("optimizer state matches the optimizer"),
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
        mut on_epoch: impl FnMut(&EpochRecord),
    ) -> Result<Outcome> {
        let mut ck = match resume {
            Some(c) => {
                if c.scene != self.scene.name {
                    return Err(Error::InvalidScene {
                        origin: self.scene.name.clone(),
                        message: format!("the checkpoint is for scene {:?}", c.scene),
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
            },
        };
        let mut stopped = None;
        while ck.next_epoch < self.epochs {
            let (loss, g) = match self.evaluate(&ck.params) {
                Ok(x) => x,
                Err(e) => {
                    stopped = Some(format!("epoch {}: {e}", ck.next_epoch));
                    break;
                }
            };
            let norm = g.iter().map(|x| x * x).sum::<f64>().sqrt();
            if !loss.is_finite() || !norm.is_finite() || norm > self.max_gradient_norm {
                stopped = Some(format!(
                    "epoch {}: the gradient is {} (norm {norm:e}, loss {loss:e}); kept the last good parameters",
                    ck.next_epoch,
                    if norm.is_finite() && loss.is_finite() { "exploding" } else { "not finite" }
                ));
                break;
            }
            let rec =
                EpochRecord { epoch: ck.next_epoch, loss, grad_norm: norm, params: ck.params };
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
        Ok(Outcome { history: ck.history, params, final_loss, stopped })
    }
}
