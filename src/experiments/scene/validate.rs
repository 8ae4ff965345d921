//! The checks a scene passes before it runs, each failure a `Problem` that names its key:
//! the names, the world (through its builder), `[loss]`, `[control]`, `[optimize]` and
//! `[output]`.

use super::build::{problem, Problem};
use super::optimizer::{action_entry, OptimizerSpec};
use super::spec::Scene;
use crate::error::{Error, Result};
use crate::math::v3;
use crate::world::settings::check_finite;

impl Scene {
    /// Re-checks a scene built or edited in code.
    pub fn check(&self) -> Result<()> {
        self.validate().map_err(|p| Error::InvalidScene {
            origin: self.name.clone(),
            message: format!("{}: {}", p.key, p.message),
        })
    }

    /// The scene's and the bodies' names: each may name files (see
    /// [`crate::io::output::check_name`]), and no two bodies share one (a body's name is its
    /// key: its frames, its rows in `bodies.csv`, the body `[loss]` and `[control]` mean).
    fn check_names(&self) -> std::result::Result<(), Problem> {
        use crate::io::output::check_name;
        check_name(&self.name).map_err(|m| problem("name", m))?;
        let mut names: Vec<String> = Vec::with_capacity(self.body.len());
        for (i, b) in self.body.iter().enumerate() {
            let name = b.name_or_default(i);
            let key = format!("body[{i}].name");
            check_name(&name).map_err(|m| problem(&key, m))?;
            if let Some(j) = names.iter().position(|n| *n == name) {
                let default =
                    if b.name.is_empty() { ", the name an unnamed body gets" } else { "" };
                return Err(problem(
                    key,
                    format!(
                        "{name:?}{default} is body[{j}]'s name too: each body needs its own \
                         (it names the body's files and rows, and the body a loss means)"
                    ),
                ));
            }
            names.push(name);
        }
        Ok(())
    }

