//! Control through the water from Python: actions at every step on the steerable bodies (a
//! force and torque on a dynamic body, a velocity and angular velocity on a kinematic one),
//! a whole run under a schedule of actions kept for its backward pass (`controlled_run` and
//! `ControlledRun`, what `diffluid.torch.trajectory` builds on), and a run driven and taken
//! back one action at a time (`Stepper`, what `diffluid.torch.Stepper` builds on for a
//! closed-loop policy).
//!
//! A body's state crosses the boundary as one row of 13 numbers: x (3), q `[w, x, y, z]`
//! (4), v (3), ω (3); an action as one row of 6 per body of the simulation, the rows of
//! bodies that are not steered being ignored.

use crate::convert::{motion_name, options, quat_norm, read_only, read_rows, state_from, wxyz};
use crate::errors::{borrow_mut, run, to_py, value_error};
use crate::sim::{mass_gradient, set_masses, Simulation};
use diffluid::geometry::body::{BodyState, Motion};
use diffluid::gradients::backward::check_settings;
use diffluid::gradients::{
    BodyAdjoint, ControlledRun as RControlledRun, GradientOptions, GradientSettings, Schedule,
    Stepper as RStepper, TrajectorySeed,
};
use diffluid::math::{so3, Rotation, Vec3};
use diffluid::world::BodyHandle;
use diffluid::Simulation as RSim;
use numpy::ndarray::{Array2, Array3};
use numpy::{IntoPyArray, PyArray1, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyTuple;

/// Numbers in a body's state row: x (3), q (4), v (3), ω (3).
const STATE: usize = 13;
/// Numbers in an action row.
const ACTION: usize = 6;

/// A body state as its row: x, q `[w, x, y, z]`, v, ω.
fn state_row(s: &BodyState) -> [f64; STATE] {
    let (x, q, v, w) = (s.x.to_array(), wxyz(s.q), s.v.to_array(), s.w.to_array());
    [x[0], x[1], x[2], q[0], q[1], q[2], q[3], v[0], v[1], v[2], w[0], w[1], w[2]]
}

/// A body state from its row (q normalised as [`state_from`] does).
fn state_of_row(r: &[f64]) -> PyResult<BodyState> {
    state_from(&r[7..10], &r[10..13], &r[0..3], &r[3..7])
}

/// A body adjoint from a row of 13 gradients (∂L/∂q in the embedding, `[w, x, y, z]`).
fn adjoint_of_row(r: &[f64]) -> BodyAdjoint {
    BodyAdjoint {
        x: Vec3::new(r[0], r[1], r[2]),
        q: Rotation::from_xyzw(r[4], r[5], r[6], r[3]),
        v: Vec3::new(r[7], r[8], r[9]),
        w: Vec3::new(r[10], r[11], r[12]),
    }
}

/// A body adjoint as its row.
fn adjoint_row(a: &BodyAdjoint) -> [f64; STATE] {
    state_row(&BodyState { x: a.x, q: a.q, v: a.v, w: a.w })
}

/// The gradient on a quaternion `q0` as given (not necessarily of unit length), whose run
/// started from q̂ = q0/|q0|, from the adjoint `qbar` of q̂ in the embedding: its tangent
/// part at q̂ over |q0| (no component along q0).
fn through_normalisation(q_hat: Rotation, qbar: Rotation, norm: f64) -> [f64; 4] {
    wxyz(so3::from_tangent_gradient(q_hat, so3::tangent_gradient(q_hat, qbar))).map(|c| c / norm)
}

/// Rows of `W` numbers as a read-only array of shape `(shape.0, shape.1, W)`.
fn rows3<'py, const W: usize>(
    py: Python<'py>,
    shape: (usize, usize),
    rows: impl Iterator<Item = [f64; W]>,
) -> PyResult<Bound<'py, PyAny>> {
    let flat: Vec<f64> = rows.flat_map(|r| r.into_iter()).collect();
    let a = Array3::from_shape_vec((shape.0, shape.1, W), flat).expect("n × B rows of W");
    read_only(a.into_pyarray(py))
}

