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
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np
import torch

from . import _diffluid
from ._diffluid import BodyTargetLoss, Simulation

__all__ = ["BodyState", "initial_state", "rollout", "target_loss"]


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


class _RolloutFunction(torch.autograd.Function):
    """forward: a taped diffluid run; backward: diffluid's adjoint over that tape."""

    @staticmethod
    def forward(ctx, sim, options, v, w, x, q, u):  # type: ignore[override]
        r = _diffluid.rollout(
            sim,
            _numpy(v),
            _numpy(w),
            _numpy(x),
            _numpy(q),
            None if u is None else _numpy(u),
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
        return (None, None, *out, gu)


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
    through_contact: bool = False,
    checkpoint_every: Optional[int] = None,
) -> BodyState:
    """Runs `steps` steps (default: the scene's ``time.steps``) of `sim` from the initial
    body state (v, w, x, q) and returns the final body state, differentiably.

    `v`, `w`, `x` are (bodies, 3) and `q` is (bodies, 4) ``[w, x, y, z]``; for a simulation
    with one body they may be (3,) and (4,), and the result then has the same shapes.
    `fluid_velocity` optionally sets the initial fluid velocity, flat in
    :meth:`Simulation.velocity_flat`'s order, and receives a gradient too. Every tensor must
    be float64 (TypeError otherwise); shapes and NaNs are checked (ValueError). `sim` itself
    is not changed: the run starts from a copy of it with this state.

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
    out = _RolloutFunction.apply(sim, options, v, w, x, q, fluid_velocity)
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
