//! `diffluid.Simulation`: a running simulation, its bodies and fields as NumPy arrays.

use crate::scene::Scene;
use crate::{lattice, read_flat, read_rows, row, rows, run, to_py_object, value_error};
use diffluid::geometry::body::{BodyState, Motion};
use diffluid::geometry::grid::Mac;
use diffluid::gradients::{BodyTargetLoss, Loss};
use diffluid::math::{Rotation, Vec3};
use diffluid::Simulation as RSim;
use numpy::PyReadonlyArrayDyn;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};

/// A running simulation: the liquid on a MAC grid, its marker particles and the rigid bodies
/// coupled to it. ``Simulation(scene)`` is the scene's initial state.
///
/// Every array it hands out is a float64 copy, marked read-only; change the state with the
/// setters. Quaternions are ``[w, x, y, z]``, as in scene files. Grid fields are indexed
/// ``[i, j, k]`` (x, y up, z). ``step`` and ``advance`` release the GIL.
#[pyclass(module = "diffluid._diffluid", name = "Simulation")]
#[derive(Clone)]
pub struct Simulation {
    pub(crate) inner: RSim,
    /// The scene's `time.steps`: the default horizon of runs and gradients.
    pub(crate) scene_steps: usize,
    /// The scene's `[loss]`, if any: the default loss of gradients.
    pub(crate) loss: Option<BodyTargetLoss>,
}

impl Simulation {
    /// The scene's simulation in its initial state (the GIL released while it builds).
    pub(crate) fn from_scene(py: Python<'_>, scene: &Scene) -> PyResult<Simulation> {
        let s = &scene.inner;
        let inner = run(py, || s.build())?;
        Ok(Simulation { inner, scene_steps: s.time.steps, loss: s.loss() })
    }

    /// The index of body `body` (an index or a name).
    pub(crate) fn body_index(&self, body: &Bound<'_, PyAny>) -> PyResult<usize> {
        let n = self.inner.bodies().len();
        if let Ok(i) = body.extract::<i64>() {
            if i < 0 || i as usize >= n {
                return Err(value_error(format!("body index {i} out of range ({n} bodies)")));
            }
            return Ok(i as usize);
        }
        if let Ok(name) = body.extract::<String>() {
            return self.inner.bodies().iter().position(|b| b.name == name).ok_or_else(|| {
                value_error(format!("no body named {name:?} (bodies: {:?})", self.names()))
            });
        }
        Err(pyo3::exceptions::PyTypeError::new_err(format!(
            "a body is an index or a name, not {}",
            body.get_type().name()?
        )))
    }

    fn names(&self) -> Vec<String> {
        self.inner.bodies().iter().map(|b| b.name.clone()).collect()
    }

    /// The lattice sizes of the three face arrays.
    pub(crate) fn face_shapes(&self) -> [[usize; 3]; 3] {
        [0, 1, 2].map(|a| self.inner.grid().faces(a).n)
    }

    /// Number of face samples in all.
    pub(crate) fn faces_len(&self) -> usize {
        self.face_shapes().iter().map(|n| n[0] * n[1] * n[2]).sum()
    }

    /// A flat (u, v, w) vector as a MAC field.
    pub(crate) fn mac_from_flat(&self, flat: &[f64]) -> Mac {
        let mut m = Mac::zeros(self.inner.grid());
        let mut at = 0;
        for a in 0..3 {
            let n = m.c[a].len();
            m.c[a].copy_from_slice(&flat[at..at + n]);
            at += n;
        }
        m
    }
}

/// A body state from rows of numbers (v, ω, x as 3, q as `[w, x, y, z]`). `q` is
/// normalised unless it is already a unit quaternion to round-off, which is kept bit for bit
/// (so that handing a simulation its own state back changes nothing).
pub(crate) fn state_from(v: &[f64], w: &[f64], x: &[f64], q: &[f64]) -> PyResult<BodyState> {
    let norm = quat_norm(q);
    if norm < 1e-12 {
        return Err(value_error("q: the zero quaternion is no orientation"));
    }
    let s = if (norm - 1.0).abs() <= 4.0 * f64::EPSILON { 1.0 } else { 1.0 / norm };
    Ok(BodyState {
        v: Vec3::new(v[0], v[1], v[2]),
        w: Vec3::new(w[0], w[1], w[2]),
        x: Vec3::new(x[0], x[1], x[2]),
        q: Rotation::from_xyzw(q[1] * s, q[2] * s, q[3] * s, q[0] * s),
    })
}

