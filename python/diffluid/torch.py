"""PyTorch autograd through diffluid.

:func:`rollout` runs a simulation forward from an initial body state given as float64
tensors and returns the final body state as tensors; ``loss.backward()`` then runs
diffluid's adjoint: the gradient torch hands back on the final state (v, ω, x, q) becomes
the adjoint of a linear loss on it, and one backward pass over the forward run's tape turns
it into the gradient on the initial state (a vector–Jacobian product). Nothing is run twice:
the forward pass keeps its tape for the backward pass.

Orientations are quaternions ``[w, x, y, z]``. The simulation starts from ``q / |q|`` (a unit
``q`` is used bit for bit), and the gradient on ``q`` is that of the map through the
normalisation (it has no component along ``q``).

Control through the water: :func:`trajectory` runs a schedule of actions (a force and torque
on each dynamic body, a velocity and angular velocity on each kinematic one, at every
action) and returns the body states at every action boundary, differentiably with respect to
every action and the initial state, in one backward sweep; :class:`Stepper` takes one action
at a time, for a closed-loop policy trained through the simulator. A body state is one row
of 13 numbers: x (3), q ``[w, x, y, z]`` (4), v (3), ω (3) (the slices :data:`X`, :data:`Q`,
:data:`V`, :data:`W`).

Physical parameters: :func:`rollout`, :func:`trajectory` and :class:`Stepper` take the
bodies' masses as an optional float64 tensor ``masses`` (bodies,), each body's inertia
scaling with its mass (its density changes, not its shape); its gradient comes from the same
backward sweep. Only dynamic bodies' masses act: the entries of kinematic, fixed and
external bodies are checked (finite, > 0) but ignored, and their gradient is zero.
"""

from __future__ import annotations

from typing import NamedTuple, Optional, Sequence, Union

import numpy as np
import torch

from . import _diffluid
from ._diffluid import BodyTargetLoss, Simulation

__all__ = [
    "BodyState",
    "Q",
    "Stepper",
    "V",
    "W",
    "X",
    "body_states",
    "initial_state",
    "rollout",
    "step",
    "target_loss",
    "trajectory",
]

#: Where x, q ``[w, x, y, z]``, v and ω sit in a body's row of 13 (:func:`trajectory`,
#: :class:`Stepper`): ``states[..., X]``.
X, Q, V, W = slice(0, 3), slice(3, 7), slice(7, 10), slice(10, 13)


class BodyState(NamedTuple):
    """A body state as tensors: v, w (ω, world frame), x (centre of mass), each (bodies, 3)
    or (3,); q ``[w, x, y, z]``, (bodies, 4) or (4,)."""

    v: torch.Tensor
    w: torch.Tensor
    x: torch.Tensor
    q: torch.Tensor


def _numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy()


def _check(name: str, t: object) -> torch.Tensor:
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name}: a torch.Tensor, not {type(t).__name__}")
    if t.dtype != torch.float64:
        raise TypeError(f"{name}: dtype must be torch.float64, got {t.dtype}")
    return t


def _masses(sim: Simulation, masses: Optional[torch.Tensor]) -> Optional[torch.Tensor]:
    """`masses` checked as a float64 tensor of one mass per body of `sim` ((bodies,), or ()
    with one body); its values are checked (finite, > 0) where they are used."""
    return None if masses is None else _masses_for(sim.num_bodies, masses)


def _masses_for(bodies: int, masses: torch.Tensor) -> torch.Tensor:
    _check("masses", masses)
    if masses.dim() == 0 and bodies == 1:
        return masses.reshape(1)
    if tuple(masses.shape) != (bodies,):
        raise ValueError(f"masses: expected shape ({bodies},), got {list(masses.shape)}")
    return masses


