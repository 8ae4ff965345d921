//! Gradient checks: the adjoint against central differences of the same forward map, one
//! body parameter at a time, with one pass criterion `|adjoint − fd| ≤ atol + rtol·|fd|`
//! (the CLI's `gradcheck`, the tests and the bench all call [`gradcheck`]).
//!
//! A central difference is only a reference where the forward map is smooth at the scale of
//! its step: each is also taken at ten times the step, and a parameter whose two differences
//! disagree by more than the criterion is reported as inconsistent rather than as an adjoint
//! error. Nor is it one at a kink, where the map has two one-sided slopes (a box whose
//! distance field ties two faces at a sample point of the fractions): the central difference
//! is then their mean, the same at every step, so the ε/10ε test cannot see it. The one-sided
//! differences at ε are compared as well; where they disagree the row is a kink, and the
//! adjoint passes if it is one of the two one-sided slopes.

use super::backward::{GradientMode, GradientOptions, SurfaceGradient};
use super::loss::Loss;
use super::run::{value_and_gradient, GradientSettings};
use crate::error::Result;
use crate::geometry::body::Param;
use crate::math::pool::{runs, Spread};
use crate::world::Simulation;
use serde::Serialize;

/// One coordinate of a body's initial state: a [`Param`] and an axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Coordinate {
    /// Which 3-vector.
    pub param: Param,
    /// Which of its components.
    pub axis: usize,
}

impl Coordinate {
    /// All twelve, in order v, ω, x, q.
    pub fn all() -> impl Iterator<Item = Coordinate> {
        Param::ALL.into_iter().flat_map(|param| (0..3).map(move |axis| Coordinate { param, axis }))
    }

    /// `v[0]`, `w[2]`, `q[1]`...
    pub fn name(&self) -> String {
        format!("{}[{}]", self.param, self.axis)
    }

    /// The component of a gradient.
    pub fn of(&self, g: &super::loss::BodyGradient) -> f64 {
        g.get(self.param).to_array()[self.axis]
    }
}

/// Central difference `(L(p + ε) − L(p − ε)) / 2ε` of a `steps`-step run from `initial`
/// along coordinate `c` of body `body`.
pub fn central_difference(
    initial: &Simulation,
    steps: usize,
    loss: &dyn Loss,
    body: usize,
    c: Coordinate,
    eps: f64,
) -> Result<f64> {
    Ok((perturbed_loss(initial, steps, loss, body, c, eps)?
        - perturbed_loss(initial, steps, loss, body, c, -eps)?)
        / (2.0 * eps))
}

/// L after a `steps`-step run from `initial` with coordinate `c` of body `body` moved by `h`.
fn perturbed_loss(
    initial: &Simulation,
    steps: usize,
    loss: &dyn Loss,
    body: usize,
    c: Coordinate,
    h: f64,
) -> Result<f64> {
    let mut s = initial.clone();
    let b = &mut s.bodies_mut()[body];
    let state = c.param.perturbed(&b.state(), c.axis, h);
    b.set_state(&state);
    super::run::value(s, steps, loss)
}

/// How [`gradcheck`] checks.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GradcheckSettings {
    /// The central differences' step.
    pub eps: f64,
    /// Absolute tolerance.
    pub atol: f64,
    /// Relative tolerance (of |fd|).
    pub rtol: f64,
    /// The backward pass checked.
    pub options: GradientOptions,
    /// Also report the paper's approximation beside it (not checked): the pose dependence
    /// of the geometry dropped and the surface held fixed in the backward pass.
    pub compare_paper: bool,
}

impl Default for GradcheckSettings {
    /// ε = 1e-6 (larger steps cross the kinks of trilinear interpolation), rtol 1e-3, atol
    /// 1e-9, the full gradient.
    fn default() -> Self {
        GradcheckSettings {
            eps: 1e-6,
            atol: 1e-9,
            rtol: 1e-3,
            options: GradientOptions::default(),
            compare_paper: false,
        }
    }
}

