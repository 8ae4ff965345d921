//! `diffluid._diffluid`: the native half of the `diffluid` Python package.
//!
//! Thin over the Rust crate: every call that steps a simulation or runs a backward pass
//! releases the GIL ([`run`]), catches a Rust panic before it can cross into Python and turns
//! it into `diffluid.InternalError`, and turns every [`diffluid::Error`] into the Python
//! exception [`to_py`] names, with the message the CLI prints after `error: `.
//!
//! Arrays cross the boundary as float64 NumPy arrays, always copied (a simulation's state
//! lives in Rust and changes every step, so a borrowed view could not stay valid); arrays
//! handed out are marked read-only so that writing into one is an error rather than a
//! silent no-op.

use diffluid::math::memory::GridAllocator;
use numpy::ndarray::{Array2, Array3, ShapeBuilder};
use numpy::{IntoPyArray, PyArray, PyArray1, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use pyo3::PyClass;
use std::panic::{catch_unwind, AssertUnwindSafe};

mod control;
mod gradients;
mod scene;
mod simulation;

pyo3::create_exception!(
    _diffluid,
    SimulationError,
    PyRuntimeError,
    "A simulation that could not go on: the state blew up (a NaN or an infinity) or a body \
     left the tank with contact off."
);
pyo3::create_exception!(
    _diffluid,
    SolverError,
    SimulationError,
    "A pressure solve (forward or adjoint) that did not reach its tolerance."
);
pyo3::create_exception!(
    _diffluid,
    GradientError,
    PyValueError,
    "A gradient asked of a forward map the backward pass cannot differentiate (weak \
     coupling, contact without through_contact, bodies added inside the taped steps)."
);
pyo3::create_exception!(
    _diffluid,
    InternalError,
    PyRuntimeError,
    "A bug in diffluid: a Rust panic, caught at the boundary. The simulation it came from may \
     be left part-way through a step."
);

/// The Python exception for a diffluid error, with the CLI's message.
///
/// Scenes and settings that are wrong (cannot parse, fail validation, a bad handle) are
/// `ValueError`; a scene file that cannot be read is `FileNotFoundError`/`OSError`; a solve
/// that does not converge is `SolverError`; a blown-up state or a body out of the tank is
/// `SimulationError` (`SolverError`'s base); an undifferentiable map is `GradientError` (a
/// `ValueError`); another file that cannot be read or written is `OSError`.
pub(crate) fn to_py(e: diffluid::Error) -> PyErr {
    use diffluid::Error as E;
    let message = e.to_string();
    match e {
        E::ReadScene { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err(message)
        }
        E::ReadScene { .. } | E::Read { .. } | E::Write { .. } => PyOSError::new_err(message),
        E::ParseScene { .. }
        | E::InvalidScene { .. }
        | E::InvalidSettings { .. }
        | E::UnknownBody { .. } => PyValueError::new_err(message),
        E::Gradient(_) => GradientError::new_err(message),
        E::NotConverged { .. } => SolverError::new_err(message),
        E::NonFinite { .. } | E::BodyLeftTank { .. } => SimulationError::new_err(message),
        // A variant added to the library after this mapping was written: still an exception
        // with the CLI's message, never a failed build of the package.
        #[allow(unreachable_patterns)]
        _ => PyRuntimeError::new_err(message),
    }
}

/// The text of a caught panic.
fn panic_message(p: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = p.downcast_ref::<&str>() {
        s.to_string()
    } else if let Some(s) = p.downcast_ref::<String>() {
        s.clone()
    } else {
        "a panic with no message".into()
    }
}

/// Runs `f` with the GIL released, so that other Python threads (and the Ray worker's own
/// threads) run meanwhile; a diffluid error becomes its Python exception and a panic an
/// `InternalError`, so no panic ever unwinds into the interpreter.
pub(crate) fn run<T: Send>(
    py: Python<'_>,
    f: impl FnOnce() -> diffluid::Result<T> + Send,
) -> PyResult<T> {
    match py.detach(|| catch_unwind(AssertUnwindSafe(f))) {
        Ok(Ok(t)) => Ok(t),
        Ok(Err(e)) => Err(to_py(e)),
        Err(p) => Err(InternalError::new_err(format!(
            "internal error in diffluid (please report it): {}",
            panic_message(p.as_ref())
        ))),
    }
}

/// `obj` (a `what`: "Simulation", "Stepper") to read, or a RuntimeError that says why not:
/// another thread is inside a call on it that released the GIL (a step, say). pyo3's own
/// message for it is a bare "Already mutably borrowed".
pub(crate) fn borrow<'py, T: PyClass>(obj: &Bound<'py, T>, what: &str) -> PyResult<PyRef<'py, T>> {
    obj.try_borrow().map_err(|_| busy(what))
}