/// Rows of `W` numbers as a read-only array of shape `(n, W)`.
fn rows2<'py, const W: usize>(
    py: Python<'py>,
    rows: impl ExactSizeIterator<Item = [f64; W]>,
) -> PyResult<Bound<'py, PyAny>> {
    let n = rows.len();
    let flat: Vec<f64> = rows.flat_map(|r| r.into_iter()).collect();
    let a = Array2::from_shape_vec((n, W), flat).expect("n rows of W");
    read_only(a.into_pyarray(py))
}

/// The numbers of a `(n, rows, width)` array, checked (shape, finite); `n` free when None.
fn read_blocks(
    name: &str,
    a: &PyReadonlyArrayDyn<'_, f64>,
    n: Option<usize>,
    rows: usize,
    width: usize,
) -> PyResult<Vec<Vec<Vec<f64>>>> {
    let shape = a.shape().to_vec();
    let ok = shape.len() == 3
        && shape[1] == rows
        && shape[2] == width
        && n.is_none_or(|n| shape[0] == n)
        && shape[0] > 0;
    if !ok {
        let first = n.map_or("T ≥ 1".to_string(), |n| n.to_string());
        return Err(value_error(format!(
            "{name}: expected shape ({first}, {rows}, {width}), got {shape:?}"
        )));
    }
    let flat: Vec<f64> = a.as_array().iter().copied().collect();
    if let Some(at) = flat.iter().position(|x| !x.is_finite()) {
        let (k, i, d) = (at / (rows * width), at / width % rows, at % width);
        return Err(value_error(format!(
            "{name}[{k}, {i}, {d}] is {}, not a finite number",
            flat[at]
        )));
    }
    Ok(flat.chunks(rows * width).map(|b| b.chunks(width).map(<[f64]>::to_vec).collect()).collect())
}

/// An integer argument that must be at least 1.
fn at_least_one(name: &str, n: i64) -> PyResult<usize> {
    if n < 1 {
        return Err(value_error(format!("{name}: must be at least 1, got {n}")));
    }
    Ok(n as usize)
}

/// The bodies actions steer: the `bodies` named (indices or names; each must exist and be
/// dynamic or kinematic), or every dynamic and kinematic body of `sim`.
fn controlled(sim: &Simulation, bodies: Option<Vec<Bound<'_, PyAny>>>) -> PyResult<Vec<usize>> {
    let all = sim.inner.bodies();
    let out: Vec<usize> = match bodies {
        Some(list) => list.iter().map(|b| sim.body_index(b)).collect::<PyResult<_>>()?,
        None => (0..all.len())
            .filter(|&i| matches!(all[i].motion, Motion::Dynamic | Motion::Kinematic))
            .collect(),
    };
    if out.is_empty() {
        return Err(value_error(format!(
            "control.bodies: no body to steer (bodies: {}); make one kinematic with \
             Simulation.set_kinematic",
            describe(&sim.inner)
        )));
    }
    Ok(out)
}

/// The bodies and their motions, for messages.
fn describe(sim: &RSim) -> String {
    let parts: Vec<String> =
        sim.bodies().iter().map(|b| format!("{} ({})", b.name, motion_name(b.motion))).collect();
    if parts.is_empty() {
        "none".into()
    } else {
        parts.join(", ")
    }
}

/// `sim`'s state with the body rows `state` (x, q, v, ω), each body checked inside the tank.
fn with_state(sim: &RSim, state: &[Vec<f64>]) -> PyResult<RSim> {
    let mut out = sim.clone();
    for (i, r) in state.iter().enumerate() {
        let st = state_of_row(r)?;
        let h = out.handles()[i];
        out.set_body_state(h, &st).map_err(to_py)?;
    }
    Ok(out)
}