    pub(super) fn validate(&self) -> std::result::Result<(), Problem> {
        self.check_names()?;
        if self.time.steps == 0 {
            return Err(problem("time.steps", "must be at least 1"));
        }
        self.builder()?.check()?;
        if let Some(l) = &self.loss {
            let names: Vec<String> =
                self.body.iter().enumerate().map(|(i, b)| b.name_or_default(i)).collect();
            if !names.contains(&l.body) {
                return Err(problem(
                    "loss.body",
                    format!("no body named {:?} (bodies: {names:?})", l.body),
                ));
            }
            let size = v3(self.domain.size);
            if let Some(t) = &l.position {
                check_finite("loss.position.target", &t.target)?;
                let x = v3(t.target);
                if x.min_element() < 0.0 || (x - size).max_element() > 0.0 {
                    return Err(problem(
                        "loss.position.target",
                        format!(
                            "target {:?} is outside the tank [0, 0, 0]..{:?}",
                            t.target, self.domain.size
                        ),
                    ));
                }
            }
            if let Some(t) = &l.velocity {
                check_finite("loss.velocity.target", &t.target)?;
            }
            if let Some(t) = &l.orientation {
                let n = t.target.iter().map(|x| x * x).sum::<f64>().sqrt();
                if !(n.is_finite() && n > 1e-12) {
                    return Err(problem(
                        "loss.orientation.target",
                        "must be a finite non-zero quaternion",
                    ));
                }
            }
            for (key, w) in [
                ("loss.position.weight", l.position.as_ref().map(|t| t.weight)),
                ("loss.orientation.weight", l.orientation.as_ref().map(|t| t.weight)),
                ("loss.velocity.weight", l.velocity.as_ref().map(|t| t.weight)),
            ] {
                if let Some(w) = w {
                    if !(w.is_finite() && w >= 0.0) {
                        return Err(problem(
                            key,
                            format!("must be a non-negative number, got {w}"),
                        ));
                    }
                }
            }
            for (k, w) in l.waypoint.iter().enumerate() {
                let key = format!("loss.waypoint[{k}]");
                if !(1..=self.time.steps).contains(&w.step) {
                    return Err(problem(
                        format!("{key}.step"),
                        format!("must be in 1..={}, got {}", self.time.steps, w.step),
                    ));
                }
                check_finite(&format!("{key}.position"), &w.position)?;
                if !(w.weight.is_finite() && w.weight >= 0.0) {
                    return Err(problem(format!("{key}.weight"), "must be a non-negative number"));
                }
            }
            for (key, w) in [("loss.effort", l.effort), ("loss.speed", l.speed)] {
                if !(w.is_finite() && w >= 0.0) {
                    return Err(problem(key, format!("must be a non-negative number, got {w}")));
                }
            }
            if let Some(b) = &l.liquid_in_box {
                check_finite("loss.liquid_in_box.min", &b.min)?;
                check_finite("loss.liquid_in_box.max", &b.max)?;
                if (0..3).any(|d| b.max[d] <= b.min[d]) {
                    return Err(problem(
                        "loss.liquid_in_box",
                        "max must be above min on every axis",
                    ));
                }
                for (key, x) in [
                    ("loss.liquid_in_box.target", b.target),
                    ("loss.liquid_in_box.weight", b.weight),
                ] {
                    if !(x.is_finite() && x >= 0.0) {
                        return Err(problem(
                            key,
                            format!("must be a non-negative number, got {x}"),
                        ));
                    }
                }
            }
            let trajectory_terms = !l.waypoint.is_empty()
                || l.effort > 0.0
                || l.speed > 0.0
                || l.liquid_in_box.is_some();
            if trajectory_terms && self.control.is_none() {
                return Err(problem(
                    "loss",
                    "waypoint, effort, speed and liquid_in_box are terms on a trajectory: they \
                     need a [control] section",
                ));
            }
            if l.position.is_none()
                && l.orientation.is_none()
                && l.velocity.is_none()
                && !trajectory_terms
            {
                return Err(problem(
                    "loss",
                    "give at least one of position, orientation, velocity",
                ));
            }
        }
        if let Some(c) = &self.control {
            let names: Vec<String> =
                self.body.iter().enumerate().map(|(i, b)| b.name_or_default(i)).collect();
            if c.bodies.is_empty() {
                return Err(problem("control.bodies", "name at least one body"));
            }
            for n in &c.bodies {
                if !names.contains(n) {
                    return Err(problem(
                        "control.bodies",
                        format!("no body named {n:?} (bodies: {names:?})"),
                    ));
                }
            }
            if c.steps_per_action == 0 {
                return Err(problem("control.steps_per_action", "must be at least 1"));
            }
            if self.time.steps % c.steps_per_action != 0 {
                return Err(problem(
                    "control.steps_per_action",
                    format!(
                        "time.steps ({}) must be a multiple of it ({})",
                        self.time.steps, c.steps_per_action
                    ),
                ));
            }
            if !c.initial.is_empty() && c.initial.len() != c.bodies.len() {
                return Err(problem(
                    "control.initial",
                    format!(
                        "one action per body: {} for {} bodies",
                        c.initial.len(),
                        c.bodies.len()
                    ),
                ));
            }
            if c.initial.iter().flatten().any(|x| !x.is_finite()) {
                return Err(problem("control.initial", "must be finite"));
            }
            if let Some(b) = c.bound {
                if !(b.is_finite() && b > 0.0) {
                    return Err(problem(
                        "control.bound",
                        format!("must be a positive number, got {b}"),
                    ));
                }
            }
            if c.epochs == 0 {
                return Err(problem("control.epochs", "must be at least 1"));
            }
            for f in &c.free {
                if action_entry(f).is_none() {
                    return Err(problem(
                        "control.free",
                        format!(
                            "unknown entry {f:?}: use vx vy vz wx wy wz (a velocity) or fx fy fz \
                             tx ty tz (a force and torque)"
                        ),
                    ));
                }
            }
            match &c.optimizer {
                OptimizerSpec::Gd { learning_rate, decay }
                | OptimizerSpec::Adam { learning_rate, decay, .. } => {
                    if !(learning_rate.is_finite() && *learning_rate > 0.0) {
                        return Err(problem(
                            "control.optimizer.learning_rate",
                            format!("must be a positive number, got {learning_rate}"),
                        ));
                    }
                    check_decay("control", *decay)?;
                }
                OptimizerSpec::Lbfgs { .. } => {
                    return Err(problem("control.optimizer", "control takes gd or adam"))
                }
            }
            if self.loss.is_none() {
                return Err(problem("control", "needs a [loss] section"));
            }
        }
        if let Some(o) = &self.optimize {
            if self.loss.is_none() {
                return Err(problem("optimize", "needs a [loss] section"));
            }
            if o.params.is_empty() {
                return Err(problem(
                    "optimize.params",
                    "name at least one of \"v\", \"w\", \"x\", \"q\"",
                ));
            }
            let lr = match &o.optimizer {
                OptimizerSpec::Gd { learning_rate, decay } => {
                    check_decay("optimize", *decay)?;
                    *learning_rate
                }
                OptimizerSpec::Adam { learning_rate, beta1, beta2, decay } => {
                    check_decay("optimize", *decay)?;
                    for (k, b) in [("beta1", beta1), ("beta2", beta2)] {
                        if !(b.is_finite() && *b >= 0.0 && *b < 1.0) {
                            return Err(problem(
                                format!("optimize.optimizer.{k}"),
                                format!("must be in [0, 1), got {b}"),
                            ));
                        }
                    }
                    *learning_rate
                }
                OptimizerSpec::Lbfgs { memory, tolerance_grad, tolerance_cost, .. } => {
                    if *memory == 0 {
                        return Err(problem("optimize.optimizer.memory", "must be at least 1"));
                    }
                    for (k, t) in
                        [("tolerance_grad", tolerance_grad), ("tolerance_cost", tolerance_cost)]
                    {
                        if !(t.is_finite() && *t >= 0.0) {
                            return Err(problem(
                                format!("optimize.optimizer.{k}"),
                                format!("must be a non-negative number, got {t}"),
                            ));
                        }
                    }
                    1.0
                }
            };
            if !(lr.is_finite() && lr > 0.0) {
                return Err(problem(
                    "optimize.optimizer.learning_rate",
                    format!("must be a positive number, got {lr}"),
                ));
            }
            if o.epochs == 0 {
                return Err(problem("optimize.epochs", "must be at least 1"));
            }
            if !(o.max_gradient_norm.is_finite() && o.max_gradient_norm > 0.0) {
                return Err(problem("optimize.max_gradient_norm", "must be a positive number"));
            }
            if let Some(v) = &o.recover_velocity {
                check_finite("optimize.recover_velocity", v)?;
            }
            if let Some(Err(Error::InvalidSettings { key, message })) =
                o.smoothing.as_ref().map(|s| s.validate())
            {
                return Err(problem(key, message));
            }
            if let Some(s) = &o.smoothing {
                check_smoothing(s, &o.params, &o.optimizer)?;
            }
        }
        if self.output.every == 0 {
            return Err(problem("output.every", "must be at least 1"));
        }
        if !(1..=8).contains(&self.output.surface_samples) {
            return Err(problem(
                "output.surface_samples",
                format!("must be 1 to 8, got {}", self.output.surface_samples),
            ));
        }
        if self.output.surface && !cfg!(feature = "surface") {
            return Err(problem("output.surface", crate::io::output::SURFACE_FEATURE_MISSING));
        }
        Ok(())
    }
}