/// `obj` to change, or the RuntimeError of [`borrow`].
pub(crate) fn borrow_mut<'py, T: PyClass<Frozen = pyo3::pyclass::boolean_struct::False>>(
    obj: &Bound<'py, T>,
    what: &str,
) -> PyResult<PyRefMut<'py, T>> {
    obj.try_borrow_mut().map_err(|_| busy(what))
}

/// The error of a call on an object another thread is using.
fn busy(what: &str) -> PyErr {
    let own = if what == "Simulation" { "its own (sim.copy())" } else { "its own" };
    PyRuntimeError::new_err(format!(
        "this {what} is in use by another thread (a call that releases the GIL, such as a \
         step, is running on it there): it takes one call at a time; give each thread {own} \
         or wait for that call to return"
    ))
}

/// A value error with `message`.
pub(crate) fn value_error(message: impl Into<String>) -> PyErr {
    PyValueError::new_err(message.into())
}

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

/// The system allocator with the largest arrays (16 MiB and more: a grid of a few million
/// cells) advised onto huge pages, as the CLI's; glibc itself is left as the interpreter set
/// it unless [`tune_memory`] is called.
#[global_allocator]
static ALLOCATOR: GridAllocator = GridAllocator;

/// Sets glibc's malloc for the whole process as the `diffluid` binary sets it (one arena,
/// no allocation mapped apart, no trimming: what a step frees, the next takes again without
/// a page fault). Returns True where it applies (Linux with glibc), False elsewhere.
///
/// Measured on `large_tank` (1M cells, 8 steps): peak RSS 384 → 302 MB (the CLI: 295 MB),
/// 200k → 79k page faults, 0.81 → 0.48 s of kernel time. It changes malloc for everything
/// in the process, NumPy and torch included, whose freed memory then also stays with the
/// process; so it is asked for, not done on import. Call it before the first step (before
/// diffluid's threads start).
#[pyfunction]
fn tune_memory() -> bool {
    GridAllocator::tune();
    cfg!(all(target_os = "linux", target_env = "gnu"))
}

/// The native module.
#[pymodule]
fn _diffluid(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("SimulationError", py.get_type::<SimulationError>())?;
    m.add("SolverError", py.get_type::<SolverError>())?;
    m.add("GradientError", py.get_type::<GradientError>())?;
    m.add("InternalError", py.get_type::<InternalError>())?;
    m.add_class::<scene::Scene>()?;
    m.add_class::<simulation::Simulation>()?;
    m.add_class::<gradients::BodyTargetLoss>()?;
    m.add_class::<gradients::Rollout>()?;
    m.add_function(wrap_pyfunction!(gradients::value_and_grad, m)?)?;
    m.add_function(wrap_pyfunction!(gradients::optimize, m)?)?;
    m.add_function(wrap_pyfunction!(gradients::rollout, m)?)?;
    m.add_class::<control::ControlledRun>()?;
    m.add_class::<control::Stepper>()?;
    m.add_function(wrap_pyfunction!(control::controlled_run, m)?)?;
    m.add_function(wrap_pyfunction!(simulation::_panic_for_tests, m)?)?;
    m.add_function(wrap_pyfunction!(tune_memory, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
