//! `diffluid.BodyTargetLoss`: a loss on one body's final position, orientation and velocity,
//! its body named by index or by name and resolved against a simulation when it is used.

use crate::convert::{check_finite, quat_norm, wxyz};
use crate::errors::value_error;
use crate::sim::Simulation;
use diffluid::gradients::{BodyTargetLoss as RLoss, Loss};
use diffluid::math::{Rotation, Vec3};
use diffluid::Simulation as RSim;
use pyo3::exceptions::PyTypeError;
use pyo3::prelude::*;
use pyo3::types::PyTuple;

/// A body named by index or by name, resolved against a simulation when the loss is used.
#[derive(Clone, Debug)]
enum BodyRef {
    Index(usize),
    Name(String),
}

/// A weighted target and its weight.
type Target<const N: usize> = Option<([f64; N], f64)>;

/// Weighted squared distances of one body's final position, orientation and velocity to
/// targets: ``wx·|x − x*|² + wq·(1 − (q·q*)²) + wv·|v − v*|²``.
///
/// ``body`` is an index or a name; each target is ``(target, weight)`` or a bare target
/// (weight 1). The orientation target is a quaternion ``[w, x, y, z]`` (normalised).
#[pyclass(module = "diffluid._diffluid", name = "BodyTargetLoss", frozen)]
#[derive(Clone, Debug)]
pub struct BodyTargetLoss {
    body: BodyRef,
    position: Target<3>,
    orientation: Target<4>,
    velocity: Target<3>,
}

/// `(target, weight)` or a bare target from a Python object.
fn target<const N: usize>(name: &str, t: Option<&Bound<'_, PyAny>>) -> PyResult<Target<N>> {
    let Some(t) = t else { return Ok(None) };
    if t.is_none() {
        return Ok(None);
    }
    let (target, weight) = if let Ok(pair) = t.extract::<([f64; N], f64)>() {
        pair
    } else if let Ok(bare) = t.extract::<[f64; N]>() {
        (bare, 1.0)
    } else {
        return Err(PyTypeError::new_err(format!(
            "{name}: a target of {N} numbers, or (target, weight)"
        )));
    };
    check_finite(name, target.iter().chain([weight].iter()))?;
    if weight < 0.0 {
        return Err(value_error(format!("{name}: the weight must be ≥ 0, got {weight}")));
    }
    Ok(Some((target, weight)))
}

impl BodyTargetLoss {
    /// The Python form of a scene's loss (its body by index; the orientation target
    /// `[w, x, y, z]`).
    pub(crate) fn from_rust(l: &RLoss) -> BodyTargetLoss {
        BodyTargetLoss {
            body: BodyRef::Index(l.body),
            position: l.position.map(|(t, w)| (t.to_array(), w)),
            orientation: l.orientation.map(|(q, w)| (wxyz(q), w)),
            velocity: l.velocity.map(|(t, w)| (t.to_array(), w)),
        }
    }

    /// The Rust loss for `sim`'s bodies.
    pub(crate) fn resolve(&self, sim: &RSim) -> PyResult<RLoss> {
        let n = sim.bodies().len();
        let body = match &self.body {
            BodyRef::Index(i) if *i < n => *i,
            BodyRef::Index(i) => {
                return Err(value_error(format!("loss body {i} out of range ({n} bodies)")))
            }
            BodyRef::Name(s) => {
                sim.bodies().iter().position(|b| &b.name == s).ok_or_else(|| {
                    value_error(format!("loss: no body named {s:?} in the simulation"))
                })?
            }
        };
        let v3 = |t: &Target<3>| t.map(|(a, w)| (Vec3::new(a[0], a[1], a[2]), w));
        let orientation = match self.orientation {
            None => None,
            Some((q, w)) => {
                let n = quat_norm(&q);
                if n < 1e-12 {
                    return Err(value_error("orientation: the zero quaternion is no target"));
                }
                Some((Rotation::from_xyzw(q[1] / n, q[2] / n, q[3] / n, q[0] / n), w))
            }
        };
        Ok(RLoss { body, position: v3(&self.position), orientation, velocity: v3(&self.velocity) })
    }
}

#[pymethods]
impl BodyTargetLoss {
    #[new]
    #[pyo3(signature = (body, position = None, orientation = None, velocity = None))]
    fn new(
        body: &Bound<'_, PyAny>,
        position: Option<&Bound<'_, PyAny>>,
        orientation: Option<&Bound<'_, PyAny>>,
        velocity: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<BodyTargetLoss> {
        let body = if let Ok(i) = body.extract::<usize>() {
            BodyRef::Index(i)
        } else if let Ok(s) = body.extract::<String>() {
            BodyRef::Name(s)
        } else {
            return Err(PyTypeError::new_err("body: an index (≥ 0) or a name"));
        };
        let loss = BodyTargetLoss {
            body,
            position: target("position", position)?,
            orientation: target("orientation", orientation)?,
            velocity: target("velocity", velocity)?,
        };
        // As a scene's [loss] section: a loss with no term is a mistake, not a zero.
        if loss.position.is_none() && loss.orientation.is_none() && loss.velocity.is_none() {
            return Err(value_error("loss: give at least one of position, orientation, velocity"));
        }
        Ok(loss)
    }

    /// The body: an index or a name, as given.
    #[getter]
    fn body<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        Ok(match &self.body {
            BodyRef::Index(i) => i.into_pyobject(py)?.into_any(),
            BodyRef::Name(s) => s.into_pyobject(py)?.into_any(),
        })
    }

    /// The body's index in `sim`.
    fn body_index(&self, sim: &Bound<'_, Simulation>) -> PyResult<usize> {
        Ok(self.resolve(&crate::sim::sim(sim)?.inner)?.body)
    }

    /// ``(target, weight)`` of the position term, or None.
    #[getter]
    fn position(&self) -> Target<3> {
        self.position
    }

    /// ``(target [w, x, y, z], weight)`` of the orientation term, or None.
    #[getter]
    fn orientation(&self) -> Target<4> {
        self.orientation
    }

    /// ``(target, weight)`` of the velocity term, or None.
    #[getter]
    fn velocity(&self) -> Target<3> {
        self.velocity
    }

    /// The loss at `sim`'s current state.
    fn value(&self, sim: &Bound<'_, Simulation>) -> PyResult<f64> {
        let s = crate::sim::sim(sim)?;
        Ok(self.resolve(&s.inner)?.value(&s.inner))
    }

    fn __reduce__<'py>(
        slf: &Bound<'py, Self>,
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyTuple>)> {
        let py = slf.py();
        let this = slf.get();
        let args = (
            this.body(py)?,
            this.position.map(|(t, w)| (t.to_vec(), w)),
            this.orientation.map(|(t, w)| (t.to_vec(), w)),
            this.velocity.map(|(t, w)| (t.to_vec(), w)),
        )
            .into_pyobject(py)?;
        Ok((slf.get_type().into_any(), args))
    }

    fn __repr__(&self) -> String {
        let body = match &self.body {
            BodyRef::Index(i) => i.to_string(),
            BodyRef::Name(s) => format!("{s:?}"),
        };
        format!(
            "BodyTargetLoss({body}, position={:?}, orientation={:?}, velocity={:?})",
            self.position, self.orientation, self.velocity
        )
    }
}
