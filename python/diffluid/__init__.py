"""diffluid: differentiable Eulerian liquid simulation with strong two-way rigid coupling.

A liquid on a MAC grid with marker particles for its free surface, rigid bodies coupled to
it through one monolithic pressure solve, and an adjoint backward pass that gives the exact
gradient of a loss on the final state with respect to the initial state. This package is the
Rust library seen from Python:

- :class:`Scene` (a scene file, TOML text or a built-in name), :class:`WorldBuilder` (a
  world in code) and :class:`Simulation`
  (``step``, ``advance``, bodies and fields as NumPy arrays);
- :func:`value_and_grad` and :class:`BodyTargetLoss`; :func:`optimize`, the Rust optimiser;
- :mod:`diffluid.torch`: ``rollout`` as a ``torch.autograd.Function``, and control through
  the water: ``trajectory`` (actions at every step, losses on the whole trajectory) and
  ``Stepper`` (a closed-loop policy trained through the simulator) (needs torch);
  :func:`controlled_run` and :class:`Stepper` are their NumPy halves;
- :mod:`diffluid.ray`: N independent rollouts or gradients as Ray tasks (needs ray).

Every diffluid error is a Python exception with the CLI's message: ``ValueError`` for a bad
scene or argument, :class:`SolverError` for a pressure solve that does not converge,
:class:`SimulationError` for a state that blew up or a body that left the tank,
:class:`GradientError` for a map the backward pass cannot differentiate. Steps and gradients
release the GIL. :func:`tune_memory` sets the process's malloc as the CLI's (for grids of a
million cells and more: a lower, steadier peak).
"""

from ._diffluid import (
    BodyTargetLoss,
    ControlledRun,
    GradientError,
    InternalError,
    Rollout,
    Scene,
    Simulation,
    SimulationError,
    SolverError,
    Stepper,
    __version__,
    controlled_run,
    optimize,
    rollout,
    tune_memory,
    value_and_grad,
)
from .builder import WorldBuilder

__all__ = [
    "BodyTargetLoss",
    "ControlledRun",
    "GradientError",
    "InternalError",
    "Rollout",
    "Scene",
    "Simulation",
    "SimulationError",
    "SolverError",
    "Stepper",
    "__version__",
    "controlled_run",
    "optimize",
    "rollout",
    "tune_memory",
    "value_and_grad",
    "WorldBuilder",
]
