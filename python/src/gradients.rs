//! Gradients from Python: a loss's value and gradient (`value_and_grad`), the Rust optimiser
//! (`optimize`), and a taped rollout whose backward pass is a vector–Jacobian product
//! (`rollout` and `Rollout`, what `diffluid.torch` builds its `autograd.Function` on).

use crate::convert::{
    lattice, options, quat_norm, read_flat, read_only, read_rows, row, rows, state_from,
    to_py_object, wxyz,
};
use crate::errors::{run, to_py, value_error};
use crate::loss::BodyTargetLoss;
use crate::scene::Scene;
use crate::sim::{mass_gradient, set_masses, sim, Simulation};
use diffluid::experiments::optimize::{Optimization, Outcome};
use diffluid::geometry::body::{BodyState, Motion, Param};
use diffluid::geometry::grid::Mac;
use diffluid::gradients::{
    value_and_gradient, value_and_smoothed_gradient, AdjointState, BodyAdjoint,
    BodyTargetLoss as RLoss, GradientOptions, GradientSettings, Rollout as RRollout, Smoothing,
    SmoothingEstimator, SmoothingScale,
};
use diffluid::math::{so3, Rotation, Vec3};
use diffluid::Simulation as RSim;
use numpy::{PyArray1, PyReadonlyArrayDyn};
use pyo3::exceptions::PyTypeError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};
use std::ops::ControlFlow;

/// The initial simulation, the loss and the horizon a gradient call starts from.
fn start(
    py: Python<'_>,
    scene: &Bound<'_, PyAny>,
    loss: Option<PyRef<'_, BodyTargetLoss>>,
    steps: Option<usize>,
) -> PyResult<(RSim, RLoss, usize)> {
    let sim = if let Ok(s) = scene.cast::<Scene>() {
        let scene = s.borrow().inner.clone();
        Simulation::from_scene(py, scene)?
    } else if let Ok(s) = scene.cast::<Simulation>() {
        sim(s)?.clone()
    } else {
        return Err(PyTypeError::new_err("scene: a diffluid.Scene or a diffluid.Simulation"));
    };
    let loss = match loss {
        Some(l) => l.resolve(&sim.inner)?,
        None => sim
            .loss
            .clone()
            .ok_or_else(|| value_error("no loss given and the scene has no [loss] section"))?,
    };
    let steps = steps.unwrap_or(sim.scene_steps);
    if steps == 0 {
        return Err(value_error("steps: must be at least 1"));
    }
    Ok((sim.inner, loss, steps))
}

/// Overrides parts of body `i`'s state from a dict of arrays (v, w, x: 3; q: 4).
fn apply_state(sim: &mut RSim, i: usize, state: &Bound<'_, PyDict>) -> PyResult<()> {
    let s = sim.bodies()[i].state();
    let mut parts: [Vec<f64>; 4] = [
        s.v.to_array().to_vec(),
        s.w.to_array().to_vec(),
        s.x.to_array().to_vec(),
        wxyz(s.q).to_vec(),
    ];
    for (k, v) in state.iter() {
        let key: String = k.extract()?;
        let part: Param = key
            .parse()
            .map_err(|_| value_error(format!("state: unknown part {key:?} (v, w, x, q)")))?;
        let slot = Param::ALL.iter().position(|p| *p == part).expect("one of the four");
        let a: PyReadonlyArrayDyn<'_, f64> = v.extract()?;
        parts[slot] = read_rows(&key, &a, 1, if slot == 3 { 4 } else { 3 })?.remove(0);
    }
    let st = state_from(&parts[0], &parts[1], &parts[2], &parts[3])?;
    let h = sim.handles()[i];
    sim.set_body_state(h, &st).map_err(to_py)
}

/// What `value_and_grad` differentiates with respect to: a part of the body's initial state,
/// its mass, or the initial fluid velocity.
#[derive(Clone, Copy)]
enum Wrt {
    Body(Param),
    Mass,
    U,
}