class _RolloutFunction(torch.autograd.Function):
    """forward: a taped diffluid run; backward: diffluid's adjoint over that tape."""

    @staticmethod
    def forward(ctx, sim, options, v, w, x, q, u, masses):  # type: ignore[override]
        r = _diffluid.rollout(
            sim,
            _numpy(v),
            _numpy(w),
            _numpy(x),
            _numpy(q),
            None if u is None else _numpy(u),
            masses=None if masses is None else _numpy(masses),
            **options,
        )
        ctx.rollout = r
        ctx.fluid = u is not None
        ctx.device = v.device
        # The arrays handed out are read-only copies: copy again into tensors torch owns.
        return tuple(torch.from_numpy(np.array(a)).to(v.device) for a in r.final_state())

    @staticmethod
    def backward(ctx, gv, gw, gx, gq):  # type: ignore[override]
        fluid = ctx.fluid and ctx.needs_input_grad[6]
        g = ctx.rollout.backward(
            _numpy(gv), _numpy(gw), _numpy(gx), _numpy(gq), fluid=fluid
        )
        out = [torch.from_numpy(np.array(a)).to(ctx.device) for a in g[:4]]
        gu = None if g[4] is None else torch.from_numpy(np.array(g[4])).to(ctx.device)
        gm = _tensor(g[5], ctx.device) if ctx.needs_input_grad[7] else None
        return (None, None, *out, gu, gm)


def rollout(
    sim: Simulation,
    v: torch.Tensor,
    w: torch.Tensor,
    x: torch.Tensor,
    q: torch.Tensor,
    fluid_velocity: Optional[torch.Tensor] = None,
    *,
    steps: Optional[int] = None,
    surface: str = "live",
    mode: str = "full",
    through_contact: bool = True,
    checkpoint_every: Optional[int] = None,
    masses: Optional[torch.Tensor] = None,
) -> BodyState:
    """Runs `steps` steps (default: the scene's ``time.steps``) of `sim` from the initial
    body state (v, w, x, q) and returns the final body state, differentiably.

    `v`, `w`, `x` are (bodies, 3) and `q` is (bodies, 4) ``[w, x, y, z]``; for a simulation
    with one body they may be (3,) and (4,), and the result then has the same shapes.
    `fluid_velocity` optionally sets the initial fluid velocity, flat in
    :meth:`Simulation.velocity_flat`'s order, and receives a gradient too; so does `masses`
    (bodies,), or () for a simulation with one body: the bodies' masses for the run (each
    finite and > 0; the entries of bodies that are not dynamic are ignored and get a zero
    gradient). Every tensor must be float64 (TypeError otherwise); shapes, NaNs and
    masses are checked (ValueError). `sim` itself is not changed: the run starts from a copy
    of it with this state.

    `surface`, `mode` and `through_contact` are the backward pass's options, as in
    :func:`diffluid.value_and_grad`. With `checkpoint_every` = k the forward pass keeps the
    state every k steps (and each step's pressure) instead of the whole tape, and the
    backward pass re-runs one segment at a time without solving the pressure again (memory
    for k steps, about half a forward pass more, the same gradient bit for bit).
    The GIL is released in both passes.
    """
    v, w, x, q = (_check(n, t) for n, t in (("v", v), ("w", w), ("x", x), ("q", q)))
    if fluid_velocity is not None:
        _check("fluid_velocity", fluid_velocity)
    masses = _masses(sim, masses)
    single = v.dim() == 1
    if single:
        if sim.num_bodies != 1:
            raise ValueError(
                f"v: a (3,) state is for a simulation with one body; this one has "
                f"{sim.num_bodies}: pass (bodies, 3)"
            )
        v, w, x, q = (t.unsqueeze(0) for t in (v, w, x, q))
    options = dict(
        steps=steps,
        surface=surface,
        mode=mode,
        through_contact=through_contact,
        checkpoint_every=checkpoint_every,
    )
    out = _RolloutFunction.apply(sim, options, v, w, x, q, fluid_velocity, masses)
    if single:
        out = tuple(t.squeeze(0) for t in out)
    return BodyState(*out)


def initial_state(sim: Simulation, requires_grad: bool = False) -> BodyState:
    """`sim`'s current body state as float64 tensors of shape (bodies, ·), copies, with
    ``requires_grad`` set as asked."""

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.tensor(np.array(a), dtype=torch.float64, requires_grad=requires_grad)

    return BodyState(
        t(sim.velocities), t(sim.angular_velocities), t(sim.positions), t(sim.orientations)
    )


