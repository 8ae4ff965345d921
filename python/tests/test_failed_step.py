"""A step that fails leaves the simulation as it was (issue 39, item 12).

A step can fail after it has moved things: the marker particles (stage 0), the bodies'
velocities (the pressure solve) and poses (stage 6). SimulationError (a body that left the
tank) and SolverError (a solve that did not converge) roll the step back: the particles,
bodies, fields, time and step count are those before it, so trying again fails the same way
without moving anything again, and after a fix (here a sane velocity) the step is the one a
simulation that never failed takes. The Rust side's test is tests/failed_step.rs.
"""

import numpy as np
import pytest

import diffluid


def snapshot(sim):
    """Everything a caller can read of the state, as arrays."""
    return {
        "time": np.array(sim.time),
        "steps_taken": np.array(sim.steps_taken),
        "particles": sim.particles,
        "positions": sim.positions,
        "orientations": sim.orientations,
        "velocities": sim.velocities,
        "angular_velocities": sim.angular_velocities,
        "fluid_forces": np.concatenate(sim.fluid_forces()),
        "velocity": sim.velocity_flat(),
        "pressure": sim.pressure,
        "liquid_phi": sim.liquid_phi,
    }


def assert_same(a, b):
    for k in a:
        assert np.array_equal(a[k], b[k]), k


def test_a_body_leaving_the_tank_leaves_the_simulation_as_it_was(small_toml):
    sim = diffluid.Simulation(diffluid.Scene.from_toml(small_toml))
    sim.run(3)  # the ball bobbing, the liquid moving
    good = sim.copy()
    sim.set_body_state("ball", v=np.array([0.0, 0.0, 40.0]))
    before = snapshot(sim)
    for _ in range(2):
        with pytest.raises(diffluid.SimulationError, match="ball left the tank at step 4"):
            sim.step()
        assert_same(snapshot(sim), before)
    sim.set_body_state("ball", v=good.velocities[0].copy())
    sim.step()
    good.step()
    assert_same(snapshot(sim), snapshot(good))


def test_a_solve_that_does_not_converge_leaves_the_simulation_as_it_was(small_toml):
    text = small_toml.replace("tolerance = 1e-10", "tolerance = 1e-14\nmax_iterations = 1")
    sim = diffluid.Simulation(diffluid.Scene.from_toml(text))
    before = snapshot(sim)
    for _ in range(2):
        with pytest.raises(diffluid.SolverError, match="did not converge at step 1"):
            sim.step()
        assert_same(snapshot(sim), before)


def test_rollback_can_be_turned_off_for_its_memory(small_toml):
    """Off (what `diffluid run` does: it stops there), the failed step puts back the bodies,
    the time and the step count, but not the marker particles."""
    sim = diffluid.Simulation(diffluid.Scene.from_toml(small_toml))
    assert sim.rollback is True and sim.copy().rollback is True
    sim.run(3)
    sim.rollback = False
    assert sim.copy().rollback is False
    sim.set_body_state("ball", v=np.array([0.0, 0.0, 40.0]))
    x = sim.positions
    with pytest.raises(diffluid.SimulationError, match="left the tank"):
        sim.step()
    assert sim.steps_taken == 3 and np.array_equal(sim.positions, x)