/// A `params` entry by name: "v", "w", "x", "q" (read through [`Param`]), "mass" or "u".
fn wrt(name: &str) -> PyResult<Wrt> {
    match name {
        "mass" => Ok(Wrt::Mass),
        "u" => Ok(Wrt::U),
        _ => name
            .parse()
            .map(Wrt::Body)
            .map_err(|_| value_error(format!("params: unknown {name:?} (v, w, x, q, mass, u)"))),
    }
}

/// The value of a loss on the final state and its gradient with respect to the initial state.
///
/// `scene` is a Scene (its initial state) or a Simulation (its current state). `loss` is a
/// BodyTargetLoss, or None for the scene's `[loss]`. `params` names what to differentiate
/// with respect to: any of "v", "w", "x", "q" (the loss body's, or `body`'s, initial linear
/// and angular velocity, position and orientation), "mass" (that body's mass, its inertia
/// scaling with it: :meth:`Simulation.set_mass`) and "u" (the initial fluid velocity).
/// `state` optionally overrides the loss body's initial state (a dict of arrays v, w, x, q).
///
/// Returns ``(loss, grads)``: grads maps each param to a float64 array: (3,) for v, w, x; for
/// q the gradient in the world-frame tangent space q → exp(θ)·q, (3,); for mass a float,
/// ∂L/∂m in 1/kg (0 for a body that is not dynamic); for u a tuple of the three face arrays.
/// `smoothing` (a dict: ``samples`` (even, at least 2; default 8), ``sigma`` (a dict of
/// ``v``, ``w``, ``x``, ``q``: the perturbation's σ per kind, m/s, rad/s, m, rad) and ``seed``
/// (default 0)) asks instead for the gradient of the loss smoothed over a Gaussian
/// perturbation of the bodies' initial state: the mean of the exact gradients of
/// `samples` runs at antithetic perturbations, for long horizons where the map jumps (see
/// docs/gradients.md, "A smoothed gradient for long horizons"). The loss is then the
/// runs' mean, and grads also holds ``standard_error``: each param's standard error of
/// the mean (not for "u", which smoothing leaves out).
/// The GIL is released for the whole forward and backward pass.
#[pyfunction]
#[pyo3(signature = (
    scene, loss = None, params = None, *, steps = None, state = None, body = None,
    surface = "live", mode = "full", checkpoint_every = None, through_contact = true,
    smoothing = None
))]
#[allow(clippy::too_many_arguments)]
pub fn value_and_grad<'py>(
    py: Python<'py>,
    scene: &Bound<'py, PyAny>,
    loss: Option<PyRef<'py, BodyTargetLoss>>,
    params: Option<Vec<String>>,
    steps: Option<usize>,
    state: Option<&Bound<'py, PyDict>>,
    body: Option<&Bound<'py, PyAny>>,
    surface: &str,
    mode: &str,
    checkpoint_every: Option<usize>,
    through_contact: bool,
    smoothing: Option<&Bound<'py, PyDict>>,
) -> PyResult<(f64, Bound<'py, PyDict>)> {
    let opts = options(surface, mode, through_contact)?;
    let smoothing = smoothing.map(smoothing_from).transpose()?;
    let (mut sim, loss, steps) = start(py, scene, loss, steps)?;
    let params: Vec<Wrt> = match params {
        None => Param::ALL.map(Wrt::Body).to_vec(),
        Some(names) => names.iter().map(|p| wrt(p)).collect::<PyResult<_>>()?,
    };
    let which = match body {
        None => loss.body,
        Some(b) => {
            let names: Vec<String> = sim.bodies().iter().map(|b| b.name.clone()).collect();
            if let Ok(i) = b.extract::<usize>() {
                if i >= names.len() {
                    return Err(value_error(format!("body index {i} out of range")));
                }
                i
            } else {
                let s: String = b.extract()?;
                names.iter().position(|n| *n == s).ok_or_else(|| {
                    value_error(format!("no body named {s:?} (bodies: {names:?})"))
                })?
            }
        }
    };
    if let Some(st) = state {
        apply_state(&mut sim, loss.body, st)?;
    }
    if checkpoint_every == Some(0) {
        return Err(value_error("checkpoint_every: must be at least 1"));
    }
    let settings = GradientSettings { options: opts, checkpoint_every, re_solve: false };
    let (value, g, errors) = match &smoothing {
        None => {
            let out = run(py, || value_and_gradient(&sim, steps, &loss, &settings))?;
            (out.loss, out.gradient, None)
        }
        Some(how) => {
            if params.iter().any(|p| matches!(p, Wrt::U)) {
                return Err(value_error(
                    "params: \"u\" has no smoothed gradient (smoothing perturbs the bodies)",
                ));
            }
            if how.estimator == SmoothingEstimator::Values {
                if let Some(name) = params.iter().find_map(|p| unperturbed(p, &how.sigma)) {
                    return Err(value_error(format!(
                        "params: {name:?} has no gradient from the losses alone (estimator \
                         \"values\"): it is not perturbed (give it a sigma > 0, or use the \
                         gradients)"
                    )));
                }
            }
            let out = run(py, || value_and_smoothed_gradient(&sim, steps, &loss, &settings, how))?;
            (out.loss, out.gradient, Some(out.standard_error))
        }
    };
    let grads = PyDict::new(py);
    if let Some(errors) = &errors {
        let se = PyDict::new(py);
        let b = errors[which];
        for p in &params {
            match *p {
                Wrt::Body(part) => se.set_item(part.name(), row(py, b.get(part).to_array())?)?,
                Wrt::Mass => se.set_item("mass", b.mass)?,
                Wrt::U => {}
            }
        }
        grads.set_item("standard_error", se)?;
    }
    for p in &params {
        let b = g.bodies[which];
        match *p {
            Wrt::Body(part) => grads.set_item(part.name(), row(py, b.get(part).to_array())?)?,
            Wrt::Mass => {
                let dynamic = sim.bodies()[which].motion == Motion::Dynamic;
                grads.set_item("mass", if dynamic { b.mass } else { 0.0 })?
            }
            Wrt::U => {
                let parts: Vec<Bound<'py, PyAny>> = (0..3)
                    .map(|a| lattice(py, sim.grid().faces(a).n, g.u.c[a].clone()))
                    .collect::<PyResult<_>>()?;
                grads.set_item("u", PyTuple::new(py, parts)?)?
            }
        }
    }
    Ok((value, grads))
}

