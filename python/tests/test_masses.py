"""Mass gradients from Python (issue 35): ∂L/∂m of each dynamic body, its inertia scaling
with its mass (its density changes, not its shape), from the same backward sweep as the
state and action gradients, against central differences of the same forward map.

- ``diffluid.torch.trajectory(..., masses=)`` and ``rollout(..., masses=)``: masses.grad;
- ``diffluid.torch.Stepper(..., masses=)``: the closed loop gives the open loop's mass
  gradient, its ``mass_gradient()`` the same, and ``reset(masses)`` starts the next
  episode with new masses;
- ``value_and_grad(params=["mass"])``, with ``Simulation.set_mass`` for the differences.

A body that is not dynamic (the kinematic paddle) has no mass the liquid feels: its entry is
ignored and its gradient is zero. The scene is test_control.py's (a kinematic paddle and a
floating ball, 4 actions of 5 steps)."""

import numpy as np
import pytest
import torch

import diffluid
from diffluid.torch import X, Stepper, body_states, initial_state, rollout, trajectory

from test_control import SPA, actions, control_sim, loss, state0


def masses_of(sim):
    return torch.tensor(np.array(sim.masses), dtype=torch.float64)


def trajectory_loss(sim, a, s0, m):
    return loss(trajectory(sim, a, s0, steps_per_action=SPA, masses=m))


def central(f, m0, i, rel=1e-6):
    h = rel * m0[i].item()
    p, q = m0.clone(), m0.clone()
    p[i] += h
    q[i] -= h
    with torch.no_grad():
        return (f(p).item() - f(q).item()) / (2 * h)


@pytest.mark.parametrize("frozen, rtol", [(True, 1e-6), (False, 1e-4)])
def test_trajectory_mass_gradient_matches_central_differences(frozen, rtol):
    """Measured: the ball's ∂L/∂m to 1.3e-10 relative with the surface frozen, 8.6e-10 with
    it moving (no cell changes between liquid and air at these steps); the kinematic
    paddle's is 0 and its entry changes nothing."""
    sim = control_sim(frozen=frozen)
    a, s0, m0 = actions(), state0(sim), masses_of(sim)
    m = m0.clone().requires_grad_()
    trajectory_loss(sim, a, s0, m).backward()
    f = lambda mm: trajectory_loss(sim, a, s0, mm)
    fd = central(f, m0, 1)
    print(f"ball mass: adjoint {m.grad[1].item():+.10e} fd {fd:+.10e} "
          f"rel {abs(m.grad[1].item() - fd) / abs(fd):.1e}")
    assert abs(m.grad[1].item() - fd) <= rtol * abs(fd)
    assert m.grad[0].item() == 0.0
    heavier = m0.clone()
    heavier[0] *= 3.0
    with torch.no_grad():
        assert f(heavier).item() == f(m0).item(), "a kinematic body's mass is ignored"


def test_masses_default_to_the_simulations_and_set_mass_changes_them():
    sim = control_sim()
    a = actions()
    with torch.no_grad():
        plain = loss(trajectory(sim, a, steps_per_action=SPA))
        same = loss(trajectory(sim, a, steps_per_action=SPA, masses=masses_of(sim)))
    assert plain.item() == same.item()
    m = np.array(sim.masses)
    heavier = sim.copy()
    heavier.set_mass("ball", 1.3 * m[1])
    assert heavier.masses[1] == 1.3 * m[1] and sim.masses[1] == m[1]
    m2 = masses_of(sim)
    m2[1] *= 1.3
    with torch.no_grad():
        a1 = loss(trajectory(heavier, a, steps_per_action=SPA)).item()
        a2 = loss(trajectory(sim, a, steps_per_action=SPA, masses=m2)).item()
    assert a1 == a2


def test_rollout_mass_gradient_matches_central_differences(box_scene):
    """The block of gradcheck_box, frozen surface: measured 2.9e-10 relative."""
    sim = diffluid.Simulation(box_scene)
    s = initial_state(sim)
    target = torch.tensor([0.4, 0.2, 0.4], dtype=torch.float64)

    def f(m):
        final = rollout(sim, s.v, s.w, s.x, s.q, masses=m)
        return ((final.x - target) ** 2).sum() + (final.v ** 2).sum()

    m0 = masses_of(sim)
    m = m0.clone().requires_grad_()
    f(m).backward()
    fd = central(f, m0, 0)
    print(f"box mass: adjoint {m.grad[0].item():+.10e} fd {fd:+.10e}")
    assert abs(m.grad[0].item() - fd) <= 1e-6 * abs(fd)
    # One body: a () tensor is its mass.
    m1 = m0[0].clone().requires_grad_()
    f(m1).backward()
    assert m1.grad.shape == () and m1.grad.item() == m.grad[0].item()


def test_value_and_grad_mass_matches_central_differences(box_scene):
    """The scene's loss on gradcheck_box: measured 2.6e-8 relative with a step of 1e-5·m
    (∂L/∂m is small there, -8.7e-5 per kg of a 6.48 kg box: the differences themselves are
    off by 1.6e-7 at a step of 1e-6·m, by 3.4e-7 at 1e-4·m)."""
    value, g = diffluid.value_and_grad(box_scene, params=["v", "mass"])
    assert set(g) == {"v", "mass"} and isinstance(g["mass"], float)
    m0 = diffluid.Simulation(box_scene).masses[0]
    h = 1e-5 * m0

    def at(m):
        sim = diffluid.Simulation(box_scene)
        sim.set_mass(0, m)
        return diffluid.value_and_grad(sim, params=[])[0]

    fd = (at(m0 + h) - at(m0 - h)) / (2 * h)
    print(f"value_and_grad mass: adjoint {g['mass']:+.10e} fd {fd:+.10e}")
    assert abs(g["mass"] - fd) <= 1e-6 * abs(fd)


