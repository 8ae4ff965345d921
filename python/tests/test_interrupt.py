"""Ctrl-C stops a long call and keeps what it did (issue 39, item 11).

``Simulation.run(n)``, ``Simulation.advance(t)`` and ``diffluid.optimize`` release the GIL
while they step, so Python's own handler cannot raise KeyboardInterrupt until they return.
They check for signals between steps (and epochs): a SIGINT ends the call after the step
(or epoch) it arrived in, with KeyboardInterrupt; the simulation keeps every step it
finished (``steps_taken`` and ``time`` say how far it got, and it steps on from there), and
``optimize`` attaches what it would have returned so far (``err.result``: the history, the
last parameters, ``stopped`` saying it was interrupted).

Each case runs in a child interpreter that sends itself SIGINT half a second into a call
that would otherwise run for hours; the timeout only keeps a broken build from hanging the
suite.
"""

import json
import subprocess
import sys

import pytest

CHILD = r"""
import json, os, signal, sys, threading
import numpy as np
import diffluid

what, scene_text = sys.argv[1], sys.argv[2]
if what == "optimize":
    scene = diffluid.Scene.builtin("recover_box")
    scene.steps = 4
else:
    sim = diffluid.Simulation(diffluid.Scene.from_toml(scene_text))
threading.Timer(0.5, lambda: os.kill(os.getpid(), signal.SIGINT)).start()
try:
    if what == "run":
        sim.run(10**8)
    elif what == "advance":
        sim.advance(1e6)
    else:
        diffluid.optimize(scene, epochs=10**7)
except KeyboardInterrupt as e:
    if what == "optimize":
        r = e.result
        out = {"epochs": len(r["history"]), "stopped": r["stopped"],
               "last": r["history"][-1]["params"]["v"], "params": r["params"]["v"],
               "final_loss": r["final_loss"], "last_loss": r["history"][-1]["loss"]}
    else:
        steps, t = sim.steps_taken, sim.time
        # The simulation goes on from where it stopped.
        sim.step()
        out = {"steps": steps, "time": t, "dt": sim.dt, "after": sim.steps_taken}
    print(json.dumps(out))
    sys.exit(0)
sys.exit(3)
"""


def interrupted(what, scene_text=""):
    out = subprocess.run(
        [sys.executable, "-c", CHILD, what, scene_text],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
    return json.loads(out.stdout)


def still(small_toml):
    """The small tank without its ball: nothing ends its run but the interrupt."""
    head, tail = small_toml.split("[[body]]")
    return head + tail[tail.index("[solver]"):]


def test_ctrl_c_stops_run_and_keeps_the_steps_taken(small_toml):
    r = interrupted("run", still(small_toml))
    assert 0 < r["steps"] < 10**8
    assert r["time"] == pytest.approx(r["steps"] * r["dt"], rel=1e-12)
    assert r["after"] == r["steps"] + 1


def test_ctrl_c_stops_advance_and_keeps_the_steps_taken(small_toml):
    r = interrupted("advance", still(small_toml))
    assert 0 < r["steps"] and 0 < r["time"] < 1e6
    assert r["after"] == r["steps"] + 1


def test_ctrl_c_stops_optimize_and_attaches_the_history():
    r = interrupted("optimize")
    assert r["epochs"] >= 1
    assert "interrupted" in r["stopped"]
    # The last epoch's parameters and loss, as for a run stopped early.
    assert r["params"] == r["last"]
    assert r["final_loss"] == r["last_loss"]
