"""Shared fixtures: small scenes, shortened so the suite runs in about a minute."""

import pytest

import diffluid


@pytest.fixture
def box_scene() -> diffluid.Scene:
    """gradcheck_box (16 x 12 x 16 cells, a tilted box, frozen surface), 6 steps."""
    s = diffluid.Scene.builtin("gradcheck_box")
    s.steps = 6
    return s


@pytest.fixture
def live_scene() -> diffluid.Scene:
    """gradcheck_live: gradcheck_box with the surface moving, 4 steps."""
    s = diffluid.Scene.builtin("gradcheck_live")
    s.steps = 4
    return s


# A scene small enough to build in milliseconds, to edit into bad ones.
SMALL = """
name = "small"
[domain]
size = [0.4, 0.4, 0.4]
dx = 0.05
[time]
dt = 0.01
steps = 3
[fluid]
density = 1000.0
gravity = [0.0, -9.81, 0.0]
[[liquid]]
shape = { kind = "box", min = [0.0, 0.0, 0.0], max = [0.4, 0.2, 0.4] }
[[body]]
name = "ball"
shape = { kind = "ball", radius = 0.06 }
density = 500.0
position = [0.2, 0.22, 0.2]
[solver]
tolerance = 1e-10
"""


@pytest.fixture
def small_toml() -> str:
    return SMALL
