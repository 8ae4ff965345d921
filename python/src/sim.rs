//! The `Simulation` object's Rust side: the wrapped simulation with the scene's horizon and
//! loss, its construction from a scene, bodies by index or name, the fields' layout, and the
//! masses. Its Python methods are in `simulation.rs`; the loss and the gradients use this
//! side alone.

use crate::convert::read_flat;
use crate::errors::{borrow, borrow_mut, run, to_py, value_error};
use diffluid::geometry::body::Motion;
use diffluid::geometry::grid::Mac;
use diffluid::gradients::BodyTargetLoss;
use diffluid::{Scene as RScene, Simulation as RSim};
use numpy::PyReadonlyArrayDyn;
use pyo3::prelude::*;

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
    /// The scene's simulation in its initial state (the GIL released while it builds; the
    /// scene is a copy, so no borrow of a Python Scene is held meanwhile).
    pub(crate) fn from_scene(py: Python<'_>, s: RScene) -> PyResult<Simulation> {
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

    pub(crate) fn names(&self) -> Vec<String> {
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

/// Simulation `slf` to read (a clear error when another thread is stepping it).
pub(crate) fn sim<'py>(slf: &Bound<'py, Simulation>) -> PyResult<PyRef<'py, Simulation>> {
    borrow(slf, "Simulation")
}

/// Simulation `slf` to change (a clear error when another thread is using it).
pub(crate) fn sim_mut<'py>(slf: &Bound<'py, Simulation>) -> PyResult<PyRefMut<'py, Simulation>> {
    borrow_mut(slf, "Simulation")
}

/// Sets the masses of `sim`'s dynamic bodies from `masses`, one per body (each a finite
/// number > 0: ValueError naming the entry otherwise); the entries of the other bodies are
/// checked but not used.
pub(crate) fn set_masses(sim: &mut RSim, masses: &PyReadonlyArrayDyn<'_, f64>) -> PyResult<()> {
    let n = sim.bodies().len();
    let m = read_flat("masses", masses, n)?;
    for (i, &kg) in m.iter().enumerate() {
        check_mass(&format!("masses[{i}]"), kg)?;
    }
    for (i, kg) in m.into_iter().enumerate() {
        if sim.bodies()[i].motion == Motion::Dynamic {
            sim.set_mass(sim.handles()[i], kg).map_err(to_py)?;
        }
    }
    Ok(())
}

/// ∂L/∂m per body of `sim` from a backward pass's mass adjoint (empty means zero): zero for
/// the bodies that are not dynamic.
pub(crate) fn mass_gradient(sim: &RSim, mass: &[f64]) -> Vec<f64> {
    let at = |i: usize| mass.get(i).copied().unwrap_or(0.0);
    let dynamic = |i: usize| sim.bodies()[i].motion == Motion::Dynamic;
    (0..sim.bodies().len()).map(|i| if dynamic(i) { at(i) } else { 0.0 }).collect()
}

/// Checks that `kg` is a mass: a finite number > 0 (`name` names it in the error).
pub(crate) fn check_mass(name: &str, kg: f64) -> PyResult<()> {
    if !(kg.is_finite() && kg > 0.0) {
        return Err(value_error(format!("{name}: a mass must be a finite number > 0, got {kg}")));
    }
    Ok(())
}