def target_loss(loss: BodyTargetLoss, sim: Simulation, final: BodyState) -> torch.Tensor:
    """`loss` (a :class:`diffluid.BodyTargetLoss`, e.g. ``scene.loss``) evaluated in torch on
    a :func:`rollout`'s final state: ``wx·|x − x*|² + wq·(1 − (q·q*)²) + wv·|v − v*|²`` for
    the loss's body, the same terms in the same order as diffluid's own."""
    i = loss.body_index(sim)
    pick = (lambda t: t) if final.x.dim() == 1 else (lambda t: t[i])
    out = torch.zeros((), dtype=torch.float64, device=final.x.device)
    if loss.position is not None:
        t, wt = loss.position
        out = out + wt * _squared(pick(final.x) - torch.tensor(t, dtype=torch.float64))
    if loss.orientation is not None:
        t, wt = loss.orientation
        qt = torch.tensor(t, dtype=torch.float64)
        qt = qt / torch.linalg.vector_norm(qt)
        out = out + wt * (1.0 - (pick(final.q) * qt).sum() ** 2)
    if loss.velocity is not None:
        t, wt = loss.velocity
        out = out + wt * _squared(pick(final.v) - torch.tensor(t, dtype=torch.float64))
    return out


def _squared(d: torch.Tensor) -> torch.Tensor:
    """|d|² summed left to right, as diffluid sums it (x·x + y·y + z·z)."""
    return d[0] * d[0] + d[1] * d[1] + d[2] * d[2]


def _tensor(a: np.ndarray, device: torch.device) -> torch.Tensor:
    """A read-only array handed out by diffluid as a tensor torch owns."""
    return torch.from_numpy(np.array(a)).to(device)


def body_states(sim: Simulation, requires_grad: bool = False) -> torch.Tensor:
    """`sim`'s current body states as a float64 tensor (bodies, 13): x, q ``[w, x, y, z]``,
    v, ω per row (a copy), with ``requires_grad`` set as asked: a ``state0`` for
    :func:`trajectory`, or the state a :class:`Stepper`'s first step starts from."""
    rows = np.concatenate(
        [sim.positions, sim.orientations, sim.velocities, sim.angular_velocities], axis=1
    )
    return torch.tensor(rows, dtype=torch.float64, requires_grad=requires_grad)


def _bodies(bodies: Optional[Sequence[Union[int, str]]]) -> Optional[list]:
    """A body or a sequence of them as a list (None: every steerable body)."""
    if bodies is None:
        return None
    if isinstance(bodies, (str, int)):
        return [bodies]
    return list(bodies)


class _TrajectoryFunction(torch.autograd.Function):
    """forward: a run under a schedule of actions, kept; backward: one adjoint sweep over it."""

    @staticmethod
    def forward(ctx, sim, options, actions, state0, masses):  # type: ignore[override]
        r = _diffluid.controlled_run(
            sim,
            _numpy(actions),
            None if state0 is None else _numpy(state0),
            masses=None if masses is None else _numpy(masses),
            **options,
        )
        ctx.run = r
        ctx.device = actions.device
        return _tensor(r.states(), actions.device)

    @staticmethod
    def backward(ctx, grad):  # type: ignore[override]
        ga, g0, gm = ctx.run.backward(_numpy(grad))
        g0 = _tensor(g0, ctx.device) if ctx.needs_input_grad[3] else None
        gm = _tensor(gm, ctx.device) if ctx.needs_input_grad[4] else None
        return None, None, _tensor(ga, ctx.device), g0, gm


