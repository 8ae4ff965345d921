"""diffluid.torch.rollout as a torch.autograd.Function: torch.autograd.gradcheck against
central differences, on the frozen-surface box and on the live-surface box, with respect to
the initial body state and the initial fluid velocity; the forward pass is the simulation's
own; the torch Adam example reaches diffluid's own Adam loss."""

import importlib.util
import pathlib

import numpy as np
import pytest
import torch

import diffluid
from diffluid.torch import initial_state, rollout, target_loss

EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples"


def leaves(sim):
    return tuple(t.clone().squeeze(0).requires_grad_() for t in initial_state(sim))


def test_forward_is_the_simulations_own(box_scene):
    sim = diffluid.Simulation(box_scene)
    out = rollout(sim, *leaves(sim))
    ref = sim.copy()
    ref.run()
    assert (out.x.detach().numpy() == ref.positions[0]).all()
    assert (out.q.detach().numpy() == ref.orientations[0]).all()
    assert (out.v.detach().numpy() == ref.velocities[0]).all()
    assert sim.steps_taken == 0, "the simulation handed in is not changed"


def test_loss_and_gradient_are_value_and_grads(box_scene):
    sim = diffluid.Simulation(box_scene)
    v, w, x, q = leaves(sim)
    loss = target_loss(box_scene.loss, sim, rollout(sim, v, w, x, q))
    loss.backward()
    value, g = diffluid.value_and_grad(box_scene, params=["v", "w", "x"])
    assert abs(loss.item() - value) <= 1e-15 * value
    for name, t in (("v", v), ("w", w), ("x", x)):
        np.testing.assert_allclose(t.grad.numpy(), g[name], rtol=1e-12, atol=1e-15)


# torch's defaults (eps 1e-6, atol 1e-5, rtol 1e-3). Measured on these maps: the largest
# |analytic − numerical| over the Jacobian is 3.4e-6 (relative 4.6e-6) for the frozen box and
# 1.2e-6 (relative 3.9e-6) for the live box; what remains is the pressure solve's tolerance
# (1e-12) divided by eps.
TOL = dict(eps=1e-6, atol=1e-5, rtol=1e-3)
# The live box at eps 1e-7. With the smooth defaults (blended liquid-air faces and phi_L
# ramped into the bodies, since 6 December 2026) its map has a kink within 1e-6 of this
# start along x1 and x2: central differences at 1e-6 straddle it (up to 1.5e-3 off in the
# Jacobian's position columns; `diffluid gradcheck` 2.9e-5 and 3.2e-5 relative), while at
# 1e-7 they agree with the adjoint to 3e-9 and 8e-9, as at either step without the blend
# or without the ramp.
LIVE_TOL = dict(TOL, eps=1e-7)


def test_gradcheck_frozen_surface(box_scene):
    sim = diffluid.Simulation(box_scene)
    f = lambda v, w, x, q: tuple(rollout(sim, v, w, x, q))
    assert torch.autograd.gradcheck(f, leaves(sim), **TOL)


def test_gradcheck_live_surface(live_scene):
    sim = diffluid.Simulation(live_scene)
    f = lambda v, w, x, q: tuple(rollout(sim, v, w, x, q))
    assert torch.autograd.gradcheck(f, leaves(sim), **LIVE_TOL)


def test_gradcheck_through_a_quaternion_that_is_not_unit(box_scene):
    sim = diffluid.Simulation(box_scene)
    v, w, x, q = leaves(sim)
    q = (1.3 * q).detach().requires_grad_()
    f = lambda q: tuple(rollout(sim, v.detach(), w.detach(), x.detach(), q))
    assert torch.autograd.gradcheck(f, (q,), **TOL)
    # The gradient has no component along q.
    rollout(sim, v, w, x, q).x.sum().backward()
    assert abs(float(q.grad @ q.detach())) < 1e-12 * float(q.grad.norm())


def test_gradcheck_fluid_velocity(box_scene):
    """With respect to the initial fluid velocity (thousands of inputs): gradcheck's fast
    mode, which checks uᵀ·J·v for random u, v against central differences."""
    sim = diffluid.Simulation(box_scene)
    v, w, x, q = (t.detach() for t in leaves(sim))
    u0 = torch.tensor(np.random.default_rng(1).standard_normal(sim.velocity_flat().size) * 0.01,
                      dtype=torch.float64, requires_grad=True)
    f = lambda u: tuple(rollout(sim, v, w, x, q, u))
    assert torch.autograd.gradcheck(f, (u0,), fast_mode=True, **TOL)


TWO_BALLS = """
name = "two_balls"
[domain]
size = [0.6, 0.4, 0.4]
dx = 0.05
[time]
dt = 0.01
steps = 4
[fluid]
density = 1000.0
gravity = [0.0, -9.81, 0.0]
[[liquid]]
shape = { kind = "box", min = [0.0, 0.0, 0.0], max = [0.6, 0.2, 0.4] }
[[body]]
name = "a"
shape = { kind = "ball", radius = 0.06 }
density = 500.0
position = [0.17, 0.2, 0.2]
velocity = [0.1, 0.0, 0.05]
[[body]]
name = "b"
shape = { kind = "ball", radius = 0.07 }
density = 700.0
position = [0.4237, 0.2131, 0.1873]
angular_velocity = [0.3, 0.2, -0.4]
[solver]
tolerance = 1e-12
freeze_surface = true
"""


