"""Simulation: steps and reports, bodies and fields as NumPy arrays (copies, read-only),
state setters that check shapes, dtypes and NaNs, errors as Python exceptions, the GIL
released while Rust runs, and no panic crossing into Python."""

import threading
import time

import numpy as np
import pytest

import diffluid


@pytest.fixture
def sim(small_toml):
    return diffluid.Simulation(diffluid.Scene.from_toml(small_toml))


def test_step_report_is_a_dict(sim):
    r = sim.step()
    assert r["step"] == 1 and r["time"] == pytest.approx(0.01)
    assert r["cg_relative_residual"] <= 1e-10 and r["liquid_cells"] > 0
    assert r["bodies"][0]["name"] == "ball" and len(r["bodies"][0]["force"]) == 3
    assert set(r["stage_seconds"]) >= {"pressure", "advect_velocity"}
    assert sim.steps_taken == 1 and sim.time == pytest.approx(0.01)


def test_arrays_have_the_documented_shapes(sim):
    nx, ny, nz = sim.shape
    assert (nx, ny, nz) == (8, 8, 8)
    sim.step()
    assert sim.positions.shape == (1, 3) and sim.orientations.shape == (1, 4)
    assert sim.velocities.shape == (1, 3) and sim.angular_velocities.shape == (1, 3)
    f, t = sim.fluid_forces()
    assert f.shape == (1, 3) and t.shape == (1, 3)
    assert sim.pressure.shape == (nx, ny, nz) and sim.liquid_phi.shape == (nx, ny, nz)
    u, v, w = sim.velocity
    assert u.shape == (nx + 1, ny, nz) and v.shape == (nx, ny + 1, nz) and w.shape == (nx, ny, nz + 1)
    assert sim.velocity_flat().shape == (u.size + v.size + w.size,)
    p = sim.particles
    assert p.ndim == 2 and p.shape[1] == 3 and p.shape[0] > 1000
    for a in (sim.positions, sim.pressure, p, u):
        assert a.dtype == np.float64


def test_pressure_is_hydrostatic_and_indexed_ijk(sim):
    """p[i, j, k] at a cell centre deep in still water ≈ ρ g (depth), and grows downward."""
    sim.step()
    p = sim.pressure
    depth = 0.2 - 0.025  # the centre of cell j = 0 under 0.2 m of water
    assert p[0, 0, 0] == pytest.approx(1000 * 9.81 * depth, rel=0.05)
    assert p[0, 0, 0] > p[0, 1, 0] > p[0, 2, 0] > 0


def test_arrays_are_read_only_copies(sim):
    x = sim.positions
    with pytest.raises(ValueError, match="read-only"):
        x[0, 0] = 1.0
    y = np.array(x)
    y[0, 0] = 5.0
    assert sim.positions[0, 0] != 5.0


def test_the_ball_floats_and_the_water_holds_it(sim):
    for _ in range(3):
        sim.step()
    f, _ = sim.fluid_forces()
    assert f[0, 1] > 0, "buoyancy"


def test_set_body_state(sim):
    sim.set_body_state("ball", v=np.array([0.1, 0.0, 0.0]), q=np.array([2.0, 0.0, 0.0, 0.0]))
    s = sim.body_state(0)
    assert (s["v"] == [0.1, 0.0, 0.0]).all() and (s["q"] == [1.0, 0.0, 0.0, 0.0]).all()
    assert (s["x"] == [0.2, 0.22, 0.2]).all()


@pytest.mark.parametrize(
    "kwargs, error, message",
    [
        ({"v": np.zeros(2)}, ValueError, r"v: expected shape \(1, 3\) or \(3,\), got \[2\]"),
        ({"q": np.zeros((1, 3))}, ValueError, "q: expected shape"),
        ({"v": np.zeros(3, dtype=np.float32)}, TypeError, "from=float32, to=float64"),
        ({"v": np.zeros(3, dtype=np.int64)}, TypeError, "from=int64, to=float64"),
        ({"v": [0.0, 0.0, 0.0]}, TypeError, "ndarray"),
        ({"x": np.array([0.2, np.nan, 0.2])}, ValueError, "x: element 1 is NaN"),
        ({"w": np.array([np.inf, 0, 0])}, ValueError, "w: element 0 is inf"),
        ({"q": np.zeros(4)}, ValueError, "zero quaternion"),
        ({"x": np.array([0.2, 0.2, 5.0])}, ValueError, 'body "ball"'),
    ],
)
def test_bad_state_is_refused(sim, kwargs, error, message):
    before = sim.body_state(0)
    with pytest.raises(error, match=message):
        sim.set_body_state(0, **kwargs)
    after = sim.body_state(0)
    assert all((before[k] == after[k]).all() for k in before), "the state is unchanged"


def test_bad_body_references(sim):
    with pytest.raises(ValueError, match='no body named "cube"'):
        sim.body_state("cube")
    with pytest.raises(ValueError, match="out of range"):
        sim.body_state(3)
    with pytest.raises(TypeError):
        sim.body_state(1.5)


def test_velocity_flat_round_trip(sim):
    u = np.arange(sim.velocity_flat().size, dtype=np.float64) * 1e-4
    sim.set_velocity_flat(u)
    assert (sim.velocity_flat() == u).all()
    a, b, c = sim.velocity
    assert (np.concatenate([a.ravel(order="F"), b.ravel(order="F"), c.ravel(order="F")]) == u).all()
    with pytest.raises(ValueError, match="flat array"):
        sim.set_velocity_flat(u[:-1])
    u[3] = np.nan
    with pytest.raises(ValueError, match="element 3 is NaN"):
        sim.set_velocity_flat(u)