/// Per body, |q| of the state rows given (1 when none were given: the run's own unit q).
fn q_norms(state: Option<&[Vec<f64>]>, bodies: usize) -> Vec<f64> {
    match state {
        Some(s) => s.iter().map(|r| quat_norm(&r[3..7])).collect(),
        None => vec![1.0; bodies],
    }
}

/// The action of each controlled body from one row per body of the simulation.
fn pick(rows: &[Vec<f64>], controlled: &[usize]) -> Vec<[f64; ACTION]> {
    controlled.iter().map(|&i| rows[i].as_slice().try_into().expect("rows of 6")).collect()
}

/// A run under a schedule of actions, kept for its backward pass: the body states at every
/// action boundary, and a backward pass that turns a gradient on them into one on every
/// action and on the initial state (a vector–Jacobian product through diffluid's adjoint, in
/// one sweep). Made by :func:`controlled_run`; what ``diffluid.torch.trajectory`` keeps
/// between its forward and backward.
#[pyclass(module = "diffluid._diffluid", name = "ControlledRun", frozen)]
pub struct ControlledRun {
    inner: RControlledRun,
    options: GradientOptions,
    controlled: Vec<usize>,
    steps_per_action: usize,
    actions: usize,
    bodies: usize,
    /// |q| of the initial quaternions as given.
    q_norms: Vec<f64>,
}

/// Runs `sim` under `actions`, an array (T, bodies, 6): action k on body i, held for
/// `steps_per_action` steps (T·steps_per_action steps in all). A dynamic body's row is an
/// external force and torque (world frame, N and N·m), a kinematic body's its velocity and
/// angular velocity (m/s, rad/s); the rows of the bodies not steered are ignored (they must
/// still be finite). `bodies` names the steered bodies (indices or names, each dynamic or
/// kinematic); by default every dynamic and kinematic body. `state0` (bodies, 13: x, q
/// ``[w, x, y, z]``, v, ω) optionally sets the initial state (q normalised; the gradient
/// goes through the normalisation). `masses` (bodies,) optionally sets the bodies' masses
/// (as :meth:`Simulation.set_mass`: each finite and > 0; the entries of bodies that are not
/// dynamic are ignored). `sim` itself is not changed. Everything is checked before a step
/// is run (ValueError naming the argument). The GIL is released.
#[pyfunction]
#[pyo3(signature = (
    sim, actions, state0 = None, *, steps_per_action = 1, surface = "live", mode = "full",
    through_contact = true, checkpoint_every = None, bodies = None, masses = None
))]
#[allow(clippy::too_many_arguments)]
pub fn controlled_run(
    py: Python<'_>,
    sim: &Bound<'_, Simulation>,
    actions: PyReadonlyArrayDyn<'_, f64>,
    state0: Option<PyReadonlyArrayDyn<'_, f64>>,
    steps_per_action: i64,
    surface: &str,
    mode: &str,
    through_contact: bool,
    checkpoint_every: Option<i64>,
    bodies: Option<Vec<Bound<'_, PyAny>>>,
    masses: Option<PyReadonlyArrayDyn<'_, f64>>,
) -> PyResult<ControlledRun> {
    // A copy: no borrow of `sim` is held while the run releases the GIL.
    let sim = crate::sim::sim(sim)?.clone();
    let options = options(surface, mode, through_contact)?;
    let spa = at_least_one("steps_per_action", steps_per_action)?;
    let checkpoint_every =
        checkpoint_every.map(|k| at_least_one("checkpoint_every", k)).transpose()?;
    let n = sim.inner.bodies().len();
    let controlled = controlled(&sim, bodies)?;
    let rows = read_blocks("actions", &actions, None, n, ACTION)?;
    let state = state0.map(|s| read_rows("state0", &s, n, STATE)).transpose()?;
    let mut initial = match &state {
        Some(s) => with_state(&sim.inner, s)?,
        None => sim.inner.clone(),
    };
    if let Some(m) = masses {
        set_masses(&mut initial, &m)?;
    }
    let handles: Vec<BodyHandle> = controlled.iter().map(|&i| initial.handles()[i]).collect();
    let schedule =
        Schedule::new(&initial, &handles, spa, rows.iter().map(|r| pick(r, &controlled)).collect())
            .map_err(to_py)?;
    check_settings(&initial, false, &options).map_err(to_py)?;
    let settings = GradientSettings { options, checkpoint_every, re_solve: false };
    let inner = run(py, || RControlledRun::run(&initial, &schedule, &settings))?;
    Ok(ControlledRun {
        inner,
        options,
        controlled,
        steps_per_action: spa,
        actions: rows.len(),
        bodies: n,
        q_norms: q_norms(state.as_deref(), n),
    })
}