@pytest.mark.parametrize("frozen", [True, False])
def test_closed_loop_mass_gradient_is_the_open_loops(frozen):
    """The Stepper with masses as an input of every step: masses.grad (what autograd sums
    over the actions) and mass_gradient() equal the trajectory's to 1e-12."""
    sim = control_sim(frozen=frozen)
    a, m0 = actions(), masses_of(sim)
    m0[1] *= 1.1
    m1 = m0.clone().requires_grad_()
    loss(trajectory(sim, a, steps_per_action=SPA, masses=m1)).backward()

    m2 = m0.clone().requires_grad_()
    stepper = Stepper(sim, steps_per_action=SPA, masses=m2)
    assert torch.equal(stepper.masses, m0)
    s = stepper.initial_state()
    out = [s]
    for k in range(4):
        s = stepper.step(a[k], s)
        out.append(s)
    loss(torch.stack(out)).backward()
    for g in (m2.grad, stepper.mass_gradient()):
        err = abs(g[1].item() - m1.grad[1].item()) / abs(m1.grad[1].item())
        print("closed against open loop, mass, relative:", err)
        assert err <= 1e-12 and g[0].item() == 0.0


def test_reset_starts_the_next_episode_with_new_masses():
    sim = control_sim()
    a = actions()
    stepper = Stepper(sim, steps_per_action=SPA)

    def episode():
        s = stepper.initial_state(requires_grad=True)
        for k in range(4):
            s = stepper.step(a[k], s)
        ((s[1, X] - 0.5) ** 2).sum().backward()
        return stepper.mass_gradient().clone()

    first = episode()
    with pytest.raises(ValueError, match="takes no more actions"):
        stepper.step(a[0], stepper.states())
    stepper.reset()
    assert stepper.steps_taken == 0
    assert torch.equal(episode(), first), "the same episode again"
    m = masses_of(sim)
    m[1] *= 0.8
    mt = m.clone().requires_grad_()
    stepper.reset(mt)
    assert torch.equal(stepper.masses, m)
    s = stepper.initial_state()
    for k in range(4):
        s = stepper.step(a[k], s)
    ((s[1, X] - 0.5) ** 2).sum().backward()
    mo = m.clone().requires_grad_()
    ((trajectory(sim, a, steps_per_action=SPA, masses=mo)[-1, 1, X] - 0.5) ** 2).sum().backward()
    assert abs(mt.grad[1].item() - mo.grad[1].item()) <= 1e-12 * abs(mo.grad[1].item())
    # A masses tensor changed in place without a reset is refused at the next step.
    stepper.reset(mt)
    with torch.no_grad():
        mt[1] *= 2.0
    with pytest.raises(ValueError, match=r"masses: changed since the run started"):
        stepper.step(a[0], stepper.initial_state())


def test_a_graph_from_before_reset_cannot_go_backward():
    sim = control_sim()
    stepper = Stepper(sim, steps_per_action=2)
    s = stepper.step(actions()[0], stepper.initial_state(requires_grad=True))
    stepper.reset()
    stepper.step(actions()[0], stepper.initial_state())
    with pytest.raises(ValueError, match="belongs to a run before reset"):
        s.sum().backward()


def test_numpy_halves_return_the_mass_gradient(box_scene):
    sim = control_sim()
    a = actions().numpy()
    run = diffluid.controlled_run(sim, a, steps_per_action=SPA)
    ga, g0, gm = run.backward(np.ones((5, 2, 13)))
    assert ga.shape == (4, 2, 6) and g0.shape == (2, 13) and gm.shape == (2,)
    assert gm[0] == 0.0 and gm[1] != 0.0
    box = diffluid.Simulation(box_scene)
    r = diffluid.rollout(box, box.velocities, box.angular_velocities, box.positions,
                         box.orientations)
    out = r.backward(np.ones((1, 3)), np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 4)))
    assert len(out) == 6 and out[5].shape == (1,) and out[5][0] != 0.0


def test_bad_masses_are_one_clear_error():
    sim = control_sim()
    a = actions()
    m = masses_of(sim)
    for bad, shown in ((float("nan"), "NaN"), (0.0, "0"), (-1.0, "-1"), (float("inf"), "inf")):
        b = m.clone()
        b[1] = bad
        with pytest.raises(ValueError, match=rf"masses(\[1\])?: .*{shown}"):
            trajectory(sim, a, masses=b)
        with pytest.raises(ValueError, match=rf"masses(\[1\])?: .*{shown}"):
            Stepper(sim, masses=b)
    with pytest.raises(ValueError, match=r"masses: expected shape \(2,\), got \[3\]"):
        trajectory(sim, a, masses=torch.ones(3, dtype=torch.float64))
    with pytest.raises(TypeError, match="dtype must be torch.float64"):
        trajectory(sim, a, masses=m.float())
    # A non-dynamic body's entry is still checked.
    b = m.clone()
    b[0] = -1.0
    with pytest.raises(ValueError, match=r"masses\[0\]: a mass must be a finite number > 0"):
        trajectory(sim, a, masses=b)
    with pytest.raises(ValueError, match="kg: a mass must be a finite number > 0, got 0"):
        sim.set_mass("ball", 0.0)
    with pytest.raises(ValueError, match='no body named "oar"'):
        sim.set_mass("oar", 1.0)
    assert sim.masses.flags.writeable is False
