//! Errors a caller can act on: each names the problem in one line.

use std::path::PathBuf;

/// Everything that can go wrong in diffluid, with a message that names the problem.
/// Non-exhaustive: a match needs a catch-all arm, so a new kind of error is not a breaking
/// change.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// A scene file that cannot be read.
    #[error("cannot read scene file {path}: {source}")]
    ReadScene {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A scene file that is not valid TOML or does not match the scene format
    /// (a missing or unknown key, a wrong type). The message carries the line.
    #[error("scene {origin}: {message}")]
    ParseScene {
        /// The file or `<embedded>`.
        origin: String,
        /// toml's message, with line and column.
        message: String,
    },
    /// A scene that parses but describes something impossible (non-positive dx, liquid
    /// outside the domain, a NaN...).
    #[error("scene {origin}: {message}")]
    InvalidScene {
        /// The file or `<embedded>`.
        origin: String,
        /// What is wrong, naming the key.
        message: String,
    },
    /// A setting of a world built in code that fails its check (a scene file's settings
    /// come back as [`Error::InvalidScene`] with the line). `key` names it as a scene file
    /// would: `domain.dx`, `liquid[0]`, `body[1]`, `solver.theta_min`.
    #[error("{key}: {message}")]
    InvalidSettings {
        /// The setting.
        key: String,
        /// What is wrong.
        message: String,
    },
    /// A body handle that names no body of the simulation (removed, or from another one).
    #[error("no body with handle {handle} in this simulation")]
    UnknownBody {
        /// The handle's number.
        handle: u32,
    },
    /// A gradient asked of a forward map the backward pass cannot differentiate.
    #[error("gradient not available: {0}")]
    Gradient(#[from] GradientError),
    /// A linear solve did not reach its tolerance.
    #[error(
        "{solve} did not converge at step {step}: relative residual {residual:.3e} after \
         {iterations} iterations (tolerance {tolerance:.1e}); raise solver.max_iterations or \
         loosen {key}",
        key = solve.key()
    )]
    NotConverged {
        /// Which solve.
        solve: Solve,
        /// The step that failed.
        step: usize,
        /// Iterations done.
        iterations: usize,
        /// Relative residual reached.
        residual: f64,
        /// The tolerance asked for.
        tolerance: f64,
    },
    /// A non-finite value appeared in the state.
    #[error("the simulation blew up at step {step}: {what}")]
    NonFinite {
        /// The step.
        step: usize,
        /// Which quantity, and how: "the fluid velocity is not finite".
        what: String,
    },
    /// A body left the tank (contact is off). The message names both ways to turn contact
    /// on: `SimulationBuilder::contact` for a world built in Rust, `[contact]` in a scene.
    #[error(
        "body {body} left the tank at step {step} (bounds {bounds:?}); turn contact on \
         (SimulationBuilder::contact(ContactSettings {{ enabled: true, .. }}) in Rust, \
         [contact] enabled = true in a scene file) or change its initial state"
    )]
    BodyLeftTank {
        /// The step.
        step: usize,
        /// The body.
        body: String,
        /// Its bounds then.
        bounds: ([f64; 3], [f64; 3]),
    },
    /// An input other than a scene (a run's frames, a mesh) that cannot be read.
    #[error("cannot read {path}: {message}")]
    Read {
        /// The file or folder.
        path: PathBuf,
        /// Why.
        message: String,
    },
    /// A checkpoint to resume from that cannot be read, is not one, or does not fit the
    /// scene being resumed (another scene, changed settings, a state of another optimiser or
    /// of the wrong size, a history that does not add up).
    #[error("checkpoint {path}: {message}")]
    Checkpoint {
        /// The file.
        path: PathBuf,
        /// What is wrong, naming the checkpoint's key.
        message: String,
    },
    /// A mesh file that cannot be loaded as a body ([`crate::geometry::mesh::load_obj`]): it
    /// cannot be read, is not valid OBJ, is not a closed oriented surface, or is too large
    /// once scaled. The message names the file and, for an open surface, the alternatives.
    #[error("{message}")]
    Mesh {
        /// The file.
        path: PathBuf,
        /// What is wrong, starting with the file's name.
        message: String,
    },
    /// Writing an output failed.
    #[error("cannot write {path}: {source}")]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
}

/// A linear solve of a step or of its adjoint.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum Solve {
    /// The coupled pressure solve (stage `pressure`).
    Pressure,
    /// The particle density projection (stage `density`).
    Density,
    /// The pressure solve's adjoint (the backward pass).
    PressureAdjoint,
    /// The density projection's adjoint (the backward pass, live surface).
    DensityAdjoint,
}

impl Solve {
    /// The scene key whose tolerance the solve works to.
    pub fn key(self) -> &'static str {
        match self {
            Solve::Pressure | Solve::PressureAdjoint => "solver.tolerance",
            Solve::Density | Solve::DensityAdjoint => "solver.density_tolerance",
        }
    }
}

impl std::fmt::Display for Solve {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Solve::Pressure => "the pressure solve",
            Solve::Density => "the density projection",
            Solve::PressureAdjoint => "the adjoint pressure solve",
            Solve::DensityAdjoint => "the adjoint density projection",
        })
    }
}

/// Why a gradient is not available.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GradientError {
    /// Bodies were added or removed inside the taped steps.
    #[error(
        "taped step {step} has {taped} bodies, the initial state {initial}: bodies were added \
         or removed inside the taped steps"
    )]
    BodiesChanged {
        /// The taped step (from 1).
        step: usize,
        /// Its bodies.
        taped: usize,
        /// The initial state's bodies.
        initial: usize,
    },
    /// The partitioned coupling has no adjoint.
    #[error("gradients are only available for solver.coupling = \"monolithic\"")]
    WeakCoupling,
    /// rapier contact acted and the options do not accept it.
    #[error(
        "rapier contact acted in the taped steps and gradients do not pass through it: set \
         [contact] enabled = false, or differentiate through rapier's contact step \
         (optimize.through_contact = true)"
    )]
    ThroughContact,
    /// A checkpointed segment's re-run did not repeat its forward pass.
    #[error(
        "re-running step {step} from its checkpoint {what}: the forward map is not \
         deterministic"
    )]
    NotDeterministic {
        /// The step re-run.
        step: usize,
        /// What differed.
        what: String,
    },
}

/// Result with diffluid's error (another error type can be named, so that the prelude's
/// `Result` does not hide the standard one).
pub type Result<T, E = Error> = std::result::Result<T, E>;