#[pymethods]
impl ControlledRun {
    /// The body states at the action boundaries, before each action (after k·steps_per_action
    /// steps, k = 0 ..= T): an array (T + 1, bodies, 13) of x, q ``[w, x, y, z]``, v, ω.
    fn states<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let states = self.inner.trajectory().states;
        rows3(
            py,
            (self.actions + 1, self.bodies),
            states.iter().step_by(self.steps_per_action).flatten().map(state_row),
        )
    }

    /// The body states after every step (before that step's action): an array
    /// (T·steps_per_action + 1, bodies, 13).
    fn step_states<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let states = self.inner.trajectory().states;
        rows3(py, (states.len(), self.bodies), states.iter().flatten().map(state_row))
    }

    /// The simulation at the end of the run (a copy).
    fn final_simulation(&self) -> Simulation {
        Simulation {
            inner: self.inner.trajectory().final_state.clone(),
            scene_steps: self.actions * self.steps_per_action,
            loss: None,
        }
    }

    /// Actions in the run (T).
    #[getter]
    fn num_actions(&self) -> usize {
        self.actions
    }

    /// Steps each action is held.
    #[getter]
    fn steps_per_action(&self) -> usize {
        self.steps_per_action
    }

    /// The steered bodies' indices.
    #[getter]
    fn controlled(&self) -> Vec<usize> {
        self.controlled.clone()
    }

    /// The vector–Jacobian product: from `grad` (T + 1, bodies, 13), the gradient of a loss
    /// on :meth:`states` (∂L/∂q in ``[w, x, y, z]``), the gradient on the actions
    /// (T, bodies, 6; zero rows for the bodies not steered), on the initial state
    /// (bodies, 13; through q's normalisation) and on the bodies' masses (bodies,; zero for
    /// the bodies that are not dynamic). One backward sweep; the run is kept, so it can go
    /// backward again.
    fn backward<'py>(
        &self,
        py: Python<'py>,
        grad: PyReadonlyArrayDyn<'py, f64>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let (t, n, spa) = (self.actions, self.bodies, self.steps_per_action);
        let g = read_blocks("grad", &grad, Some(t + 1), n, STATE)?;
        let mut seed = TrajectorySeed {
            states: vec![vec![BodyAdjoint::zero(); n]; t * spa + 1],
            actions: vec![vec![[0.0; ACTION]; self.controlled.len()]; t],
            liquid: None,
        };
        for (b, rows) in g.iter().enumerate() {
            seed.states[b * spa] = rows.iter().map(|r| adjoint_of_row(r)).collect();
        }
        let (ga, g0, _) = run(py, || self.inner.backward(&seed, &self.options))?;
        let mut actions = vec![[0.0; ACTION]; t * n];
        for (k, row) in ga.iter().enumerate() {
            for (&i, a) in self.controlled.iter().zip(row) {
                actions[k * n + i] = *a;
            }
        }
        let start = &self.inner.trajectory().states[0];
        // The gradient's q is ∂L/∂θ at q̂ = q/|q| (q → exp(θ)·q̂): in the embedding, over |q|.
        let initial = g0.bodies.iter().zip(start).zip(&self.q_norms).map(|((g, s), norm)| {
            let q = wxyz(so3::from_tangent_gradient(s.q, g.q)).map(|c| c / norm);
            let (x, v, w) = (g.x.to_array(), g.v.to_array(), g.w.to_array());
            [x[0], x[1], x[2], q[0], q[1], q[2], q[3], v[0], v[1], v[2], w[0], w[1], w[2]]
        });
        let masses: Vec<f64> = g0.bodies.iter().map(|b| b.mass).collect();
        let masses = mass_gradient(self.inner.trajectory().final_state, &masses);
        PyTuple::new(
            py,
            [
                rows3(py, (t, n), actions.into_iter())?,
                rows2(py, initial)?,
                read_only(PyArray1::from_vec(py, masses))?,
            ],
        )
    }

    fn __repr__(&self) -> String {
        format!(
            "ControlledRun(actions={}, steps_per_action={}, controlled={:?})",
            self.actions, self.steps_per_action, self.controlled
        )
    }
}