/// One checked coordinate.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GradcheckRow {
    /// `<body>.v[0]`.
    pub name: String,
    /// The adjoint's component.
    pub adjoint: f64,
    /// The central difference at ε.
    pub fd: f64,
    /// The central difference at 10·ε.
    pub fd_coarse: f64,
    /// |adjoint − fd| / |fd| (with |fd| floored at 1e-300).
    pub rel_error: f64,
    /// |adjoint − fd| ≤ atol + rtol·|fd|.
    pub pass: bool,
    /// |fd − fd_coarse| ≤ atol + rtol·|fd|: the map is smooth at the scale of ε.
    pub consistent: bool,
    /// The one-sided differences (L(p + ε) − L(p)) / ε and (L(p) − L(p − ε)) / ε.
    pub fd_right: f64,
    /// See `fd_right`.
    pub fd_left: f64,
    /// The one-sided differences disagree by more than the criterion: the map has a kink at
    /// p, the central difference is the mean of its two slopes, and the row passes if the
    /// adjoint is one of them.
    pub kink: bool,
    /// The paper's approximation, when asked for.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub paper: Option<f64>,
}

/// A gradient check's result.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GradcheckReport {
    /// The loss.
    pub loss: f64,
    /// Steps run.
    pub steps: usize,
    /// The central differences' step.
    pub eps: f64,
    /// Absolute tolerance.
    pub atol: f64,
    /// Relative tolerance.
    pub rtol: f64,
    /// Wall time of the gradient's forward pass, s.
    pub forward_seconds: f64,
    /// Wall time of its backward pass, s.
    pub backward_seconds: f64,
    /// Tape bytes per step.
    pub tape_bytes_per_step: usize,
    /// One row per coordinate of each body that moves.
    pub params: Vec<GradcheckRow>,
}

impl GradcheckReport {
    /// The report as JSON: its fields, and with the paper's approximation a `paper` array of
    /// `{name, adjoint, fd, rel_error}`.
    pub fn to_json(&self) -> serde_json::Value {
        let mut json = serde_json::to_value(self).expect("serialisable");
        if self.params.iter().all(|r| r.paper.is_some()) {
            json["paper"] = self
                .params
                .iter()
                .map(|r| {
                    let paper = r.paper.unwrap_or(f64::NAN);
                    let rel = (paper - r.fd).abs() / r.fd.abs().max(1e-300);
                    serde_json::json!({ "name": r.name, "adjoint": paper, "fd": r.fd, "rel_error": rel })
                })
                .collect();
        }
        json
    }

    /// Whether every coordinate passes.
    pub fn passed(&self) -> bool {
        self.params.iter().all(|r| r.pass)
    }

    /// The largest relative error.
    pub fn worst_rel_error(&self) -> f64 {
        self.params.iter().map(|r| r.rel_error).fold(0.0, f64::max)
    }
}

impl std::fmt::Display for GradcheckReport {
    /// A table: one row per coordinate, with the paper's approximation when there is one.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let paper = self.params.iter().any(|r| r.paper.is_some());
        write!(
            f,
            "{:<12} {:>16} {:>16} {:>10} {:>5}",
            "param", "adjoint", "central diff", "rel err", "fd"
        )?;
        if paper {
            write!(f, " {:>16} {:>10}", "paper approx", "rel err")?;
        }
        writeln!(f)?;
        for r in &self.params {
            write!(
                f,
                "{:<12} {:>16.8e} {:>16.8e} {:>10.2e} {:>5}",
                r.name,
                r.adjoint,
                r.fd,
                r.rel_error,
                if r.kink {
                    "kink"
                } else if r.consistent {
                    "ok"
                } else {
                    "10ε≠"
                },
            )?;
            if let Some(p) = r.paper {
                write!(f, " {:>16.8e} {:>10.2e}", p, (p - r.fd).abs() / r.fd.abs().max(1e-300))?;
            }
            writeln!(f)?;
        }
        for r in self.params.iter().filter(|r| r.kink) {
            writeln!(
                f,
                "{}: a kink (one-sided slopes {:.8e} on the left, {:.8e} on the right); the \
                 adjoint {} one of them",
                r.name,
                r.fd_left,
                r.fd_right,
                if r.pass { "is" } else { "is not" }
            )?;
        }
        Ok(())
    }
}

/// L with one coordinate moved by h.
type Moved<'a> = Box<dyn Fn(f64) -> Result<f64> + Sync + 'a>;

/// One row of a check to be made: its name, the adjoint's component, the paper's, and L with
/// the coordinate moved by h.
struct RowSpec<'a> {
    name: String,
    adjoint: f64,
    paper: Option<f64>,
    at: Moved<'a>,
}