/// What a smoothing must hold for the optimisation that uses it: the losses alone give no
/// gradient for a kind of parameter they do not perturb, and L-BFGS's line search needs one
/// function, so one σ.
fn check_smoothing(
    s: &crate::gradients::Smoothing,
    params: &[crate::geometry::body::Param],
    optimizer: &OptimizerSpec,
) -> Result<(), Problem> {
    use crate::gradients::SmoothingEstimator;
    if s.estimator == SmoothingEstimator::Values {
        for &p in params {
            if s.sigma.of(p) == 0.0 {
                let name = p.name();
                return Err(problem(
                    format!("optimize.smoothing.sigma.{name}"),
                    format!(
                        "estimator = \"values\" needs a σ > 0 for every optimised parameter: \
                         {name} is optimised and its σ is 0 (the losses alone give no gradient \
                         along what they do not perturb)"
                    ),
                ));
            }
        }
    }
    if s.sigma_decay != 1.0 && matches!(optimizer, OptimizerSpec::Lbfgs { .. }) {
        return Err(problem(
            "optimize.smoothing.sigma_decay",
            "L-BFGS's line search needs the same function every iteration: sigma_decay is for gd \
             and adam",
        ));
    }
    Ok(())
}

/// A learning-rate decay of section `section` must be in (0, 1].
fn check_decay(section: &str, decay: f64) -> Result<(), Problem> {
    if decay.is_finite() && decay > 0.0 && decay <= 1.0 {
        return Ok(());
    }
    Err(problem(format!("{section}.optimizer.decay"), format!("must be in (0, 1], got {decay}")))
}
