//! `diffluid.Simulation`: a running simulation, its bodies and fields as NumPy arrays.

use crate::convert::{
    lattice, motion_name, read_flat, read_only, read_rows, row, rows, state_from, to_py_object,
    wxyz,
};
use crate::errors::{run, to_py, value_error};
use crate::scene::Scene;
use crate::sim::{check_mass, sim, sim_mut, Simulation};
use diffluid::geometry::body::Motion;
use diffluid::gradients::Loss;
use diffluid::math::Vec3;
use numpy::PyReadonlyArrayDyn;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};
use std::ops::ControlFlow;

#[pymethods]
impl Simulation {
    /// The scene's simulation in its initial state.
    #[new]
    fn new(py: Python<'_>, scene: &Bound<'_, Scene>) -> PyResult<Simulation> {
        let scene = scene.borrow().inner.clone();
        Simulation::from_scene(py, scene)
    }

    /// Advances one step of the fixed Δt and returns its report as a dict (step, time,
    /// liquid_cells, cg_iterations, cg_relative_residual, density_cg_iterations,
    /// max_divergence, liquid_volume,
    /// max_speed, kinetic_energy, bodies: [{name, force, torque, volume_error}],
    /// contact_iterations, contact_residual, stage_seconds, and warnings when there are any).
    ///
    /// Raises SolverError when the pressure solve does not converge and SimulationError when
    /// the state blows up or a body leaves the tank; the step is then rolled back (the
    /// simulation is as it was before it, every field, particle and body, its time and step
    /// count), unless :attr:`rollback` is off.
    fn step<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let mut this = sim_mut(slf)?;
        let sim = &mut this.inner;
        let report = run(py, || sim.step())?;
        to_py_object(py, &report)
    }

    /// Advances `steps` steps (default: the scene's `time.steps`) in one call, the GIL
    /// released while each step runs, and returns the last step's report.
    ///
    /// Ctrl-C (any signal whose handler raises) is noticed between steps: it raises
    /// KeyboardInterrupt with every step finished so far kept (``steps_taken`` and ``time``
    /// say how far it got). A step that fails raises as :meth:`step` does, rolled back, the
    /// steps before it kept.
    #[pyo3(signature = (steps = None))]
    fn run<'py>(
        slf: &Bound<'py, Self>,
        py: Python<'py>,
        steps: Option<usize>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let mut this = sim_mut(slf)?;
        let n = steps.unwrap_or(this.scene_steps);
        if n == 0 {
            return Err(value_error("steps: must be at least 1"));
        }
        let sim = &mut this.inner;
        let mut last = None;
        for _ in 0..n {
            last = Some(run(py, || sim.step())?);
            py.check_signals()?;
        }
        to_py_object(py, &last.expect("at least one step"))
    }

    /// Advances by `frame_dt` seconds in as many CFL-limited steps as needed (a game or
    /// robot loop's frame) and returns their reports. Ctrl-C is noticed between steps, as in
    /// :meth:`run` (the frame's finished steps kept, ``time`` short of the frame's end).
    fn advance<'py>(
        slf: &Bound<'py, Self>,
        py: Python<'py>,
        frame_dt: f64,
    ) -> PyResult<Bound<'py, PyList>> {
        let mut this = sim_mut(slf)?;
        let sim = &mut this.inner;
        let mut interrupt = None;
        let reports = run(py, || {
            sim.advance_while(frame_dt, |_| match Python::attach(|py| py.check_signals()) {
                Ok(()) => ControlFlow::Continue(()),
                Err(e) => {
                    interrupt = Some(e);
                    ControlFlow::Break(())
                }
            })
        })?;
        if let Some(e) = interrupt {
            return Err(e);
        }
        let out = PyList::empty(py);
        for r in &reports {
            out.append(to_py_object(py, r)?)?;
        }
        Ok(out)
    }

    /// An independent copy (the same state; stepping one does not move the other).
    fn copy(slf: &Bound<'_, Self>) -> PyResult<Simulation> {
        Ok(sim(slf)?.clone())
    }

    fn __copy__(slf: &Bound<'_, Self>) -> PyResult<Simulation> {
        Ok(sim(slf)?.clone())
    }

    fn __deepcopy__(slf: &Bound<'_, Self>, _memo: &Bound<'_, PyAny>) -> PyResult<Simulation> {
        Ok(sim(slf)?.clone())
    }

    /// Whether a step that fails is rolled back (True by default; see :meth:`step`). Rolling
    /// back keeps a copy of the particles, the narrow band and φ_L through every step (on a
    /// grid of a million cells, about 55 MB); set it to False to save that memory when a
    /// failed step ends the run anyway: a step that fails then leaves the particles and the
    /// bodies where it had moved them, ``time`` and ``steps_taken`` as before.
    #[getter]
    fn rollback(slf: &Bound<'_, Self>) -> PyResult<bool> {
        Ok(sim(slf)?.inner.rollback())
    }

    #[setter]
    fn set_rollback(slf: &Bound<'_, Self>, on: bool) -> PyResult<()> {
        sim_mut(slf)?.inner.set_rollback(on);
        Ok(())
    }

    /// Simulated time, s.
    #[getter]
    fn time(slf: &Bound<'_, Self>) -> PyResult<f64> {
        Ok(sim(slf)?.inner.time())
    }

    /// Steps taken so far.
    #[getter]
    fn steps_taken(slf: &Bound<'_, Self>) -> PyResult<usize> {
        Ok(sim(slf)?.inner.steps_taken())
    }

    /// The scene's `time.steps` (the default horizon of `run` and the gradients).
    #[getter]
    fn scene_steps(slf: &Bound<'_, Self>) -> PyResult<usize> {
        Ok(sim(slf)?.scene_steps)
    }

    /// The fixed step Δt, s.
    #[getter]
    fn dt(slf: &Bound<'_, Self>) -> PyResult<f64> {
        Ok(sim(slf)?.inner.dt())
    }

    /// Cell side, m.
    #[getter]
    fn dx(slf: &Bound<'_, Self>) -> PyResult<f64> {
        Ok(sim(slf)?.inner.grid().dx)
    }

    /// Cells along x, y, z.
    #[getter]
    fn shape(slf: &Bound<'_, Self>) -> PyResult<[usize; 3]> {
        Ok(sim(slf)?.inner.grid().n)
    }

    /// Every warning so far, each once.
    #[getter]
    fn warnings(slf: &Bound<'_, Self>) -> PyResult<Vec<String>> {
        Ok(sim(slf)?.inner.warnings().to_vec())
    }

    /// The bodies' names, in order.
    #[getter]
    fn body_names(slf: &Bound<'_, Self>) -> PyResult<Vec<String>> {
        Ok(sim(slf)?.names())
    }

    /// Number of bodies.
    #[getter]
    fn num_bodies(slf: &Bound<'_, Self>) -> PyResult<usize> {
        Ok(sim(slf)?.inner.bodies().len())
    }

    /// Centres of mass, shape (bodies, 3), m.
    #[getter]
    fn positions<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        rows(py, sim(slf)?.inner.bodies().iter().map(|b| b.x.to_array()))
    }

    /// Orientations as quaternions ``[w, x, y, z]``, shape (bodies, 4).
    #[getter]
    fn orientations<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        rows(py, sim(slf)?.inner.bodies().iter().map(|b| wxyz(b.q)))
    }

    /// Linear velocities of the centres of mass, shape (bodies, 3), m/s.
    #[getter]
    fn velocities<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        rows(py, sim(slf)?.inner.bodies().iter().map(|b| b.v.to_array()))
    }

    /// Angular velocities (world frame), shape (bodies, 3), rad/s.
    #[getter]
    fn angular_velocities<'py>(
        slf: &Bound<'py, Self>,
        py: Python<'py>,
    ) -> PyResult<Bound<'py, PyAny>> {
        rows(py, sim(slf)?.inner.bodies().iter().map(|b| b.w.to_array()))
    }

    /// Each body's mass, shape (bodies,), kg (:meth:`set_mass` changes one).
    #[getter]
    fn masses<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let m: Vec<f64> = sim(slf)?.inner.bodies().iter().map(|b| b.mass).collect();
        read_only(numpy::PyArray1::from_vec(py, m))
    }

    /// Sets body `body`'s (an index or a name) mass to `kg`, its inertia scaling with it (its
    /// density changes, not its shape): what the gradients' ``mass`` entries differentiate.
    /// It must be a finite number > 0 (ValueError otherwise). Only a dynamic body's mass
    /// moves anything in the liquid; a kinematic, fixed or external body's is kept but read
    /// only by contact.
    fn set_mass(slf: &Bound<'_, Self>, body: &Bound<'_, PyAny>, kg: f64) -> PyResult<()> {
        let mut this = sim_mut(slf)?;
        let i = this.body_index(body)?;
        check_mass("kg", kg)?;
        let h = this.inner.handles()[i];
        this.inner.set_mass(h, kg).map_err(crate::errors::to_py)?;
        Ok(())
    }

    /// The pressure force (N) and torque (N·m, about the centre of mass) of the last step's
    /// solve on each body: a pair of arrays of shape (bodies, 3), zero before the first step.
    fn fluid_forces<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let this = sim(slf)?;
        let ft: Vec<(Vec3, Vec3)> = this
            .inner
            .handles()
            .iter()
            .map(|&h| this.inner.fluid_force(h).expect("a handle of this simulation"))
            .collect();
        let f = rows(py, ft.iter().map(|(f, _)| f.to_array()))?;
        let t = rows(py, ft.iter().map(|(_, t)| t.to_array()))?;
        PyTuple::new(py, [f, t])
    }

    /// Body `body`'s (an index or a name) state as a dict of arrays: v (3,), w (3,), x (3,)
    /// and q (4,) ``[w, x, y, z]``.
    fn body_state<'py>(
        slf: &Bound<'py, Self>,
        py: Python<'py>,
        body: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let this = sim(slf)?;
        let b = &this.inner.bodies()[this.body_index(body)?];
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
        slf: &Bound<'_, Self>,
        body: &Bound<'_, PyAny>,
        v: Option<PyReadonlyArrayDyn<'_, f64>>,
        w: Option<PyReadonlyArrayDyn<'_, f64>>,
        x: Option<PyReadonlyArrayDyn<'_, f64>>,
        q: Option<PyReadonlyArrayDyn<'_, f64>>,
    ) -> PyResult<()> {
        let mut this = sim_mut(slf)?;
        let i = this.body_index(body)?;
        let s = this.inner.bodies()[i].state();
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
        let h = this.inner.handles()[i];
        this.inner.set_body_state(h, &state).map_err(to_py)
    }

    /// Sets the external force (N, on the centre of mass) and torque (N·m) on body `body`,
    /// world frame, float64 arrays of 3; they act every step, with gravity, until changed.
    #[pyo3(signature = (body, force, torque = None))]
    fn set_external_force(
        slf: &Bound<'_, Self>,
        body: &Bound<'_, PyAny>,
        force: PyReadonlyArrayDyn<'_, f64>,
        torque: Option<PyReadonlyArrayDyn<'_, f64>>,
    ) -> PyResult<()> {
        let mut this = sim_mut(slf)?;
        let i = this.body_index(body)?;
        let f = read_rows("force", &force, 1, 3)?.remove(0);
        let t = match torque {
            Some(t) => read_rows("torque", &t, 1, 3)?.remove(0),
            None => vec![0.0; 3],
        };
        let h = this.inner.handles()[i];
        this.inner
            .set_external_force(h, Vec3::new(f[0], f[1], f[2]), Vec3::new(t[0], t[1], t[2]))
            .map_err(to_py)
    }

    /// How each body moves, in order: "dynamic" (moved by the liquid, gravity and external
    /// forces), "kinematic" (moved along its own velocity, a moving boundary no force
    /// changes), "fixed" (held still) or "external" (moved by the caller's engine). A scene's
    /// ``dynamic = false`` body is kinematic if it has a velocity, fixed if not.
    #[getter]
    fn motions(slf: &Bound<'_, Self>) -> PyResult<Vec<&'static str>> {
        Ok(sim(slf)?.inner.bodies().iter().map(|b| motion_name(b.motion)).collect())
    }

    /// Makes body `body` (an index or a name) kinematic: it moves along its own velocity and
    /// angular velocity (kept, and set by :meth:`set_body_state`), a moving boundary the
    /// pressure solve sees and no force changes; in :mod:`diffluid.torch`'s control its
    /// action is that velocity. The way to steer a paddle that a scene file holds at rest
    /// (a ``dynamic = false`` body without a velocity is fixed). A dynamic body made
    /// kinematic keeps its velocity; an external one (moved by the caller's engine) cannot
    /// be made kinematic (ValueError).
    fn set_kinematic(slf: &Bound<'_, Self>, body: &Bound<'_, PyAny>) -> PyResult<()> {
        let mut this = sim_mut(slf)?;
        let i = this.body_index(body)?;
        let b = &this.inner.bodies()[i];
        if b.motion == Motion::External {
            return Err(value_error(format!(
                "body {:?} is moved by the caller's engine (external): it cannot be made \
                 kinematic",
                b.name
            )));
        }
        let h = this.inner.handles()[i];
        this.inner.set_motion(h, Motion::Kinematic).map_err(crate::errors::to_py)
    }

    /// Marker particle positions, shape (particles, 3), m (a copy).
    #[getter]
    fn particles<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        rows(py, sim(slf)?.inner.particles().iter().map(|p| p.to_array()))
    }

    /// Pressure at cell centres from the last solve, shape (nx, ny, nz), Pa (a copy; zero
    /// outside the liquid and before the first step).
    #[getter]
    fn pressure<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let this = sim(slf)?;
        lattice(py, this.inner.grid().n, this.inner.pressure().to_vec())
    }

    /// The liquid signed distance at cell centres from the last step, shape (nx, ny, nz), m
    /// (negative in the liquid; zero before the first step; a copy).
    #[getter]
    fn liquid_phi<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let this = sim(slf)?;
        lattice(py, this.inner.grid().n, this.inner.liquid_phi().to_vec())
    }

    /// The fluid velocity on the MAC faces: a tuple (u, v, w) of arrays of shapes
    /// (nx+1, ny, nz), (nx, ny+1, nz), (nx, ny, nz+1), m/s (copies).
    #[getter]
    fn velocity<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let this = sim(slf)?;
        let shapes = this.face_shapes();
        let parts: Vec<Bound<'py, PyAny>> = (0..3)
            .map(|a| lattice(py, shapes[a], this.inner.velocity_field().c[a].clone()))
            .collect::<PyResult<_>>()?;
        PyTuple::new(py, parts)
    }

    /// The fluid velocity as one flat array: u, v then w, each x-fastest (the order
    /// :func:`diffluid.torch.rollout` takes and returns it in).
    fn velocity_flat<'py>(slf: &Bound<'py, Self>, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let flat: Vec<f64> = sim(slf)?.inner.velocity_field().c.iter().flatten().copied().collect();
        read_only(numpy::PyArray1::from_vec(py, flat))
    }

    /// Sets the fluid velocity from a flat array in :meth:`velocity_flat`'s order.
    fn set_velocity_flat(slf: &Bound<'_, Self>, u: PyReadonlyArrayDyn<'_, f64>) -> PyResult<()> {
        let mut this = sim_mut(slf)?;
        let flat = read_flat("u", &u, this.faces_len())?;
        let u = this.mac_from_flat(&flat);
        this.inner.set_velocity_field(u).map_err(crate::errors::to_py)?;
        Ok(())
    }

    /// The value of the scene's `[loss]` at the current state (None without one).
    fn scene_loss(slf: &Bound<'_, Self>) -> PyResult<Option<f64>> {
        let this = sim(slf)?;
        Ok(this.loss.as_ref().map(|l| l.value(&this.inner)))
    }

    fn __repr__(slf: &Bound<'_, Self>) -> String {
        // A repr that raises would break debuggers and tracebacks: say it is busy instead.
        let Ok(this) = slf.try_borrow() else {
            return "Simulation(<in use by another thread>)".into();
        };
        format!(
            "Simulation(shape={:?}, dx={}, t={:.4}, step={}, bodies={:?})",
            this.inner.grid().n,
            this.inner.grid().dx,
            this.inner.time(),
            this.inner.steps_taken(),
            this.names()
        )
    }
}

/// Panics inside the boundary guard: the test that a Rust panic reaches Python as
/// `InternalError` and never unwinds into the interpreter. Not part of the API.
#[pyfunction]
pub fn _panic_for_tests(py: Python<'_>) -> PyResult<()> {
    run(py, || -> diffluid::Result<()> { panic!("a deliberate panic") })
}
