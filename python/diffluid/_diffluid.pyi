"""Type stubs for diffluid's native module (the docstrings are the Rust side's)."""

from os import PathLike
from typing import Any, Optional, Sequence, Tuple, TypedDict, Union, final

import numpy as np
import numpy.typing as npt

__version__: str

F64 = npt.NDArray[np.float64]
Body = Union[int, str]
Target3 = Union[Sequence[float], Tuple[Sequence[float], float]]
Target4 = Union[Sequence[float], Tuple[Sequence[float], float]]

class SimulationError(RuntimeError):
    """The state blew up (NaN or infinity) or a body left the tank with contact off."""

class SolverError(SimulationError):
    """A pressure solve (forward or adjoint) did not reach its tolerance."""

class GradientError(ValueError):
    """A forward map the backward pass cannot differentiate."""

class InternalError(RuntimeError):
    """A Rust panic caught at the boundary: a bug in diffluid."""

@final
class Scene:
    """A validated scene. Pickles (as JSON, every number exact)."""

    @staticmethod
    def from_file(path: Union[str, PathLike[str]]) -> Scene: ...
    @staticmethod
    def from_toml(
        text: str, origin: str = "<string>", base_dir: Optional[Union[str, PathLike[str]]] = None
    ) -> Scene: ...
    @staticmethod
    def builtin(name: str) -> Scene: ...
    @staticmethod
    def load(scene: Union[str, PathLike[str]]) -> Scene:
        """A path, or a built-in name, as the CLI resolves its SCENE argument."""
    @staticmethod
    def builtin_names() -> list[str]: ...
    @staticmethod
    def from_json(text: str, base_dir: Optional[Union[str, PathLike[str]]] = None) -> Scene: ...
    def to_json(self) -> str: ...
    @property
    def name(self) -> str: ...
    @property
    def description(self) -> str: ...
    @property
    def steps(self) -> int: ...
    @steps.setter
    def steps(self, steps: int) -> None: ...
    @property
    def dt(self) -> float: ...
    @property
    def dx(self) -> float: ...
    @property
    def size(self) -> list[float]: ...
    @property
    def body_names(self) -> list[str]: ...
    @property
    def freeze_surface(self) -> bool: ...
    @freeze_surface.setter
    def freeze_surface(self, on: bool) -> None: ...
    @property
    def has_loss(self) -> bool: ...
    @property
    def loss(self) -> Optional[BodyTargetLoss]: ...
    @property
    def optimize_spec(self) -> Optional[dict[str, Any]]: ...
    def __copy__(self) -> Scene: ...
    def __deepcopy__(self, memo: Any) -> Scene: ...
    def __eq__(self, other: object, /) -> bool: ...

class BodyForceReport(TypedDict):
    name: str
    force: list[float]
    torque: list[float]
    volume_error: float

class StepReport(TypedDict, total=False):
    step: int
    time: float
    liquid_cells: int
    cg_iterations: int
    cg_relative_residual: float
    density_cg_iterations: int
    max_divergence: float
    liquid_volume: float
    max_speed: float
    kinetic_energy: float
    bodies: list[BodyForceReport]
    contact_iterations: int
    contact_residual: float
    stage_seconds: dict[str, float]
    warnings: list[str]

class BodyStateDict(TypedDict):
    v: F64
    w: F64
    x: F64
    q: F64

