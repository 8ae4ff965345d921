"""N independent diffluid rollouts or gradients as Ray tasks.

A multi-start search or a parameter sweep: each initial state is one Ray task, which builds
the scene's simulation in its worker, sets the state and runs it (or its gradient). The scene
is sent once (``ray.put``). The same code runs on a local Ray instance (``ray.init()``, or
none: Ray starts one on first use) and on a cluster (``ray.init(address="auto")`` on a node
of the cluster, ``ray.init(address="ray://head:10001")`` from outside, or the RAY_ADDRESS
environment variable); the workers need this package installed (or a ``runtime_env`` that
installs it).

Each task runs diffluid with ``threads_per_task`` rayon threads (RAYON_NUM_THREADS in the
task's runtime environment; default 1) and asks Ray for that many CPUs, so a node runs as
many tasks at once as it has cores. Results come back in the order of ``states`` and are
identical to running :func:`rollout_one` or :func:`value_and_grad_one` serially: diffluid's
results do not depend on the thread count.
"""

from __future__ import annotations

from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import ray

from ._diffluid import BodyTargetLoss, Scene, Simulation, value_and_grad

__all__ = ["rollout_one", "rollouts", "value_and_grad_one", "value_and_grads"]

State = Mapping[str, Any]
Body = Union[int, str]


def _arrays(state: Optional[State]) -> Dict[str, np.ndarray]:
    return {k: np.asarray(v, dtype=np.float64) for k, v in (state or {}).items()}


def rollout_one(
    scene: Scene, state: Optional[State] = None, body: Body = 0, steps: Optional[int] = None
) -> Dict[str, np.ndarray]:
    """One rollout: `scene`'s simulation with body `body`'s initial state overridden by
    `state` (any of v, w, x, q), run `steps` steps (default: the scene's). Returns the final
    state of every body: v, w, x (bodies, 3), q (bodies, 4) ``[w, x, y, z]``, and the final
    time t. What each task of :func:`rollouts` runs."""
    sim = Simulation(scene)
    if state:
        sim.set_body_state(body, **_arrays(state))
    sim.run(steps)
    return {
        "v": np.array(sim.velocities),
        "w": np.array(sim.angular_velocities),
        "x": np.array(sim.positions),
        "q": np.array(sim.orientations),
        "t": np.array(sim.time),
    }


def value_and_grad_one(
    scene: Scene,
    state: Optional[State] = None,
    loss: Optional[BodyTargetLoss] = None,
    params: Optional[Sequence[str]] = None,
    **kwargs: Any,
) -> Tuple[float, Dict[str, Any]]:
    """One gradient: :func:`diffluid.value_and_grad` from the loss body's initial state
    overridden by `state`. What each task of :func:`value_and_grads` runs."""
    return value_and_grad(
        scene, loss, None if params is None else list(params), state=_arrays(state), **kwargs
    )


def _options(threads_per_task: int, ray_options: Dict[str, Any]) -> Dict[str, Any]:
    if threads_per_task < 1:
        raise ValueError(f"threads_per_task: at least 1, got {threads_per_task}")
    opts: Dict[str, Any] = {"num_cpus": threads_per_task}
    env = {"RAYON_NUM_THREADS": str(threads_per_task)}
    runtime_env = dict(ray_options.pop("runtime_env", None) or {})
    runtime_env["env_vars"] = {**env, **runtime_env.get("env_vars", {})}
    opts["runtime_env"] = runtime_env
    opts.update(ray_options)
    return opts


_rollout_task = ray.remote(rollout_one)
_gradient_task = ray.remote(value_and_grad_one)


def rollouts(
    scene: Scene,
    states: Sequence[Optional[State]],
    *,
    body: Body = 0,
    steps: Optional[int] = None,
    threads_per_task: int = 1,
    **ray_options: Any,
) -> List[Dict[str, np.ndarray]]:
    """Runs one Ray task per entry of `states` (see :func:`rollout_one`) and returns their
    results in order. Extra keyword arguments are Ray task options (``num_cpus``,
    ``resources``, ``runtime_env``...)."""
    opts = _options(threads_per_task, ray_options)
    ref = ray.put(scene)
    task = _rollout_task.options(**opts)
    return ray.get([task.remote(ref, s, body, steps) for s in states])


def value_and_grads(
    scene: Scene,
    states: Sequence[Optional[State]],
    loss: Optional[BodyTargetLoss] = None,
    params: Optional[Sequence[str]] = None,
    *,
    threads_per_task: int = 1,
    gradient_options: Optional[Dict[str, Any]] = None,
    **ray_options: Any,
) -> List[Tuple[float, Dict[str, Any]]]:
    """Runs one Ray task per entry of `states` (see :func:`value_and_grad_one`) and returns
    their ``(loss, grads)`` in order. `gradient_options` are passed to
    :func:`diffluid.value_and_grad` (steps, body, surface, mode, checkpoint_every,
    through_contact); extra keyword arguments are Ray task options."""
    opts = _options(threads_per_task, ray_options)
    ref = ray.put(scene)
    task = _gradient_task.options(**opts)
    kw = dict(gradient_options or {})
    return ray.get([task.remote(ref, s, loss, params, **kw) for s in states])