def test_advance_takes_cfl_steps(sim):
    reports = sim.advance(1 / 30)
    assert len(reports) >= 4 and sim.time == pytest.approx(1 / 30)
    with pytest.raises(ValueError, match="frame_dt: must be a positive number"):
        sim.advance(float("nan"))


def test_copies_are_independent(sim):
    other = sim.copy()
    sim.run(2)
    assert other.steps_taken == 0 and sim.steps_taken == 2


def test_non_convergence_is_a_solver_error(small_toml):
    text = small_toml.replace("tolerance = 1e-10", "tolerance = 1e-14\nmax_iterations = 1")
    sim = diffluid.Simulation(diffluid.Scene.from_toml(text))
    with pytest.raises(diffluid.SolverError, match="pressure solve did not converge at step 1"):
        sim.step()
    assert issubclass(diffluid.SolverError, diffluid.SimulationError)
    assert issubclass(diffluid.SolverError, RuntimeError)


def test_a_body_leaving_the_tank_is_a_simulation_error(small_toml):
    text = small_toml.replace("density = 500.0", "density = 500.0\nvelocity = [0.0, 0.0, 40.0]")
    sim = diffluid.Simulation(diffluid.Scene.from_toml(text))
    with pytest.raises(diffluid.SimulationError, match="left the tank"):
        sim.run(3)


def test_a_panic_becomes_an_internal_error():
    with pytest.raises(diffluid.InternalError, match="a deliberate panic"):
        diffluid._diffluid._panic_for_tests()
    # The interpreter is fine afterwards.
    assert diffluid.Scene.builtin("still_water").name == "still_water"


def test_steps_release_the_gil(box_scene):
    """While one thread is inside a long Rust call, another runs Python code. With the GIL
    held, the other thread could run only in the switch intervals (5 ms) just before the
    call starts and just after it returns, never in the middle half of a call this long."""
    sim = diffluid.Simulation(box_scene)
    span = []
    stamps = []

    def stepping():
        span.append(time.monotonic())
        sim.run(60)
        span.append(time.monotonic())

    t = threading.Thread(target=stepping)
    t.start()
    while t.is_alive():
        stamps.append(time.monotonic())
    t.join()
    start, end = span
    assert end - start > 0.1, "the call is long enough for the test to mean something"
    middle = [s for s in stamps if start + 0.25 * (end - start) < s < start + 0.75 * (end - start)]
    assert len(middle) > 100, len(middle)


def test_a_simulation_in_use_by_another_thread_says_so(box_scene):
    """A call from a second thread while the first steps the simulation (the GIL released)
    is refused with a message that says why and what to do (issue 39, item 13), never a bare
    "Already borrowed"; a copy taken before is free to use meanwhile, and the simulation is
    fine once the first call returns."""
    sim = diffluid.Simulation(box_scene)
    other = sim.copy()
    done = threading.Event()

    # 150 steps: under the soft φ_L (the default since 7 December) this box keeps its drift
    # and reaches the wall at step 213 (under the nearest particle's it swung back).
    def stepping():
        sim.run(150)
        done.set()

    t = threading.Thread(target=stepping)
    t.start()
    errors = []
    while not done.is_set() and len(errors) < 3:
        for call in (lambda: sim.time, lambda: sim.step(), lambda: sim.positions):
            try:
                call()
            except RuntimeError as e:
                errors.append(str(e))
    other.step()
    t.join()
    assert errors, "the second thread never found the simulation in use"
    for e in errors:
        assert "in use by another thread" in e and "copy()" in e, e
    assert sim.steps_taken == 150
    sim.step()


def test_external_force_pushes_the_body(sim):
    other = sim.copy()
    sim.set_external_force("ball", np.array([3.0, 0.0, 0.0]), np.zeros(3))
    sim.run(3)
    other.run(3)
    assert sim.velocities[0, 0] > other.velocities[0, 0] + 0.01
    with pytest.raises(ValueError, match="force: element 1 is NaN"):
        sim.set_external_force(0, np.array([0.0, np.nan, 0.0]))


# In a fresh interpreter: tune_memory sets malloc for the whole process.
TUNED_RUN = """
import json, sys
import diffluid
tuned = diffluid.tune_memory() if sys.argv[1] == "tune" else None
scene = diffluid.Scene.builtin("gradcheck_live")
scene.steps = 3
sim = diffluid.Simulation(scene)
report = sim.run()
print(json.dumps({
    "tuned": tuned,
    "x": sim.positions.tolist(),
    "v": sim.velocities.tolist(),
    "particles": sim.particles.tolist(),
    "volume": report["liquid_volume"],
}))
"""


def test_tune_memory_applies_on_glibc_and_changes_no_result():
    import json
    import platform
    import subprocess
    import sys

    def run(mode):
        out = subprocess.run(
            [sys.executable, "-c", TUNED_RUN, mode], check=True, capture_output=True, text=True
        )
        return json.loads(out.stdout)

    tuned, plain = run("tune"), run("plain")
    glibc = sys.platform == "linux" and platform.libc_ver()[0] == "glibc"
    assert tuned.pop("tuned") is glibc and plain.pop("tuned") is None
    # Every float as its shortest round-trip text: the same bits.
    assert tuned == plain