@final
class Simulation:
    """A running simulation. Arrays are float64 read-only copies; quaternions [w, x, y, z];
    grid fields indexed [i, j, k]. step/run/advance release the GIL; a call from another
    thread meanwhile raises RuntimeError ("in use by another thread")."""

    def __new__(cls, scene: Scene) -> Simulation: ...
    def step(self) -> StepReport:
        """A step that fails (SimulationError, SolverError) is rolled back."""
    def run(self, steps: Optional[int] = None) -> StepReport:
        """Ctrl-C between steps raises KeyboardInterrupt, the steps taken kept."""
    def advance(self, frame_dt: float) -> list[StepReport]:
        """Ctrl-C between steps raises KeyboardInterrupt, the steps taken kept."""
    def copy(self) -> Simulation: ...
    def __copy__(self) -> Simulation: ...
    def __deepcopy__(self, memo: Any) -> Simulation: ...
    @property
    def rollback(self) -> bool:
        """Whether a step that fails is rolled back (True by default)."""
    @rollback.setter
    def rollback(self, on: bool) -> None: ...
    @property
    def time(self) -> float: ...
    @property
    def steps_taken(self) -> int: ...
    @property
    def scene_steps(self) -> int: ...
    @property
    def dt(self) -> float: ...
    @property
    def dx(self) -> float: ...
    @property
    def shape(self) -> list[int]: ...
    @property
    def warnings(self) -> list[str]: ...
    @property
    def body_names(self) -> list[str]: ...
    @property
    def num_bodies(self) -> int: ...
    @property
    def positions(self) -> F64:
        """(bodies, 3)"""
    @property
    def orientations(self) -> F64:
        """(bodies, 4), [w, x, y, z]"""
    @property
    def velocities(self) -> F64:
        """(bodies, 3)"""
    @property
    def angular_velocities(self) -> F64:
        """(bodies, 3)"""
    @property
    def masses(self) -> F64:
        """(bodies,), kg"""
    def set_mass(self, body: Body, kg: float) -> None:
        """The body's mass (finite, > 0), its inertia scaling with it."""
    def fluid_forces(self) -> Tuple[F64, F64]:
        """(forces (bodies, 3), torques (bodies, 3)) of the last step's solve."""
    def body_state(self, body: Body) -> BodyStateDict: ...
    def set_body_state(
        self,
        body: Body,
        *,
        v: Optional[F64] = None,
        w: Optional[F64] = None,
        x: Optional[F64] = None,
        q: Optional[F64] = None,
    ) -> None: ...
    def set_external_force(self, body: Body, force: F64, torque: Optional[F64] = None) -> None: ...
    @property
    def motions(self) -> list[str]:
        """Per body: "dynamic", "kinematic", "fixed" or "external"."""
    def set_kinematic(self, body: Body) -> None:
        """Makes a body (e.g. a paddle a scene holds at rest, "fixed") kinematic: moved along
        its own velocity, which control actions set."""
    @property
    def particles(self) -> F64:
        """(particles, 3)"""
    @property
    def pressure(self) -> F64:
        """(nx, ny, nz)"""
    @property
    def liquid_phi(self) -> F64:
        """(nx, ny, nz)"""
    @property
    def velocity(self) -> Tuple[F64, F64, F64]:
        """u (nx+1, ny, nz), v (nx, ny+1, nz), w (nx, ny, nz+1)"""
    def velocity_flat(self) -> F64: ...
    def set_velocity_flat(self, u: F64) -> None: ...
    def scene_loss(self) -> Optional[float]: ...

@final
class BodyTargetLoss:
    """wx·|x − x*|² + wq·(1 − (q·q*)²) + wv·|v − v*|² on one body's final state."""

    def __new__(
        cls,
        body: Body,
        position: Optional[Target3] = None,
        orientation: Optional[Target4] = None,
        velocity: Optional[Target3] = None,
    ) -> BodyTargetLoss: ...
    @property
    def body(self) -> Body: ...
    def body_index(self, sim: Simulation) -> int: ...
    @property
    def position(self) -> Optional[Tuple[list[float], float]]: ...
    @property
    def orientation(self) -> Optional[Tuple[list[float], float]]: ...
    @property
    def velocity(self) -> Optional[Tuple[list[float], float]]: ...
    def value(self, sim: Simulation) -> float: ...

@final
class Rollout:
    """A taped forward run; backward() is the vector–Jacobian product."""

    @property
    def steps(self) -> int: ...
    def final_state(self) -> Tuple[F64, F64, F64, F64]: ...
    def final_simulation(self) -> Simulation: ...
    def backward(
        self, gv: F64, gw: F64, gx: F64, gq: F64, *, fluid: bool = False
    ) -> Tuple[F64, F64, F64, F64, Optional[F64], F64]:
        """(gv0, gw0, gx0, gq0, gu0 or None, gm0 (bodies,): ∂L/∂masses)."""

def value_and_grad(
    scene: Union[Scene, Simulation],
    loss: Optional[BodyTargetLoss] = None,
    params: Optional[Sequence[str]] = None,
    *,
    steps: Optional[int] = None,
    state: Optional[dict[str, F64]] = None,
    body: Optional[Body] = None,
    surface: str = "live",
    mode: str = "full",
    checkpoint_every: Optional[int] = None,
    through_contact: bool = True,
    smoothing: Optional[dict[str, Any]] = None,
) -> Tuple[float, dict[str, Any]]:
    """(loss, {param: gradient}): v, w, x, q (tangent) as (3,) arrays; mass as a float; u
    as a tuple of three face arrays. With smoothing ({samples, sigma: {v, w, x, q}, seed,
    estimator: "gradients" or "values"}), the smoothed loss and gradient, and
    grads["standard_error"] per param."""