/// The name of `p` if a smoothing of scales `sigma` does not perturb it (the mass never is;
/// ∂L/∂u₀ is refused before).
fn unperturbed(p: &Wrt, sigma: &SmoothingScale) -> Option<&'static str> {
    match *p {
        Wrt::Body(part) if sigma.of(part) == 0.0 => Some(part.name()),
        Wrt::Mass => Some("mass"),
        _ => None,
    }
}

/// A `smoothing` dict as [`Smoothing`]: samples (default 8), sigma {v, w, x, q} (each
/// default 0), seed (default 0), estimator ("gradients", the default, or "values"); an
/// unknown key or a bad value is a ValueError naming it.
fn smoothing_from(d: &Bound<'_, PyDict>) -> PyResult<Smoothing> {
    let mut out = Smoothing::new(8, SmoothingScale { v: 0.0, w: 0.0, x: 0.0, q: 0.0 }, 0);
    for (k, v) in d.iter() {
        let key: String = k.extract()?;
        match key.as_str() {
            "samples" => out.samples = v.extract()?,
            "estimator" => {
                let name: String = v.extract()?;
                let all = SmoothingEstimator::ALL;
                out.estimator = all.into_iter().find(|e| e.name() == name).ok_or_else(|| {
                    let names: Vec<&str> = all.iter().map(|e| e.name()).collect();
                    value_error(format!(
                        "smoothing.estimator: unknown estimator {name:?} ({})",
                        names.join(", ")
                    ))
                })?;
            }
            "seed" => out.seed = v.extract()?,
            "sigma" => {
                let sigma = v
                    .cast::<PyDict>()
                    .map_err(|_| value_error("smoothing.sigma: must be a dict of v, w, x, q"))?;
                for (k, v) in sigma.iter() {
                    let name: String = k.extract()?;
                    let x: f64 = v.extract()?;
                    match name.as_str() {
                        "v" => out.sigma.v = x,
                        "w" => out.sigma.w = x,
                        "x" => out.sigma.x = x,
                        "q" => out.sigma.q = x,
                        other => {
                            return Err(value_error(format!(
                                "smoothing.sigma: unknown key {other:?} (v, w, x, q)"
                            )))
                        }
                    }
                }
            }
            other => {
                return Err(value_error(format!(
                    "smoothing: unknown key {other:?} (samples, sigma, seed, estimator)"
                )))
            }
        }
    }
    out.validate().map_err(to_py)?;
    Ok(out)
}