impl<'a> RowSpec<'a> {
    fn new(
        name: String,
        adjoint: f64,
        paper: Option<f64>,
        at: impl Fn(f64) -> Result<f64> + Sync + 'a,
    ) -> RowSpec<'a> {
        RowSpec { name, adjoint, paper, at: Box::new(at) }
    }
}

/// The rows of `specs`: each coordinate moved by ±ε and ±10·ε, the runs of a simulation
/// whose steps are spread `spread` ([`crate::math::pool::runs`]: side by side on a small
/// grid). The same values either way.
fn rows(
    specs: Vec<RowSpec<'_>>,
    l0: f64,
    s: &GradcheckSettings,
    spread: Spread,
) -> Result<Vec<GradcheckRow>> {
    let hs = [s.eps, -s.eps, 10.0 * s.eps, -10.0 * s.eps];
    let jobs: Vec<(usize, f64)> =
        (0..specs.len()).flat_map(|r| hs.iter().map(move |&h| (r, h))).collect();
    let run = |&(r, h): &(usize, f64)| (specs[r].at)(h);
    let values: Vec<f64> = runs(spread, &jobs, run).into_iter().collect::<Result<_>>()?;
    Ok(specs
        .into_iter()
        .zip(values.chunks(4))
        .map(|(spec, v)| {
            check_row(spec.name, spec.adjoint, [v[0], v[1], v[2], v[3]], l0, s, spec.paper)
        })
        .collect())
}

/// One row of a check: the adjoint's component against central differences of L with the
/// coordinate moved by ε, −ε, 10·ε and −10·ε (`at`; `l0` unmoved) at ε and 10·ε, and the
/// one-sided ones.
fn check_row(
    name: String,
    adjoint: f64,
    at: [f64; 4],
    l0: f64,
    s: &GradcheckSettings,
    paper: Option<f64>,
) -> GradcheckRow {
    let ok = |err: f64, fd: f64| err <= s.atol + s.rtol * fd.abs();
    let [plus, minus, coarse_plus, coarse_minus] = at;
    let fd = (plus - minus) / (2.0 * s.eps);
    let fd_coarse = (coarse_plus - coarse_minus) / (20.0 * s.eps);
    let (fd_right, fd_left) = ((plus - l0) / s.eps, (l0 - minus) / s.eps);
    let kink = !ok((fd_right - fd_left).abs(), fd_right.abs().max(fd_left.abs()));
    let err = (adjoint - fd).abs();
    let one_sided =
        ok((adjoint - fd_right).abs(), fd_right) || ok((adjoint - fd_left).abs(), fd_left);
    GradcheckRow {
        name,
        adjoint,
        fd,
        fd_coarse,
        rel_error: err / fd.abs().max(1e-300),
        pass: ok(err, fd) || (kink && one_sided),
        consistent: ok((fd - fd_coarse).abs(), fd),
        fd_right,
        fd_left,
        kink,
        paper,
    }
}