/// A run driven one action at a time and taken back one action at a time: what a
/// closed-loop policy trained through the simulator needs. The caller sees the bodies'
/// states; the liquid's adjoint is carried inside from one action's backward step to the
/// one before. What ``diffluid.torch.Stepper`` builds on.
///
/// :meth:`step` takes an action (bodies, 6) for `steps_per_action` taped steps and returns
/// the states after them (bodies, 13). :meth:`backward` takes action k back: it must be
/// called for the actions in reverse order (what an autograd engine does), each once. Once
/// a backward step has run, the stepper takes no more actions until :meth:`reset`.
#[pyclass(module = "diffluid._diffluid", name = "Stepper")]
pub struct Stepper {
    /// The simulation given, with the masses asked for (its liquid and bodies are where the
    /// run starts, unless the first step is handed another body state).
    base: RSim,
    inner: RStepper,
    controlled: Vec<usize>,
    steps_per_action: usize,
    options: GradientOptions,
    /// |q| of each body's initial quaternion as given, and the unit quaternion used.
    q_norms: Vec<f64>,
    q_start: Vec<Rotation>,
    /// Actions taken in the runs before the last reset: this run's action k is numbered
    /// `offset + k`, so that an autograd graph of an earlier run cannot take back this one's.
    offset: usize,
    /// Actions taken.
    taken: usize,
    /// Actions taken and not yet taken back.
    remaining: usize,
    /// Whether a backward step has run (the stepper takes no more actions).
    backward_started: bool,
    /// Why the stepper can no longer be used (a step or a backward step that failed).
    broken: Option<String>,
}

impl Stepper {
    fn start(
        base: &RSim,
        controlled: &[usize],
        spa: usize,
        options: GradientOptions,
    ) -> PyResult<RStepper> {
        let handles: Vec<BodyHandle> = controlled.iter().map(|&i| base.handles()[i]).collect();
        RStepper::new(base, &handles, spa, options).map_err(to_py)
    }

    fn usable(&self) -> PyResult<()> {
        match &self.broken {
            Some(why) => Err(value_error(format!(
                "this Stepper cannot be used any more ({why}); reset() it or make a new one"
            ))),
            None => Ok(()),
        }
    }

    fn current(&self) -> Vec<[f64; STATE]> {
        self.inner.states().iter().map(state_row).collect()
    }

    /// ∂L/∂m of every body over the actions taken back so far (zero for bodies not dynamic).
    fn masses_bar(&self) -> Vec<f64> {
        mass_gradient(&self.base, &self.inner.mass_gradient())
    }
}

/// Stepper `slf` to use (a clear error when another thread is using it).
fn stepper<'py>(slf: &Bound<'py, Stepper>) -> PyResult<PyRefMut<'py, Stepper>> {
    borrow_mut(slf, "Stepper")
}