/// Runs the scene's `[optimize]` section with diffluid's own optimiser (gradient descent,
/// Adam or L-BFGS), exactly as ``diffluid optimize`` does (without its files), and returns a
/// dict: history (a list of {epoch, loss, grad_norm, params, evaluations, and with smoothing
/// unsmoothed_loss}), params (the
/// final state {v, w, x, q}), final_loss, stopped, converged, evaluations. `epochs`
/// overrides the scene's (at least 1, as ``--epochs``). The GIL is released while it runs.
///
/// Ctrl-C (any signal whose handler raises) is noticed after each epoch: it raises
/// KeyboardInterrupt with the result so far attached as its ``result`` attribute (the same
/// dict, ``stopped`` saying it was interrupted, params and final_loss those of the last
/// epoch evaluated).
#[pyfunction]
#[pyo3(signature = (scene, *, epochs = None))]
pub fn optimize<'py>(
    py: Python<'py>,
    scene: &Bound<'py, Scene>,
    epochs: Option<i64>,
) -> PyResult<Bound<'py, PyDict>> {
    let mut s = scene.borrow().inner.clone();
    if let Some(e) = epochs {
        if e < 1 {
            return Err(value_error(format!("epochs: must be at least 1, got {e}")));
        }
        if let Some(o) = s.optimize.as_mut() {
            o.epochs = e as usize;
        }
    }
    let mut interrupt = None;
    let outcome = run(py, || {
        Optimization::new(s)?.run_while(None, None, |_| {
            match Python::attach(|py| py.check_signals()) {
                Ok(()) => ControlFlow::Continue(()),
                Err(e) => {
                    interrupt = Some(e);
                    ControlFlow::Break(())
                }
            }
        })
    })?;
    // A signal during the last epoch's final forward pass is kept with the result too.
    let interrupt = match interrupt {
        Some(e) => Some(e),
        None => py.check_signals().err(),
    };
    let d = outcome_dict(py, &outcome)?;
    if let Some(e) = interrupt {
        e.value(py).setattr("result", &d)?;
        return Err(e);
    }
    Ok(d)
}

/// What :func:`optimize` returns.
fn outcome_dict<'py>(py: Python<'py>, outcome: &Outcome) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("history", to_py_object(py, &outcome.history)?)?;
    d.set_item("params", to_py_object(py, &outcome.params)?)?;
    d.set_item("final_loss", outcome.final_loss)?;
    d.set_item("stopped", &outcome.stopped)?;
    d.set_item("converged", &outcome.converged)?;
    d.set_item("evaluations", outcome.evaluations)?;
    Ok(d)
}

/// A taped forward run from a given initial body state: the final state, and a backward
/// pass that turns a gradient on the final body state into one on the initial state (a
/// vector–Jacobian product through diffluid's adjoint). Made by :func:`rollout`; what
/// ``diffluid.torch.rollout`` keeps between its forward and backward.
#[pyclass(module = "diffluid._diffluid", name = "Rollout", frozen)]
pub struct Rollout {
    /// The run: the whole tape, or with checkpointing its snapshots and the last segment's
    /// tape.
    inner: RRollout,
    options: GradientOptions,
    /// |q| of each body's initial quaternion as given (the run starts from q/|q|).
    q_norms: Vec<f64>,
}

