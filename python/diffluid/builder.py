"""A world built in code: the tank, the liquid's regions, obstacles and bodies, with shapes
given as the scene file's shape tables (``{"kind": "ball", "radius": 0.06}``,
``{"kind": "cuboid", "half_extents": [...]}``, ``{"kind": "mesh", "obj": "..."}``...).

The builder writes a scene and validates it as a scene file is validated, so a mistake is a
ValueError naming the key (``body[1].density``), and what it builds is a :class:`Scene`
like any other: it pickles, goes to Ray tasks, and has the same defaults.

>>> import diffluid
>>> sim = (diffluid.WorldBuilder([0.6, 0.4, 0.4], 0.05, dt=0.01)
...        .liquid({"kind": "box", "min": [0, 0, 0], "max": [0.6, 0.2, 0.4]})
...        .body("ball", {"kind": "ball", "radius": 0.06}, position=[0.3, 0.25, 0.2],
...              density=500.0)
...        .build())
>>> sim.body_names
['ball']
"""

from __future__ import annotations

import json
import os
from typing import Any, Dict, List, Mapping, Optional, Sequence

from ._diffluid import Scene, Simulation

__all__ = ["WorldBuilder"]

Vec = Sequence[float]


def _placed(shape: Mapping[str, Any], position: Optional[Vec], quaternion: Optional[Vec]) -> Dict[str, Any]:
    out: Dict[str, Any] = {"shape": dict(shape)}
    if position is not None:
        out["position"] = [float(c) for c in position]
    if quaternion is not None:
        out["quaternion"] = [float(c) for c in quaternion]
    return out


class WorldBuilder:
    """Builds a world from plain parts; everything has a default but the tank.

    `size` is the tank's extent (x, y up, z) in metres and `dx` the cell side; `steps` is the
    default horizon of :meth:`Simulation.run` and the gradients. `solver` and `contact` are
    dicts of the scene file's ``[solver]`` and ``[contact]`` keys.
    """

    def __init__(
        self,
        size: Vec,
        dx: float,
        *,
        dt: float = 0.01,
        steps: int = 1,
        density: float = 1000.0,
        gravity: Vec = (0.0, -9.81, 0.0),
        solver: Optional[Mapping[str, Any]] = None,
        contact: Optional[Mapping[str, Any]] = None,
        name: str = "world",
        base_dir: Optional[str] = None,
    ) -> None:
        self._scene: Dict[str, Any] = {
            "name": name,
            "domain": {"size": [float(c) for c in size], "dx": float(dx)},
            "time": {"dt": float(dt), "steps": int(steps)},
            "fluid": {"density": float(density), "gravity": [float(c) for c in gravity]},
            "liquid": [],
            "obstacle": [],
            "body": [],
            "solver": dict(solver or {}),
            "contact": dict(contact or {}),
            "output": {"particles": False, "every": 1},
        }
        self._base = base_dir if base_dir is not None else os.getcwd()

    def liquid(
        self, shape: Mapping[str, Any], *, position: Optional[Vec] = None, quaternion: Optional[Vec] = None
    ) -> "WorldBuilder":
        """Adds a region that starts full of liquid (the liquid is the union of them)."""
        self._scene["liquid"].append(_placed(shape, position, quaternion))
        return self

    def obstacle(
        self, shape: Mapping[str, Any], *, position: Optional[Vec] = None, quaternion: Optional[Vec] = None
    ) -> "WorldBuilder":
        """Adds a static solid."""
        self._scene["obstacle"].append(_placed(shape, position, quaternion))
        return self

    def body(
        self,
        name: str,
        shape: Mapping[str, Any],
        *,
        position: Vec = (0.0, 0.0, 0.0),
        quaternion: Optional[Vec] = None,
        density: Optional[float] = None,
        mass: Optional[float] = None,
        velocity: Vec = (0.0, 0.0, 0.0),
        angular_velocity: Vec = (0.0, 0.0, 0.0),
        dynamic: bool = True,
    ) -> "WorldBuilder":
        """Adds a rigid body: a shape placed at `position` (its local origin), with a density
        or a mass, and an initial velocity. ``dynamic=False`` holds it still, or with a
        velocity moves it along that velocity (a paddle)."""
        b = _placed(shape, position, quaternion)
        b.update(
            name=name,
            velocity=[float(c) for c in velocity],
            angular_velocity=[float(c) for c in angular_velocity],
            dynamic=bool(dynamic),
        )
        if density is not None:
            b["density"] = float(density)
        if mass is not None:
            b["mass"] = float(mass)
        self._scene["body"].append(b)
        return self

    def scene(self) -> Scene:
        """The scene, validated (ValueError naming the key when something is wrong)."""
        return Scene.from_json(json.dumps(self._scene), base_dir=self._base)

    def build(self) -> Simulation:
        """The simulation in its initial state."""
        return Simulation(self.scene())
