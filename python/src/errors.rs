//! The Python exceptions and how a Rust error, a panic or a busy object becomes one.
//!
//! Every call that steps a simulation or runs a backward pass goes through [`run`]: the GIL
//! released, a Rust panic caught before it can cross into Python (`InternalError`), and every
//! [`diffluid::Error`] turned into the exception [`to_py`] names, with the message the CLI
//! prints after `error: `.

use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::PyClass;
use std::panic::{catch_unwind, AssertUnwindSafe};

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
     coupling, contact with through_contact=False, bodies added inside the taped steps)."
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