/// Body states as four row arrays (v, w, x, q).
fn state_rows<'py>(py: Python<'py>, s: &[BodyState]) -> PyResult<Bound<'py, PyTuple>> {
    PyTuple::new(
        py,
        [
            rows(py, s.iter().map(|b| b.v.to_array()))?,
            rows(py, s.iter().map(|b| b.w.to_array()))?,
            rows(py, s.iter().map(|b| b.x.to_array()))?,
            rows(py, s.iter().map(|b| wxyz(b.q)))?,
        ],
    )
}

/// Runs `steps` steps (default: the scene's) of `sim` from the initial body states `v`, `w`,
/// `x` (bodies, 3) and `q` (bodies, 4) ``[w, x, y, z]``, and optionally the
/// initial fluid velocity `u` (flat, in :meth:`Simulation.velocity_flat`'s order), taping
/// what the backward pass needs. The run starts from q/|q| (q unchanged when it is a unit
/// quaternion to round-off), and the backward pass differentiates through that
/// normalisation. `masses` (bodies,) optionally sets the bodies' masses first (as
/// :meth:`Simulation.set_mass`: each finite and > 0; the entries of bodies that are not
/// dynamic are ignored). `sim` itself is not changed. Raises GradientError at once
/// if the run cannot be differentiated with these options.
///
/// With `checkpoint_every` = k, only the state every k steps (and each step's pressure) is
/// kept, and the backward pass re-runs one segment at a time without solving again: memory
/// for k steps' tape instead of all of them, for about half a forward pass more; the
/// gradient is the same bit for bit.
#[pyfunction]
#[pyo3(signature = (
    sim, v, w, x, q, u = None, *, steps = None, surface = "live", mode = "full",
    through_contact = true, checkpoint_every = None, masses = None
))]
#[allow(clippy::too_many_arguments)]
pub fn rollout(
    py: Python<'_>,
    sim: &Bound<'_, Simulation>,
    v: PyReadonlyArrayDyn<'_, f64>,
    w: PyReadonlyArrayDyn<'_, f64>,
    x: PyReadonlyArrayDyn<'_, f64>,
    q: PyReadonlyArrayDyn<'_, f64>,
    u: Option<PyReadonlyArrayDyn<'_, f64>>,
    steps: Option<usize>,
    surface: &str,
    mode: &str,
    through_contact: bool,
    checkpoint_every: Option<usize>,
    masses: Option<PyReadonlyArrayDyn<'_, f64>>,
) -> PyResult<Rollout> {
    // A copy: no borrow of `sim` is held while the run releases the GIL.
    let sim = crate::sim::sim(sim)?.clone();
    let options = options(surface, mode, through_contact)?;
    if checkpoint_every == Some(0) {
        return Err(value_error("checkpoint_every: must be at least 1"));
    }
    let n = sim.inner.bodies().len();
    let (v, w, x, q) = (
        read_rows("v", &v, n, 3)?,
        read_rows("w", &w, n, 3)?,
        read_rows("x", &x, n, 3)?,
        read_rows("q", &q, n, 4)?,
    );
    let steps = steps.unwrap_or(sim.scene_steps);
    if steps == 0 {
        return Err(value_error("steps: must be at least 1"));
    }
    let mut initial = sim.inner.clone();
    for i in 0..n {
        let st = state_from(&v[i], &w[i], &x[i], &q[i])?;
        let h = initial.handles()[i];
        initial.set_body_state(h, &st).map_err(to_py)?;
    }
    if let Some(u) = u {
        let flat = read_flat("u", &u, sim.faces_len())?;
        initial.set_velocity_field(sim.mac_from_flat(&flat)).map_err(to_py)?;
    }
    if let Some(m) = masses {
        set_masses(&mut initial, &m)?;
    }
    let settings = GradientSettings { options, checkpoint_every, re_solve: false };
    let inner = run(py, || {
        let rollout = RRollout::run(&initial, steps, &settings)?;
        rollout.check(&options)?;
        Ok(rollout)
    })?;
    let q_norms = q.iter().map(|r| quat_norm(r)).collect();
    Ok(Rollout { inner, options, q_norms })
}

