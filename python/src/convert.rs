//! Values across the boundary: NumPy arrays in (checked for shape and finiteness) and out
//! (copies marked read-only), body states and quaternions as rows of numbers, serialisable
//! values as Python objects, and the option strings read through the Rust types' own names.

use crate::errors::{value_error, InternalError};
use diffluid::geometry::body::{BodyState, Motion};
use diffluid::gradients::backward::SurfaceGradient;
use diffluid::gradients::{GradientMode, GradientOptions};
use diffluid::math::{Rotation, Vec3};
use numpy::ndarray::{Array2, Array3, ShapeBuilder};
use numpy::{IntoPyArray, PyArray, PyArray1, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

/// Marks `a` read-only (a copy handed out: writing into it would change nothing).
pub(crate) fn read_only<'py, D>(a: Bound<'py, PyArray<f64, D>>) -> PyResult<Bound<'py, PyAny>> {
    let kw = PyDict::new(a.py());
    kw.set_item("write", false)?;
    a.call_method("setflags", (), Some(&kw))?;
    Ok(a.into_any())
}

/// Rows of `width` numbers as an `(n, width)` read-only array.
pub(crate) fn rows<'py, const W: usize>(
    py: Python<'py>,
    rows: impl ExactSizeIterator<Item = [f64; W]>,
) -> PyResult<Bound<'py, PyAny>> {
    let n = rows.len();
    let flat: Vec<f64> = rows.flat_map(|r| r.into_iter()).collect();
    let a = Array2::from_shape_vec((n, W), flat).expect("n rows of W");
    read_only(a.into_pyarray(py))
}

/// One row of `W` numbers as a `(W,)` read-only array.
pub(crate) fn row<'py, const W: usize>(
    py: Python<'py>,
    r: [f64; W],
) -> PyResult<Bound<'py, PyAny>> {
    read_only(PyArray1::from_vec(py, r.to_vec()))
}

/// A field stored x-fastest on a lattice of `n` samples, as an `(nx, ny, nz)` array indexed
/// `[i, j, k]` (Fortran order, the copy's memory in the solver's own order).
pub(crate) fn lattice<'py>(
    py: Python<'py>,
    n: [usize; 3],
    data: Vec<f64>,
) -> PyResult<Bound<'py, PyAny>> {
    let a = Array3::from_shape_vec((n[0], n[1], n[2]).f(), data).expect("a lattice's samples");
    read_only(a.into_pyarray(py))
}

/// The numbers of `a`, checked to have shape `(n, width)` (or `(width,)` when `n` is 1) and
/// to be finite. `name` names the argument in errors.
pub(crate) fn read_rows(
    name: &str,
    a: &PyReadonlyArrayDyn<'_, f64>,
    n: usize,
    width: usize,
) -> PyResult<Vec<Vec<f64>>> {
    let shape = a.shape().to_vec();
    let ok = shape == [n, width] || (n == 1 && shape == [width]);
    if !ok {
        return Err(value_error(format!(
            "{name}: expected shape ({n}, {width}){}, got {shape:?}",
            if n == 1 { format!(" or ({width},)") } else { String::new() }
        )));
    }
    let view = a.as_array();
    let view = view.to_shape((n, width)).map_err(|e| value_error(format!("{name}: {e}")))?;
    let out: Vec<Vec<f64>> = view.rows().into_iter().map(|r| r.to_vec()).collect();
    check_finite(name, out.iter().flatten())?;
    Ok(out)
}

/// A flat float64 vector of `len` finite numbers.
pub(crate) fn read_flat(
    name: &str,
    a: &PyReadonlyArrayDyn<'_, f64>,
    len: usize,
) -> PyResult<Vec<f64>> {
    if a.ndim() != 1 || a.len() != len {
        return Err(value_error(format!(
            "{name}: expected a flat array of {len} numbers, got shape {:?}",
            a.shape()
        )));
    }
    let out: Vec<f64> = a.as_array().iter().copied().collect();
    check_finite(name, out.iter())?;
    Ok(out)
}

/// Raises a `ValueError` naming `name` if any value is NaN or infinite.
pub(crate) fn check_finite<'a>(name: &str, xs: impl Iterator<Item = &'a f64>) -> PyResult<()> {
    for (i, x) in xs.enumerate() {
        if !x.is_finite() {
            return Err(value_error(format!("{name}: element {i} is {x}, not a finite number")));
        }
    }
    Ok(())
}

/// A JSON value (a serialised step report, optimisation record) as Python objects.
pub(crate) fn json_to_py<'py>(
    py: Python<'py>,
    v: &serde_json::Value,
) -> PyResult<Bound<'py, PyAny>> {
    use serde_json::Value;
    Ok(match v {
        // serde_json writes a non-finite float as null; floats are the only numbers that can be.
        Value::Null => f64::NAN.into_pyobject(py)?.into_any(),
        Value::Bool(b) => b.into_pyobject(py)?.to_owned().into_any(),
        Value::Number(n) => match (n.as_u64(), n.as_i64()) {
            (Some(u), _) => u.into_pyobject(py)?.into_any(),
            (None, Some(i)) => i.into_pyobject(py)?.into_any(),
            _ => n.as_f64().unwrap_or(f64::NAN).into_pyobject(py)?.into_any(),
        },
        Value::String(s) => s.into_pyobject(py)?.into_any(),
        Value::Array(a) => {
            let l = PyList::empty(py);
            for x in a {
                l.append(json_to_py(py, x)?)?;
            }
            l.into_any()
        }
        Value::Object(m) => {
            let d = PyDict::new(py);
            for (k, x) in m {
                d.set_item(k, json_to_py(py, x)?)?;
            }
            d.into_any()
        }
    })
}

/// A serialisable value as Python objects (through JSON).
pub(crate) fn to_py_object<'py>(
    py: Python<'py>,
    v: &impl serde::Serialize,
) -> PyResult<Bound<'py, PyAny>> {
    let j = serde_json::to_value(v)
        .map_err(|e| InternalError::new_err(format!("cannot serialise: {e}")))?;
    json_to_py(py, &j)
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

/// The backward pass's options from their Python names (`surface`: "live" or "frozen";
/// `mode`: "full" or "paper"), read through the Rust types.
pub(crate) fn options(
    surface: &str,
    mode: &str,
    through_contact: bool,
) -> PyResult<GradientOptions> {
    let surface: SurfaceGradient = surface.parse().map_err(value_error)?;
    let mode: GradientMode = mode.parse().map_err(value_error)?;
    Ok(GradientOptions { mode, surface, through_contact })
}