def test_gradcheck_two_bodies():
    """Two balls (a box straddling the surface here is not used: diffluid's own gradcheck
    fails on an axis-aligned cuboid there, in its position gradient, whatever the binding)."""
    sim = diffluid.Simulation(diffluid.Scene.from_toml(TWO_BALLS))
    args = tuple(t.clone().requires_grad_() for t in initial_state(sim))
    assert args[0].shape == (2, 3) and args[3].shape == (2, 4)
    f = lambda v, w, x, q: tuple(rollout(sim, v, w, x, q))
    assert torch.autograd.gradcheck(f, args, **TOL)


def test_backward_twice_is_the_same(box_scene):
    sim = diffluid.Simulation(box_scene)
    v, w, x, q = leaves(sim)
    out = rollout(sim, v, w, x, q)
    loss = (out.x ** 2).sum() + out.q[1]
    (g1,) = torch.autograd.grad(loss, v, retain_graph=True)
    (g2,) = torch.autograd.grad(loss, v)
    assert torch.equal(g1, g2)


def test_checkpointing_gives_the_same_gradient_bit_for_bit(live_scene):
    live_scene.steps = 7
    sim = diffluid.Simulation(live_scene)
    grads = []
    for every in (None, 3, 1):
        v, w, x, q = leaves(sim)
        out = rollout(sim, v, w, x, q, checkpoint_every=every)
        ((out.x - 0.3) ** 2).sum().add(out.q[2] + out.w.sum()).backward()
        grads.append([t.grad for t in (v, w, x, q)])
    for g in grads[1:]:
        assert all(torch.equal(a, b) for a, b in zip(grads[0], g))
    with pytest.raises(ValueError, match="checkpoint_every"):
        rollout(sim, *leaves(sim), checkpoint_every=0)


def test_bad_inputs(box_scene):
    sim = diffluid.Simulation(box_scene)
    v, w, x, q = (t.detach() for t in leaves(sim))
    with pytest.raises(TypeError, match="dtype must be torch.float64"):
        rollout(sim, v.float(), w, x, q)
    with pytest.raises(TypeError, match="a torch.Tensor"):
        rollout(sim, [0.0, 0.0, 0.0], w, x, q)
    with pytest.raises(ValueError, match=r"x: expected shape \(1, 3\)"):
        rollout(sim, v, w, torch.zeros(2, dtype=torch.float64), q)
    with pytest.raises(ValueError, match="element 0 is NaN"):
        rollout(sim, torch.tensor([float("nan"), 0, 0], dtype=torch.float64), w, x, q)
    with pytest.raises(ValueError, match="zero quaternion"):
        rollout(sim, v, w, x, torch.zeros(4, dtype=torch.float64))
    with pytest.raises(ValueError, match="flat array"):
        rollout(sim, v, w, x, q, torch.zeros(5, dtype=torch.float64))
    with pytest.raises(ValueError, match='body "box"'):
        rollout(sim, v, w, torch.tensor([0.4, 0.3, 3.0], dtype=torch.float64), q)
    two = diffluid.Simulation(diffluid.Scene.from_toml(TWO_BALLS))
    with pytest.raises(ValueError, match="has 2"):
        rollout(two, v, w, x, q)


def test_gradients_go_through_contact_unless_refused(small_toml):
    scene = diffluid.Scene.from_toml(small_toml.replace(
        "[solver]", "[contact]\nenabled = true\n[solver]").replace(
        "position = [0.2, 0.22, 0.2]", "position = [0.2, 0.065, 0.2]\nvelocity = [0, -1, 0]"))
    sim = diffluid.Simulation(scene)
    v, w, x, q = (t.detach().squeeze(0) for t in initial_state(sim))
    with pytest.raises(diffluid.GradientError, match="contact"):
        rollout(sim, v, w, x, q, through_contact=False)
    v.requires_grad_(True)
    final = rollout(sim, v, w, x, q)
    final.x.sum().backward()
    # The default goes through rapier's step (checked against central differences in
    # tests/gradients/adjoint.rs).
    assert torch.isfinite(v.grad).all() and v.grad.abs().sum() > 0


def test_torch_adam_example_reaches_rusts_adam_loss():
    spec = importlib.util.spec_from_file_location("torch_adam", EXAMPLES / "torch_adam.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    scene = diffluid.Scene.from_file(EXAMPLES / "block_drop_adam.toml")
    epochs = 6
    final, history = mod.torch_adam(scene.__copy__(), epochs)
    rust = diffluid.optimize(scene, epochs=epochs)
    assert len(history) == epochs and history[-1] < history[0]
    for a, b in zip(history, (h["loss"] for h in rust["history"])):
        assert abs(a - b) <= 1e-9 * abs(b)
    assert abs(final - rust["final_loss"]) <= 1e-9 * abs(rust["final_loss"])