#[pymethods]
impl Rollout {
    /// The final body states: a tuple (v, w, x, q) of arrays (bodies, 3) and (bodies, 4).
    fn final_state<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let s: Vec<BodyState> =
            self.inner.final_state().bodies().iter().map(|b| b.state()).collect();
        state_rows(py, &s)
    }

    /// The simulation at the end of the run (a copy).
    fn final_simulation(&self) -> Simulation {
        Simulation {
            inner: self.inner.final_state().clone(),
            scene_steps: self.steps(),
            loss: None,
        }
    }

    /// Steps run.
    #[getter]
    fn steps(&self) -> usize {
        self.inner.steps()
    }

    /// The vector–Jacobian product: from the gradient of a loss on the final body state
    /// (gv, gw, gx: (bodies, 3); gq: (bodies, 4) in ``[w, x, y, z]``) the gradient on the
    /// initial state: a tuple (gv0, gw0, gx0, gq0, gu0, gm0). gq0 is the gradient on the q
    /// given, through q/|q| (so it has no component along q); gu0 is the
    /// gradient on the initial fluid velocity, flat, when `fluid` is true, else None; gm0
    /// (bodies,) is ∂L/∂(each body's mass), from the same sweep (0 for a body that is not
    /// dynamic). The
    /// backward pass is the adjoint of the linear loss L = Σ g·(final state), whose gradient
    /// is g itself. The tape is kept, so it can run again (``retain_graph``).
    #[pyo3(signature = (gv, gw, gx, gq, *, fluid = false))]
    fn backward<'py>(
        &self,
        py: Python<'py>,
        gv: PyReadonlyArrayDyn<'py, f64>,
        gw: PyReadonlyArrayDyn<'py, f64>,
        gx: PyReadonlyArrayDyn<'py, f64>,
        gq: PyReadonlyArrayDyn<'py, f64>,
        fluid: bool,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let initial = self.inner.initial();
        let n = initial.bodies().len();
        let (gv, gw, gx, gq) = (
            read_rows("gv", &gv, n, 3)?,
            read_rows("gw", &gw, n, 3)?,
            read_rows("gx", &gx, n, 3)?,
            read_rows("gq", &gq, n, 4)?,
        );
        let bodies: Vec<BodyAdjoint> = (0..n)
            .map(|i| BodyAdjoint {
                v: Vec3::new(gv[i][0], gv[i][1], gv[i][2]),
                w: Vec3::new(gw[i][0], gw[i][1], gw[i][2]),
                x: Vec3::new(gx[i][0], gx[i][1], gx[i][2]),
                q: Rotation::from_xyzw(gq[i][1], gq[i][2], gq[i][3], gq[i][0]),
            })
            .collect();
        let adj = AdjointState {
            u: Mac::zeros(initial.grid()),
            bodies,
            particles: Vec::new(),
            mass: Vec::new(),
        };
        let adj = run(py, || Ok(self.inner.backward(adj, &self.options)?.0))?;
        // The tangent part at q̂ = q/|q|, over |q|: the gradient through the normalisation.
        let q0: Vec<[f64; 4]> = adj
            .bodies
            .iter()
            .zip(initial.bodies())
            .zip(&self.q_norms)
            .map(|((a, b), n)| {
                let t = so3::from_tangent_gradient(b.q, so3::tangent_gradient(b.q, a.q));
                wxyz(t).map(|c| c / n)
            })
            .collect();
        let gu = if fluid {
            let flat: Vec<f64> = adj.u.c.iter().flatten().copied().collect();
            read_only(numpy::PyArray1::from_vec(py, flat))?
        } else {
            py.None().into_bound(py)
        };
        PyTuple::new(
            py,
            [
                rows(py, adj.bodies.iter().map(|a| a.v.to_array()))?,
                rows(py, adj.bodies.iter().map(|a| a.w.to_array()))?,
                rows(py, adj.bodies.iter().map(|a| a.x.to_array()))?,
                rows(py, q0.into_iter())?,
                gu,
                read_only(PyArray1::from_vec(py, mass_gradient(initial, &adj.mass)))?,
            ],
        )
    }
}