def trajectory(
    sim: Simulation,
    actions: torch.Tensor,
    state0: Optional[torch.Tensor] = None,
    *,
    steps_per_action: int = 1,
    surface: str = "live",
    mode: str = "full",
    through_contact: bool = True,
    checkpoint_every: Optional[int] = None,
    bodies: Optional[Sequence[Union[int, str]]] = None,
    masses: Optional[torch.Tensor] = None,
) -> torch.Tensor:
    """Runs `sim` under `actions` and returns the body states at every action boundary,
    differentiably with respect to `actions`, `state0` and `masses`.

    `actions` is a float64 tensor (T, bodies, 6): action k on body i, held for
    `steps_per_action` steps (T·steps_per_action steps in all). A dynamic body's row is an
    external force and torque (world frame, N and N·m, on top of gravity), a kinematic
    body's (see :meth:`diffluid.Simulation.set_kinematic`) its velocity and angular velocity
    (m/s and rad/s, world frame); the rows of the other bodies (fixed, external, or left out
    of `bodies`) are ignored and get a zero gradient. `bodies` names the steered bodies
    (indices or names, each dynamic or kinematic); by default every dynamic and kinematic
    body is. `state0` (bodies, 13), optional, sets the initial body states (x, q
    ``[w, x, y, z]``, v, ω; q is normalised and its gradient goes through the
    normalisation); by default the run starts from `sim`'s current state. `masses`
    (bodies,), optional, sets the bodies' masses for the run (each finite and > 0; the
    entries of bodies that are not dynamic are ignored and get a zero gradient). `sim`
    itself is not changed.

    Returns ``states`` (T + 1, bodies, 13): ``states[k]`` the bodies after
    k·steps_per_action steps, before action k (``states[0]`` the initial state; a kinematic
    body's velocity there is the one the action before set). Any torch loss on them works:
    ``loss.backward()`` runs diffluid's adjoint once over the kept run (one sweep, whatever
    T) and gives ∂L/∂actions, ∂L/∂state0 and ∂L/∂masses.

    Checked before anything runs: float64 tensors (TypeError), shapes, NaNs and infinities,
    ``steps_per_action`` ≥ 1, the steered bodies (ValueError with the message). `surface`,
    `mode`, `through_contact` and `checkpoint_every` are as in :func:`rollout`. The GIL is
    released in both passes.
    """
    _check("actions", actions)
    if state0 is not None:
        _check("state0", state0)
    masses = _masses(sim, masses)
    options = dict(
        steps_per_action=steps_per_action,
        surface=surface,
        mode=mode,
        through_contact=through_contact,
        checkpoint_every=checkpoint_every,
        bodies=_bodies(bodies),
    )
    return _TrajectoryFunction.apply(sim, options, actions, state0, masses)


class _StepFunction(torch.autograd.Function):
    """forward: one action's taped steps; backward: that action taken back, the liquid's
    adjoint carried inside the native stepper (and what its steps add to ∂L/∂masses)."""

    @staticmethod
    def forward(ctx, native, action, state, masses):  # type: ignore[override]
        k, after = native.step(_numpy(action), _numpy(state))
        ctx.native, ctx.k, ctx.device = native, k, action.device
        return _tensor(after, action.device)

    @staticmethod
    def backward(ctx, grad):  # type: ignore[override]
        ga, gs, gm = ctx.native.backward(ctx.k, _numpy(grad))
        gm = _tensor(gm, ctx.device) if ctx.needs_input_grad[3] else None
        return None, _tensor(ga, ctx.device), _tensor(gs, ctx.device), gm