/// |q| of a quaternion's four numbers.
pub(crate) fn quat_norm(q: &[f64]) -> f64 {
    q.iter().map(|c| c * c).sum::<f64>().sqrt()
}

/// A motion's Python name.
pub(crate) fn motion_name(m: Motion) -> &'static str {
    match m {
        Motion::Dynamic => "dynamic",
        Motion::Fixed => "fixed",
        Motion::External => "external",
        Motion::Kinematic => "kinematic",
    }
}

/// `[w, x, y, z]`.
pub(crate) fn wxyz(q: Rotation) -> [f64; 4] {
    [q.w, q.x, q.y, q.z]
}

#[pymethods]
impl Simulation {
    /// The scene's simulation in its initial state.
    #[new]
    fn new(py: Python<'_>, scene: PyRef<'_, Scene>) -> PyResult<Simulation> {
        Simulation::from_scene(py, &scene)
    }

    /// Advances one step of the fixed Δt and returns its report as a dict (step, time,
    /// liquid_cells, cg_iterations, cg_relative_residual, density_cg_iterations,
    /// max_divergence, liquid_volume,
    /// max_speed, kinetic_energy, bodies: [{name, force, torque, volume_error}],
    /// contact_iterations, contact_residual, stage_seconds, and warnings when there are any).
    ///
    /// Raises SolverError when the pressure solve does not converge and SimulationError when
    /// the state blows up or a body leaves the tank.
    fn step<'py>(&mut self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let sim = &mut self.inner;
        let report = run(py, || sim.step())?;
        to_py_object(py, &report)
    }

    /// Advances `steps` steps (default: the scene's `time.steps`) in one call, the GIL
    /// released throughout, and returns the last step's report.
    #[pyo3(signature = (steps = None))]
    fn run<'py>(&mut self, py: Python<'py>, steps: Option<usize>) -> PyResult<Bound<'py, PyAny>> {
        let n = steps.unwrap_or(self.scene_steps);
        if n == 0 {
            return Err(value_error("steps: must be at least 1"));
        }
        let sim = &mut self.inner;
        let report = run(py, || {
            let mut last = None;
            for _ in 0..n {
                last = Some(sim.step()?);
            }
            Ok(last.expect("at least one step"))
        })?;
        to_py_object(py, &report)
    }

    /// Advances by `frame_dt` seconds in as many CFL-limited steps as needed (a game or
    /// robot loop's frame) and returns their reports.
    fn advance<'py>(&mut self, py: Python<'py>, frame_dt: f64) -> PyResult<Bound<'py, PyList>> {
        let sim = &mut self.inner;
        let reports = run(py, || sim.advance(frame_dt))?;
        let out = PyList::empty(py);
        for r in &reports {
            out.append(to_py_object(py, r)?)?;
        }
        Ok(out)
    }

    /// An independent copy (the same state; stepping one does not move the other).
    fn copy(&self) -> Simulation {
        self.clone()
    }

    fn __copy__(&self) -> Simulation {
        self.clone()
    }

    fn __deepcopy__(&self, _memo: &Bound<'_, PyAny>) -> Simulation {
        self.clone()
    }

    /// Simulated time, s.
    #[getter]
    fn time(&self) -> f64 {
        self.inner.time()
    }

    /// Steps taken so far.
    #[getter]
    fn steps_taken(&self) -> usize {
        self.inner.steps_taken()
    }

    /// The scene's `time.steps` (the default horizon of `run` and the gradients).
    #[getter]
    fn scene_steps(&self) -> usize {
        self.scene_steps
    }

    /// The fixed step Δt, s.
    #[getter]
    fn dt(&self) -> f64 {
        self.inner.dt()
    }

    /// Cell side, m.
    #[getter]
    fn dx(&self) -> f64 {
        self.inner.grid().dx
    }

    /// Cells along x, y, z.
    #[getter]
    fn shape(&self) -> [usize; 3] {
        self.inner.grid().n
    }

    /// Every warning so far, each once.
    #[getter]
    fn warnings(&self) -> Vec<String> {
        self.inner.warnings().to_vec()
    }

    /// The bodies' names, in order.
    #[getter]
    fn body_names(&self) -> Vec<String> {
        self.names()
    }

    /// Number of bodies.
    #[getter]
    fn num_bodies(&self) -> usize {
        self.inner.bodies().len()
    }

    /// Centres of mass, shape (bodies, 3), m.
    #[getter]
    fn positions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        rows(py, self.inner.bodies().iter().map(|b| b.x.to_array()))
    }

    /// Orientations as quaternions ``[w, x, y, z]``, shape (bodies, 4).
    #[getter]
    fn orientations<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        rows(py, self.inner.bodies().iter().map(|b| wxyz(b.q)))
    }

    /// Linear velocities of the centres of mass, shape (bodies, 3), m/s.
    #[getter]
    fn velocities<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        rows(py, self.inner.bodies().iter().map(|b| b.v.to_array()))
    }

    /// Angular velocities (world frame), shape (bodies, 3), rad/s.
    #[getter]
    fn angular_velocities<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        rows(py, self.inner.bodies().iter().map(|b| b.w.to_array()))
    }

    /// The pressure force (N) and torque (N·m, about the centre of mass) of the last step's
    /// solve on each body: a pair of arrays of shape (bodies, 3), zero before the first step.
    fn fluid_forces<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let ft: Vec<(Vec3, Vec3)> = self
            .inner
            .handles()
            .iter()
            .map(|&h| self.inner.fluid_force(h).expect("a handle of this simulation"))
            .collect();
        let f = rows(py, ft.iter().map(|(f, _)| f.to_array()))?;
        let t = rows(py, ft.iter().map(|(_, t)| t.to_array()))?;
        PyTuple::new(py, [f, t])
    }

    /// Body `body`'s (an index or a name) state as a dict of arrays: v (3,), w (3,), x (3,)
    /// and q (4,) ``[w, x, y, z]``.
    fn body_state<'py>(
        &self,
        py: Python<'py>,
        body: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let b = &self.inner.bodies()[self.body_index(body)?];
        let d = PyDict::new(py);
        d.set_item("v", row(py, b.v.to_array())?)?;
        d.set_item("w", row(py, b.w.to_array())?)?;
        d.set_item("x", row(py, b.x.to_array())?)?;
        d.set_item("q", row(py, wxyz(b.q))?)?;
        Ok(d)
    }

    /// Sets parts of body `body`'s state (an index or a name): any of v, w (3,), x (3,)
    /// and q (4,) ``[w, x, y, z]``, normalised. The body must stay inside the tank, and every
    /// number must be finite (ValueError otherwise); arrays must be float64 (TypeError).
    #[pyo3(signature = (body, *, v = None, w = None, x = None, q = None))]
    fn set_body_state(
        &mut self,
        body: &Bound<'_, PyAny>,
        v: Option<PyReadonlyArrayDyn<'_, f64>>,
        w: Option<PyReadonlyArrayDyn<'_, f64>>,
        x: Option<PyReadonlyArrayDyn<'_, f64>>,
        q: Option<PyReadonlyArrayDyn<'_, f64>>,
    ) -> PyResult<()> {
        let i = self.body_index(body)?;
        let s = self.inner.bodies()[i].state();
        let part = |name: &str, a: &Option<PyReadonlyArrayDyn<'_, f64>>, old: Vec<f64>| {
            a.as_ref().map_or(Ok(old), |a| {
                read_rows(name, a, 1, if name == "q" { 4 } else { 3 }).map(|r| r[0].clone())
            })
        };
        let v = part("v", &v, s.v.to_array().to_vec())?;
        let w = part("w", &w, s.w.to_array().to_vec())?;
        let x = part("x", &x, s.x.to_array().to_vec())?;
        let q = part("q", &q, wxyz(s.q).to_vec())?;
        let state = state_from(&v, &w, &x, &q)?;
        let h = self.inner.handles()[i];
        self.inner.set_body_state(h, &state).map_err(crate::to_py)
    }

    /// Sets the external force (N, on the centre of mass) and torque (N·m) on body `body`,
    /// world frame, float64 arrays of 3; they act every step, with gravity, until changed.
    #[pyo3(signature = (body, force, torque = None))]
    fn set_external_force(
        &mut self,
        body: &Bound<'_, PyAny>,
        force: PyReadonlyArrayDyn<'_, f64>,
        torque: Option<PyReadonlyArrayDyn<'_, f64>>,
    ) -> PyResult<()> {
        let i = self.body_index(body)?;
        let f = read_rows("force", &force, 1, 3)?.remove(0);
        let t = match torque {
            Some(t) => read_rows("torque", &t, 1, 3)?.remove(0),
            None => vec![0.0; 3],
        };
        let h = self.inner.handles()[i];
        self.inner
            .set_external_force(h, Vec3::new(f[0], f[1], f[2]), Vec3::new(t[0], t[1], t[2]))
            .map_err(crate::to_py)
    }

    /// How each body moves, in order: "dynamic" (moved by the liquid, gravity and external
    /// forces), "kinematic" (moved along its own velocity, a moving boundary no force
    /// changes), "fixed" (held still) or "external" (moved by the caller's engine). A scene's
    /// ``dynamic = false`` body is kinematic if it has a velocity, fixed if not.
    #[getter]
    fn motions(&self) -> Vec<&'static str> {
        self.inner.bodies().iter().map(|b| motion_name(b.motion)).collect()
    }

    /// Makes body `body` (an index or a name) kinematic: it moves along its own velocity and
    /// angular velocity (kept, and set by :meth:`set_body_state`), a moving boundary the
    /// pressure solve sees and no force changes; in :mod:`diffluid.torch`'s control its
    /// action is that velocity. The way to steer a paddle that a scene file holds at rest
    /// (a ``dynamic = false`` body without a velocity is fixed). A dynamic body made
    /// kinematic keeps its velocity; an external one (moved by the caller's engine) cannot
    /// be made kinematic (ValueError).
    fn set_kinematic(&mut self, body: &Bound<'_, PyAny>) -> PyResult<()> {
        let i = self.body_index(body)?;
        let b = &mut self.inner.bodies_mut()[i];
        if b.motion == Motion::External {
            return Err(value_error(format!(
                "body {:?} is moved by the caller's engine (external): it cannot be made \
                 kinematic",
                b.name
            )));
        }
        b.motion = Motion::Kinematic;
        Ok(())
    }

    /// Marker particle positions, shape (particles, 3), m (a copy).
    #[getter]
    fn particles<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        rows(py, self.inner.particles.iter().map(|p| p.to_array()))
    }

    /// Pressure at cell centres from the last solve, shape (nx, ny, nz), Pa (a copy; zero
    /// outside the liquid and before the first step).
    #[getter]
    fn pressure<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        lattice(py, self.inner.grid().n, self.inner.pressure().to_vec())
    }

    /// The liquid signed distance at cell centres from the last step, shape (nx, ny, nz), m
    /// (negative in the liquid; zero before the first step; a copy).
    #[getter]
    fn liquid_phi<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        lattice(py, self.inner.grid().n, self.inner.liquid_phi().to_vec())
    }

    /// The fluid velocity on the MAC faces: a tuple (u, v, w) of arrays of shapes
    /// (nx+1, ny, nz), (nx, ny+1, nz), (nx, ny, nz+1), m/s (copies).
    #[getter]
    fn velocity<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let shapes = self.face_shapes();
        let parts: Vec<Bound<'py, PyAny>> = (0..3)
            .map(|a| lattice(py, shapes[a], self.inner.u.c[a].clone()))
            .collect::<PyResult<_>>()?;
        PyTuple::new(py, parts)
    }

    /// The fluid velocity as one flat array: u, v then w, each x-fastest (the order
    /// :func:`diffluid.torch.rollout` takes and returns it in).
    fn velocity_flat<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let flat: Vec<f64> = self.inner.u.c.iter().flatten().copied().collect();
        crate::read_only(numpy::PyArray1::from_vec(py, flat))
    }

    /// Sets the fluid velocity from a flat array in :meth:`velocity_flat`'s order.
    fn set_velocity_flat(&mut self, u: PyReadonlyArrayDyn<'_, f64>) -> PyResult<()> {
        let flat = read_flat("u", &u, self.faces_len())?;
        self.inner.u = self.mac_from_flat(&flat);
        Ok(())
    }

    /// The value of the scene's `[loss]` at the current state (None without one).
    fn scene_loss(&self) -> Option<f64> {
        self.loss.as_ref().map(|l| l.value(&self.inner))
    }

    fn __repr__(&self) -> String {
        format!(
            "Simulation(shape={:?}, dx={}, t={:.4}, step={}, bodies={:?})",
            self.inner.grid().n,
            self.inner.grid().dx,
            self.inner.time(),
            self.inner.steps_taken(),
            self.names()
        )
    }
}

/// Panics inside the boundary guard: the test that a Rust panic reaches Python as
/// `InternalError` and never unwinds into the interpreter. Not part of the API.
#[pyfunction]
pub fn _panic_for_tests(py: Python<'_>) -> PyResult<()> {
    run(py, || -> diffluid::Result<()> { panic!("a deliberate panic") })
}
