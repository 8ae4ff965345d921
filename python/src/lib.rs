//! `diffluid._diffluid`: the native half of the `diffluid` Python package.
//!
//! Thin over the Rust crate: every call that steps a simulation or runs a backward pass
//! releases the GIL ([`errors::run`]), catches a Rust panic before it can cross into Python and turns
//! it into `diffluid.InternalError`, and turns every [`diffluid::Error`] into the Python
//! exception [`errors::to_py`] names, with the message the CLI prints after `error: `.
//!
//! Arrays cross the boundary as float64 NumPy arrays, always copied (a simulation's state
//! lives in Rust and changes every step, so a borrowed view could not stay valid); arrays
//! handed out are marked read-only so that writing into one is an error rather than a
//! silent no-op ([`convert`]).
//!
//! The modules, lowest first: `errors` and `convert`; `sim` (the `Simulation` object's Rust
//! side); `loss` (`BodyTargetLoss`); `scene`; `simulation` (the `Simulation` object's Python
//! methods), `gradients` and `control`. Each uses only those below it.

use diffluid::math::memory::GridAllocator;
use errors::{GradientError, InternalError, SimulationError, SolverError};
use pyo3::prelude::*;

mod control;
mod convert;
mod errors;
mod gradients;
mod loss;
mod scene;
mod sim;
mod simulation;

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
    m.add_class::<sim::Simulation>()?;
    m.add_class::<loss::BodyTargetLoss>()?;
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