class Stepper:
    """A run driven one action at a time, for a closed-loop policy trained through the
    simulator::

        stepper = Stepper(sim, steps_per_action=5)
        s = stepper.initial_state()
        for t in range(T):
            s = stepper.step(policy(s), s)     # (bodies, 6), (bodies, 13) -> (bodies, 13)
        loss(s).backward()

    Each :meth:`step` is a ``torch.autograd.Function``: its forward runs the action's
    `steps_per_action` steps, taped, from `state` (the previous step's output: that is how
    torch links the steps); its backward takes that action back with diffluid's adjoint,
    returning the gradients on the action and on `state`, while the liquid's adjoint (its
    velocity and particles, which the states do not show) is carried inside the stepper from
    one action to the one before. The actions are as :func:`trajectory`'s (a force and torque
    on a dynamic body, a velocity on a kinematic one; other rows ignored), and the gradients
    are the same as :func:`trajectory`'s on the same actions.

    The backward steps must run once each, the last action first: what autograd does for
    one ``loss.backward()``. A second backward pass through the same steps (after
    ``retain_graph=True``) raises ValueError; sum the losses and call backward once. Once a
    backward pass has run, the stepper takes no more actions: :meth:`reset` starts the next
    episode from the same start, or go on from where it is with a new one,
    ``Stepper(stepper.simulation(), ...)`` (truncated backpropagation through time). Steps
    after the last one the loss reads are dropped at the cost of a backward step each.

    `masses` (bodies,), optional, a float64 tensor, sets the bodies' masses for the run
    (each finite and > 0; entries of bodies that are not dynamic are ignored): every step
    takes it as an input, so ``loss.backward()`` also gives ``masses.grad`` (what each
    action's steps add, summed by autograd). Without it, :meth:`mass_gradient` gives
    ∂L/∂m at the simulation's masses after the backward pass. To train masses over
    episodes, hand the updated tensor to ``reset(masses)``.

    The first step may start from any `state` (bodies, 13), and its gradient then goes
    through q's normalisation; each later `state` must be the states the step before
    returned (ValueError otherwise). `bodies`, `surface`, `mode` and `through_contact` are as
    in :func:`trajectory`. `sim` itself is not changed.
    """

    def __init__(
        self,
        sim: Simulation,
        *,
        steps_per_action: int = 1,
        surface: str = "live",
        mode: str = "full",
        through_contact: bool = True,
        bodies: Optional[Sequence[Union[int, str]]] = None,
        masses: Optional[torch.Tensor] = None,
    ) -> None:
        masses = _masses(sim, masses)
        self._native = _diffluid.Stepper(
            sim,
            steps_per_action=steps_per_action,
            surface=surface,
            mode=mode,
            through_contact=through_contact,
            bodies=_bodies(bodies),
            masses=None if masses is None else _numpy(masses),
        )
        self._masses = masses
        self._masses_used = None if masses is None else masses.detach().clone()
        self._num_bodies = sim.num_bodies
        self._initial = body_states(sim)

    def initial_state(self, requires_grad: bool = False) -> torch.Tensor:
        """The body states the run starts from (bodies, 13), a copy."""
        return self._initial.clone().requires_grad_(requires_grad)

    def step(self, action: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """Takes `action` (bodies, 6) from `state` (bodies, 13) for `steps_per_action` steps
        and returns the body states after them (bodies, 13), differentiably."""
        _check("action", action)
        _check("state", state)
        if self._masses is not None and not torch.equal(
            self._masses.detach().reshape(-1), self._masses_used
        ):
            raise ValueError(
                "masses: changed since the run started (an optimiser step?); reset(masses) "
                "starts a run with the new values"
            )
        return _StepFunction.apply(self._native, action, state, self._masses)

    def reset(self, masses: Optional[torch.Tensor] = None) -> None:
        """Starts the next run from where this one started, every action and adjoint of
        this one dropped (its graph can no longer go backward); with `masses`, a float64
        tensor (bodies,), the new run's masses (and the tensor its steps take as input)."""
        if masses is not None:
            masses = _masses_for(self._num_bodies, masses)
        self._native.reset(masses=None if masses is None else _numpy(masses))
        if masses is not None:
            self._masses = masses
            self._masses_used = masses.detach().clone()

    def mass_gradient(self) -> torch.Tensor:
        """∂L/∂(each body's mass) (bodies,) over the actions taken back so far: the run's
        once the backward pass has reached its first action (zero for bodies that are not
        dynamic), a tensor outside the graph."""
        return _tensor(self._native.mass_gradient(), self._initial.device)

    @property
    def masses(self) -> torch.Tensor:
        """The bodies' masses in the run (bodies,), kg, a copy outside the graph."""
        return _tensor(self._native.masses, self._initial.device)

    def states(self) -> torch.Tensor:
        """The body states now (bodies, 13), a copy outside the graph."""
        return _tensor(self._native.states(), self._initial.device)

    def simulation(self) -> Simulation:
        """The simulation now (a copy)."""
        return self._native.simulation()

    @property
    def steps_taken(self) -> int:
        """Actions taken in this run (since the last :meth:`reset`)."""
        return self._native.steps_taken

    @property
    def steps_per_action(self) -> int:
        return self._native.steps_per_action

    @property
    def controlled(self) -> list[int]:
        """The steered bodies' indices."""
        return self._native.controlled

    def __repr__(self) -> str:
        return repr(self._native)


def step(stepper: Stepper, action: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
    """``stepper.step(action, state)``."""
    return stepper.step(action, state)