def optimize(scene: Scene, *, epochs: Optional[int] = None) -> dict[str, Any]:
    """Ctrl-C after an epoch raises KeyboardInterrupt with the result so far as .result."""
def rollout(
    sim: Simulation,
    v: F64,
    w: F64,
    x: F64,
    q: F64,
    u: Optional[F64] = None,
    *,
    steps: Optional[int] = None,
    surface: str = "live",
    mode: str = "full",
    through_contact: bool = True,
    checkpoint_every: Optional[int] = None,
    masses: Optional[F64] = None,
) -> Rollout: ...
@final
class ControlledRun:
    """A run under a schedule of actions, kept; backward() is the vector–Jacobian product
    from a gradient on the states at the action boundaries to the actions and initial state."""

    @property
    def num_actions(self) -> int: ...
    @property
    def steps_per_action(self) -> int: ...
    @property
    def controlled(self) -> list[int]: ...
    def states(self) -> F64:
        """(T + 1, bodies, 13): x, q [w, x, y, z], v, ω at every action boundary."""
    def step_states(self) -> F64:
        """(T·steps_per_action + 1, bodies, 13): after every step."""
    def final_simulation(self) -> Simulation: ...
    def backward(self, grad: F64) -> Tuple[F64, F64, F64]:
        """grad (T + 1, bodies, 13) -> (∂L/∂actions (T, bodies, 6), ∂L/∂state0 (bodies, 13),
        ∂L/∂masses (bodies,))."""

def controlled_run(
    sim: Simulation,
    actions: F64,
    state0: Optional[F64] = None,
    *,
    steps_per_action: int = 1,
    surface: str = "live",
    mode: str = "full",
    through_contact: bool = True,
    checkpoint_every: Optional[int] = None,
    bodies: Optional[Sequence[Body]] = None,
    masses: Optional[F64] = None,
) -> ControlledRun:
    """actions (T, bodies, 6): [force, torque] of a dynamic body, [v, ω] of a kinematic one
    (other rows ignored); state0 (bodies, 13)."""

@final
class Stepper:
    """A run driven one action at a time and taken back one action at a time (last first,
    each once), the liquid's adjoint carried inside; what diffluid.torch.Stepper builds on."""

    def __new__(
        cls,
        sim: Simulation,
        *,
        steps_per_action: int = 1,
        surface: str = "live",
        mode: str = "full",
        through_contact: bool = True,
        bodies: Optional[Sequence[Body]] = None,
        masses: Optional[F64] = None,
    ) -> Stepper: ...
    def step(self, action: F64, state: Optional[F64] = None) -> Tuple[int, F64]:
        """action (bodies, 6), state (bodies, 13) -> (k, states after (bodies, 13))."""
    def backward(self, k: int, grad: F64) -> Tuple[F64, F64, F64]:
        """∂L/∂(states after action k) -> (∂L/∂action k (bodies, 6), ∂L/∂(states before),
        what action k adds to ∂L/∂masses (bodies,))."""
    def mass_gradient(self) -> F64:
        """∂L/∂masses (bodies,) over the actions taken back so far."""
    def reset(self, masses: Optional[F64] = None) -> None:
        """A new run from where this one started, optionally with new masses."""
    @property
    def masses(self) -> F64: ...
    def states(self) -> F64: ...
    def simulation(self) -> Simulation: ...
    @property
    def steps_taken(self) -> int: ...
    @property
    def actions_pending(self) -> int:
        """Actions taken and not yet taken back."""
    @property
    def steps_per_action(self) -> int: ...
    @property
    def controlled(self) -> list[int]: ...

def _panic_for_tests() -> None:
    """Panics inside the boundary guard (raises InternalError); for the tests."""
def tune_memory() -> bool:
    """Sets glibc's malloc for the whole process as the diffluid binary does (one arena, no
    allocation mapped apart, no trimming); True where it applies (Linux with glibc). Call it
    before the first step."""