#[pymethods]
impl Stepper {
    /// A run from `sim`'s current state (`sim` itself is not changed), steering `bodies`
    /// (indices or names, each dynamic or kinematic; default: every dynamic and kinematic
    /// body), each action held `steps_per_action` steps; `surface`, `mode` and
    /// `through_contact` are the backward pass's options. `masses` (bodies,) optionally sets
    /// the bodies' masses for the run (each finite and > 0; the entries of bodies that are
    /// not dynamic are ignored); :meth:`mass_gradient` gives ∂L/∂m.
    #[new]
    #[pyo3(signature = (
        sim, *, steps_per_action = 1, surface = "live", mode = "full", through_contact = true,
        bodies = None, masses = None
    ))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        sim: &Bound<'_, Simulation>,
        steps_per_action: i64,
        surface: &str,
        mode: &str,
        through_contact: bool,
        bodies: Option<Vec<Bound<'_, PyAny>>>,
        masses: Option<PyReadonlyArrayDyn<'_, f64>>,
    ) -> PyResult<Stepper> {
        let sim = crate::sim::sim(sim)?;
        let options = options(surface, mode, through_contact)?;
        let spa = at_least_one("steps_per_action", steps_per_action)?;
        let controlled = controlled(&sim, bodies)?;
        let mut base = sim.inner.clone();
        if let Some(m) = masses {
            set_masses(&mut base, &m)?;
        }
        check_settings(&base, false, &options).map_err(to_py)?;
        let inner = Stepper::start(&base, &controlled, spa, options)?;
        let n = base.bodies().len();
        let q_start = base.bodies().iter().map(|b| b.q).collect();
        Ok(Stepper {
            base,
            inner,
            controlled,
            steps_per_action: spa,
            options,
            q_norms: vec![1.0; n],
            q_start,
            offset: 0,
            taken: 0,
            remaining: 0,
            backward_started: false,
            broken: None,
        })
    }

    /// Takes `action` (bodies, 6; the rows of the bodies not steered ignored) for
    /// `steps_per_action` taped steps from `state` (bodies, 13), and returns ``(k, states)``:
    /// the action's number and the body states after it (bodies, 13). `state` must be the
    /// states the last step returned (ValueError otherwise: a stepper goes on from where it
    /// is); before the first step it may be any state, which the run then starts from (q
    /// normalised). None: go on from where the run is. The GIL is released.
    #[pyo3(signature = (action, state = None))]
    fn step<'py>(
        slf: &Bound<'py, Self>,
        py: Python<'py>,
        action: PyReadonlyArrayDyn<'py, f64>,
        state: Option<PyReadonlyArrayDyn<'py, f64>>,
    ) -> PyResult<(usize, Bound<'py, PyAny>)> {
        let mut this = stepper(slf)?;
        let this = &mut *this;
        this.usable()?;
        if this.backward_started {
            return Err(value_error(
                "this Stepper's actions are being taken back (a backward pass ran): it takes no \
                 more actions; reset() starts a new run from the same state, or go on from \
                 where it is with a new Stepper (Stepper(stepper.simulation(), ...))",
            ));
        }
        let n = this.base.bodies().len();
        let rows = read_rows("action", &action, n, ACTION)?;
        let action = pick(&rows, &this.controlled);
        if let Some(s) = state {
            let s = read_rows("state", &s, n, STATE)?;
            let same = s.iter().zip(this.current()).all(|(a, b)| a.as_slice() == b.as_slice());
            if !same {
                if this.taken > 0 {
                    return Err(value_error(format!(
                        "state: not the states step {} returned; a Stepper goes on from where \
                         it is (to start elsewhere, reset() it or make a new one)",
                        this.offset + this.taken - 1
                    )));
                }
                let start = with_state(&this.base, &s)?;
                this.inner =
                    Stepper::start(&start, &this.controlled, this.steps_per_action, this.options)?;
                this.q_norms = s.iter().map(|r| quat_norm(&r[3..7])).collect();
                this.q_start = start.bodies().iter().map(|b| b.q).collect();
            }
        }
        let inner = &mut this.inner;
        match run(py, || inner.step(&action)) {
            Ok(states) => {
                let k = this.offset + this.taken;
                this.taken += 1;
                this.remaining += 1;
                Ok((k, rows2(py, states.iter().map(state_row))?))
            }
            Err(e) => {
                this.broken = Some(format!("step {} failed", this.offset + this.taken));
                Err(e)
            }
        }
    }

    /// Takes action `k` back: from `grad` (bodies, 13), ∂L/∂(the states after it), returns
    /// ``(grad_action, grad_state, grad_masses)``: ∂L/∂(action k) (bodies, 6; zero rows for
    /// the bodies not steered), ∂L/∂(the states before it) (bodies, 13; for the run's first
    /// action through q's normalisation) and what action k's steps add to ∂L/∂(the masses)
    /// (bodies,; zero for bodies that are not dynamic; summed over the actions, the run's
    /// :meth:`mass_gradient`). The liquid's adjoint is carried from action k + 1, taken back
    /// before. Actions after k that were never taken back (the loss does not read them) are
    /// dropped first, at the cost of a backward step each. Each action goes back once: asking
    /// for one taken back already (a second backward pass through the same steps), or for
    /// one of a run before :meth:`reset`, is a ValueError. The GIL is released.
    fn backward<'py>(
        slf: &Bound<'py, Self>,
        py: Python<'py>,
        k: usize,
        grad: PyReadonlyArrayDyn<'py, f64>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let mut this = stepper(slf)?;
        let this = &mut *this;
        this.usable()?;
        if k < this.offset {
            return Err(value_error(format!(
                "action {k} belongs to a run before reset(): its steps cannot be taken back"
            )));
        }
        let local = k - this.offset;
        if local >= this.taken {
            return Err(value_error(format!(
                "action {k}: this Stepper took {} actions",
                this.offset + this.taken
            )));
        }
        if local >= this.remaining {
            return Err(value_error(format!(
                "action {k} was already taken back: a Stepper's steps go backward once, last \
                 first (a second backward pass through the same steps, e.g. with \
                 retain_graph=True, is not supported; sum the losses and call backward once, \
                 or run the steps again after reset())"
            )));
        }
        let n = this.base.bodies().len();
        let g = read_rows("grad", &grad, n, STATE)?;
        let after: Vec<BodyAdjoint> = g.iter().map(|r| adjoint_of_row(r)).collect();
        this.backward_started = true;
        let drop = this.remaining - (local + 1);
        let masses_before = this.masses_bar();
        let inner = &mut this.inner;
        let out = run(py, || {
            let zero = vec![BodyAdjoint::zero(); n];
            for _ in 0..drop {
                inner.backward(&zero)?;
            }
            inner.backward(&after)
        });
        let (ga, before) = match out {
            Ok(o) => o,
            Err(e) => {
                this.broken = Some(format!("taking action {k} back failed"));
                return Err(e);
            }
        };
        this.remaining = local;
        let masses: Vec<f64> =
            this.masses_bar().iter().zip(&masses_before).map(|(a, b)| a - b).collect();
        let mut actions = vec![[0.0; ACTION]; n];
        for (&i, a) in this.controlled.iter().zip(&ga) {
            actions[i] = *a;
        }
        let before = before.iter().enumerate().map(|(i, a)| {
            let mut r = adjoint_row(a);
            if local == 0 {
                let q = through_normalisation(this.q_start[i], a.q, this.q_norms[i]);
                r[3..7].copy_from_slice(&q);
            }
            r
        });
        let before: Vec<[f64; STATE]> = before.collect();
        PyTuple::new(
            py,
            [
                rows2(py, actions.into_iter())?,
                rows2(py, before.into_iter())?,
                read_only(PyArray1::from_vec(py, masses))?,
            ],
        )
    }

    /// ∂L/∂(each body's mass) (bodies,), summed over the actions taken back so far: the
    /// run's once its backward pass has reached its first action (zero before; zero for the
    /// bodies that are not dynamic). The masses are :attr:`masses`.
    fn mass_gradient<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let m = stepper(slf)?.masses_bar();
        read_only(PyArray1::from_vec(py, m))
    }

    /// The bodies' masses in the run (bodies,), kg.
    #[getter]
    fn masses<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let m: Vec<f64> = stepper(slf)?.base.bodies().iter().map(|b| b.mass).collect();
        read_only(PyArray1::from_vec(py, m))
    }

    /// Starts a new run from where this one started (the state its first step was handed,
    /// or the simulation's), every action and adjoint dropped, optionally with new `masses`
    /// (bodies,; checked as in the constructor): the next episode of a policy's training.
    /// Also makes a stepper whose step failed usable again. The actions of the runs before
    /// cannot be taken back after it (their numbers go on from theirs).
    #[pyo3(signature = (masses = None))]
    fn reset(slf: &Bound<'_, Self>, masses: Option<PyReadonlyArrayDyn<'_, f64>>) -> PyResult<()> {
        let mut this = stepper(slf)?;
        let this = &mut *this;
        let mut base = this.base.clone();
        if let Some(m) = &masses {
            set_masses(&mut base, m)?;
        }
        this.inner.reset();
        if masses.is_some() {
            let mut start = this.inner.simulation().clone();
            for (&h, m) in base.handles().iter().zip(base.bodies()) {
                start.set_mass(h, m.mass).map_err(crate::errors::to_py)?;
            }
            this.inner =
                Stepper::start(&start, &this.controlled, this.steps_per_action, this.options)?;
            this.base = base;
        }
        this.offset += this.taken;
        this.taken = 0;
        this.remaining = 0;
        this.backward_started = false;
        this.broken = None;
        Ok(())
    }

    /// The body states now (bodies, 13).
    fn states<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let rows = stepper(slf)?.current();
        rows2(py, rows.into_iter())
    }

    /// The simulation now (a copy): to look at, or to go on from with a new Stepper.
    fn simulation(slf: &Bound<'_, Self>) -> PyResult<Simulation> {
        let this = stepper(slf)?;
        Ok(Simulation {
            inner: this.inner.simulation().clone(),
            scene_steps: this.steps_per_action,
            loss: None,
        })
    }

    /// Actions taken in this run (since the last :meth:`reset`).
    #[getter]
    fn steps_taken(slf: &Bound<'_, Self>) -> PyResult<usize> {
        Ok(stepper(slf)?.taken)
    }

    /// Actions taken and not yet taken back.
    #[getter]
    fn actions_pending(slf: &Bound<'_, Self>) -> PyResult<usize> {
        Ok(stepper(slf)?.inner.actions_taken())
    }

    /// Steps each action is held.
    #[getter]
    fn steps_per_action(slf: &Bound<'_, Self>) -> PyResult<usize> {
        Ok(stepper(slf)?.steps_per_action)
    }

    /// The steered bodies' indices.
    #[getter]
    fn controlled(slf: &Bound<'_, Self>) -> PyResult<Vec<usize>> {
        Ok(stepper(slf)?.controlled.clone())
    }

    fn __repr__(slf: &Bound<'_, Self>) -> String {
        let Ok(this) = slf.try_borrow() else {
            return "Stepper(<in use by another thread>)".into();
        };
        format!(
            "Stepper(steps_per_action={}, controlled={:?}, actions taken={}, not taken back={})",
            this.steps_per_action, this.controlled, this.taken, this.remaining
        )
    }
}