/// The adjoint gradient of a trajectory loss under `schedule` against central differences:
/// `samples` of the action entries (spread evenly over the actions, bodies and entries;
/// named `<body>.a<k>[<entry>]`) and every initial coordinate of every body that moves.
pub fn gradcheck_controlled(
    sim: &Simulation,
    schedule: &super::schedule::Schedule,
    loss: &dyn super::control::TrajectoryLoss,
    s: &GradcheckSettings,
    samples: usize,
) -> Result<GradcheckReport> {
    use super::control::{value_and_gradient_controlled, Trajectory};
    let run =
        value_and_gradient_controlled(sim, schedule, loss, &GradientSettings::from(s.options))?;
    let value = |schedule: &super::schedule::Schedule, start: &Simulation| -> Result<f64> {
        let mut sim = start.clone();
        let mut states = Vec::with_capacity(schedule.steps() + 1);
        for t in 0..schedule.steps() {
            states.push(sim.bodies().iter().map(|b| b.state()).collect());
            schedule.apply(&mut sim, t);
            sim.step()?;
        }
        states.push(sim.bodies().iter().map(|b| b.state()).collect());
        Ok(loss.value(&Trajectory { states: &states, final_state: &sim, schedule }))
    };
    let value = &value;
    let l0 = value(schedule, sim)?;
    let mut specs = Vec::new();
    let (k_n, j_n) = (schedule.actions.len(), schedule.bodies.len());
    let total = k_n * j_n * 6;
    let picked: Vec<usize> = if samples >= total {
        (0..total).collect()
    } else {
        (0..samples).map(|n| n * total / samples.max(1)).collect()
    };
    for idx in picked {
        let (k, j, d) = (idx / (6 * j_n), (idx / 6) % j_n, idx % 6);
        let at = move |h: f64| {
            let mut moved = schedule.clone();
            moved.actions[k][j][d] += h;
            value(&moved, sim)
        };
        let name = format!("{}.a{k}[{d}]", sim.bodies()[schedule.bodies[j].0].name);
        specs.push(RowSpec::new(name, run.actions[k][j][d], None, at));
    }
    for (b, body) in sim.bodies().iter().enumerate().filter(|(_, b)| b.moves()) {
        for c in Coordinate::all() {
            let at = move |h: f64| {
                let mut start = sim.clone();
                let moved = &mut start.bodies_mut()[b];
                let state = c.param.perturbed(&moved.state(), c.axis, h);
                moved.set_state(&state);
                value(schedule, &start)
            };
            let name = format!("{}.{}", body.name, c.name());
            specs.push(RowSpec::new(name, c.of(&run.initial.bodies[b]), None, at));
        }
        let at = move |h: f64| {
            let mut start = sim.clone();
            start.bodies_mut()[b].set_mass(body.mass + h);
            value(schedule, &start)
        };
        let name = format!("{}.mass", body.name);
        specs.push(RowSpec::new(name, run.initial.bodies[b].mass, None, at));
    }
    let params = rows(specs, l0, s, sim.spread())?;
    Ok(GradcheckReport {
        loss: run.loss,
        steps: schedule.steps(),
        eps: s.eps,
        atol: s.atol,
        rtol: s.rtol,
        forward_seconds: run.forward_seconds,
        backward_seconds: run.backward_seconds,
        tape_bytes_per_step: 0,
        params,
    })
}

/// The adjoint gradient of `loss` after `steps` steps from `sim` against central
/// differences, for every coordinate of every body that moves.
pub fn gradcheck(
    sim: &Simulation,
    steps: usize,
    loss: &dyn Loss,
    s: &GradcheckSettings,
) -> Result<GradcheckReport> {
    let run = value_and_gradient(sim, steps, loss, &GradientSettings::from(s.options))?;
    let paper = if s.compare_paper {
        let options = GradientOptions {
            mode: GradientMode::Paper,
            surface: SurfaceGradient::Frozen,
            ..s.options
        };
        Some(value_and_gradient(sim, steps, loss, &GradientSettings::from(options))?)
    } else {
        None
    };
    // L(p) by the same untaped steps as the differences.
    let mut base = sim.clone();
    for _ in 0..steps {
        base.step()?;
    }
    let l0 = loss.value(&base);
    let mut specs = Vec::new();
    for (b, body) in sim.bodies().iter().enumerate().filter(|(_, b)| b.moves()) {
        for c in Coordinate::all() {
            let at = move |h: f64| perturbed_loss(sim, steps, loss, b, c, h);
            let paper = paper.as_ref().map(|p| c.of(&p.gradient.bodies[b]));
            let name = format!("{}.{}", body.name, c.name());
            specs.push(RowSpec::new(name, c.of(&run.gradient.bodies[b]), paper, at));
        }
        let at = move |h: f64| {
            let mut start = sim.clone();
            start.bodies_mut()[b].set_mass(body.mass + h);
            for _ in 0..steps {
                start.step()?;
            }
            Ok(loss.value(&start))
        };
        let name = format!("{}.mass", body.name);
        let paper = paper.as_ref().map(|p| p.gradient.bodies[b].mass);
        specs.push(RowSpec::new(name, run.gradient.bodies[b].mass, paper, at));
    }
    let params = rows(specs, l0, s, sim.spread())?;
    Ok(GradcheckReport {
        loss: run.loss,
        steps,
        eps: s.eps,
        atol: s.atol,
        rtol: s.rtol,
        forward_seconds: run.forward_seconds,
        backward_seconds: run.backward_seconds,
        tape_bytes_per_step: run.tape_bytes_per_step,
        params,
    })
}
