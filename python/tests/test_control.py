"""Control through the water from torch: diffluid.torch.trajectory (a schedule of actions,
gradients on every action and on the initial state in one sweep) against central
differences of the same forward map; the closed-loop Stepper against the open-loop
trajectory on the same actions; a policy's parameter gradient through the closed loop; and
the bad inputs, each one clear exception before anything runs.

The scene is tests/control.rs's: a 0.8 x 0.6 x 0.8 tank (dx 0.05), a kinematic paddle (a
tilted box, at rest in the scene file, made kinematic with Simulation.set_kinematic) and a
floating ball, 4 actions of 5 steps."""

import numpy as np
import pytest
import torch

import diffluid
from diffluid.torch import Q, V, W, X, Stepper, body_states, step, trajectory

CONTROL = """
name = "control"
[domain]
size = [0.8, 0.6, 0.8]
dx = 0.05
[time]
dt = 0.01
steps = 20
[fluid]
density = 1000.0
gravity = [0.0, -9.81, 0.0]
[[liquid]]
shape = { kind = "box", min = [0.0, 0.0, 0.0], max = [0.8, 0.3, 0.8] }
[[body]]
name = "paddle"
shape = { kind = "cuboid", half_extents = [0.06, 0.12, 0.16] }
density = 1000.0
dynamic = false
position = [0.23, 0.27, 0.41]
axis_angle = { axis = [0.2, 1.0, 0.1], degrees = 10 }
[[body]]
name = "ball"
shape = { kind = "ball", radius = 0.08 }
density = 600.0
position = [0.47, 0.31, 0.38]
[solver]
tolerance = 1e-12
freeze_surface = FROZEN
"""

SPA = 5


def control_sim(frozen=True, kinematic=True):
    scene = diffluid.Scene.from_toml(CONTROL.replace("FROZEN", "true" if frozen else "false"))
    sim = diffluid.Simulation(scene)
    if kinematic:
        sim.set_kinematic("paddle")
    return sim


def actions():
    """tests/control.rs's schedule: the paddle's velocity and angular velocity, the ball's
    force and torque, for 4 actions."""
    a = torch.zeros(4, 2, 6, dtype=torch.float64)
    for k in range(4):
        a[k, 0] = torch.tensor([0.6 + 0.1 * k, 0.05, -0.1 * k, 0.0, 0.3 - 0.1 * k, 0.1])
        a[k, 1] = torch.tensor([1.5 - k, 0.5 * k, 0.8, 0.01 * k, -0.02, 0.015])
    return a


TARGET = torch.tensor([0.55, 0.3, 0.42], dtype=torch.float64)
Q_TARGET = torch.tensor([0.9, 0.1, 0.3, -0.2], dtype=torch.float64)
Q_TARGET = Q_TARGET / Q_TARGET.norm()


def loss(st):
    """A trajectory loss that reads every part of the states: a waypoint and a final target
    for the ball, its final velocity and orientation, its spin all along, the paddle's
    speed all along and its final pose."""
    ball, paddle = st[:, 1], st[:, 0]
    return (
        2.0 * ((ball[2, X] - TARGET) ** 2).sum()
        + ((ball[-1, X] - TARGET) ** 2).sum()
        + 0.3 * (ball[-1, V] ** 2).sum()
        + 0.5 * (1.0 - (ball[-1, Q] @ Q_TARGET) ** 2)
        + 0.1 * (ball[:, W] ** 2).sum()
        + 0.05 * (paddle[1:, V] ** 2).sum()
        + ((paddle[-1, X] - 0.3) ** 2).sum()
        + 0.2 * (1.0 - paddle[-1, Q][0] ** 2)
    )


def state0(sim):
    """The scene's initial state, with the ball's quaternion not of unit length (the
    gradient goes through the normalisation)."""
    s = body_states(sim)
    s[1, Q] *= 1.2
    return s


def adjoint_and_fd(sim, a0, s0, action_entries, state_entries, eps=1e-6):
    """(adjoint, central difference) pairs for the entries asked."""
    a = a0.clone().requires_grad_()
    s = s0.clone().requires_grad_()
    loss(trajectory(sim, a, s, steps_per_action=SPA)).backward()

    def value(a, s):
        with torch.no_grad():
            return loss(trajectory(sim, a, s, steps_per_action=SPA)).item()

    out = []
    for e in action_entries:
        p, m = a0.clone(), a0.clone()
        p[e] += eps
        m[e] -= eps
        out.append(("actions", e, a.grad[e].item(), (value(p, s0) - value(m, s0)) / (2 * eps)))
    for e in state_entries:
        p, m = s0.clone(), s0.clone()
        p[e] += eps
        m[e] -= eps
        out.append(("state0", e, s.grad[e].item(), (value(a0, p) - value(a0, m)) / (2 * eps)))
    return out


def worst(pairs, atol):
    errors = [abs(g - n) / max(abs(n), atol) for _, _, g, n in pairs]
    for (what, e, g, n), err in zip(pairs, errors):
        print(f"{what}{list(e)}: adjoint {g:+.10e} fd {n:+.10e} rel {err:.1e}")
    return max(errors)


# Action entries on both bodies (paddle velocity and spin, ball force and torque), at
# every action; state0 entries: the ball's whole row (x, q not unit, v, ω), the paddle's
# pose (its velocity is overwritten by the first action: its gradient is the loss's own, 0).
ACTION_ENTRIES = [(0, 0, 0), (1, 0, 2), (2, 0, 1), (3, 0, 4), (0, 1, 0), (1, 1, 3),
                  (2, 1, 1), (3, 1, 5), (0, 1, 4)]
STATE_ENTRIES = [(1, c) for c in range(13)] + [(0, 0), (0, 1), (0, 3), (0, 5), (0, 7)]


def test_gradients_match_central_differences_frozen_surface():
    """Measured: worst relative error 1.6e-7 (the ball's initial x), 2e-8 on the actions;
    the ball's q_w (along q: no gradient) is 0 against an fd of 2e-10."""
    sim = control_sim(frozen=True)
    pairs = adjoint_and_fd(sim, actions(), state0(sim), ACTION_ENTRIES, STATE_ENTRIES)
    assert worst(pairs, atol=1e-5) < 1e-4


def test_action_gradients_match_central_differences_live_surface():
    """With the surface moving the map is smooth only piecewise (cells change between
    liquid and air): measured 5.3e-5 worst, on the paddle's first velocity."""
    sim = control_sim(frozen=False)
    pairs = adjoint_and_fd(sim, actions(), state0(sim), ACTION_ENTRIES, [(1, c) for c in (0, 2, 7, 10)])
    assert worst(pairs, atol=1e-5) < 1e-3


def test_forward_is_stepping_with_the_actions_set():
    """states[k] is the simulation after k·steps_per_action steps, each step run with the
    kinematic paddle's velocity set to its action and the ball's external force to its."""
    sim = control_sim()
    a = actions()
    st = trajectory(sim, a, steps_per_action=SPA)
    assert st.shape == (5, 2, 13) and st.dtype == torch.float64
    assert sim.steps_taken == 0, "the simulation handed in is not changed"
    ref = sim.copy()
    assert torch.equal(st[0], body_states(ref))
    for k in range(4):
        for _ in range(SPA):
            p, b = a[k, 0].numpy(), a[k, 1].numpy()
            ref.set_body_state("paddle", v=p[:3].copy(), w=p[3:].copy())
            ref.set_external_force("ball", b[:3].copy(), b[3:].copy())
            ref.step()
        assert torch.equal(st[k + 1], body_states(ref))


@pytest.mark.parametrize("frozen", [True, False])
def test_closed_loop_gradients_are_the_open_loops(frozen):
    """The same actions stepped one at a time through a Stepper, the liquid's adjoint
    carried inside: the same states, loss and gradients as the whole trajectory's (measured:
    equal bit for bit)."""
    sim = control_sim(frozen=frozen)
    s0 = state0(sim)
    a1, s1 = actions().requires_grad_(), s0.clone().requires_grad_()
    st1 = trajectory(sim, a1, s1, steps_per_action=SPA)
    l1 = loss(st1)
    l1.backward()

    a2, s2 = actions().requires_grad_(), s0.clone().requires_grad_()
    stepper = Stepper(sim, steps_per_action=SPA)
    s, out = s2, [st1[0].detach()]  # states[0]: q normalised (the loss reads only its ω)
    for k in range(4):
        s = step(stepper, a2[k], s)
        out.append(s)
    st2 = torch.stack(out)
    assert torch.equal(st1[1:].detach(), st2[1:].detach())
    l2 = loss(st2)
    assert l2.item() == l1.item()
    l2.backward()
    for g1, g2 in ((a1.grad, a2.grad), (s1.grad, s2.grad)):
        err = ((g1 - g2).abs().max() / g1.abs().max()).item()
        print("closed against open loop, relative:", err)
        assert err <= 1e-12


def test_checkpointing_gives_the_same_gradients_bit_for_bit():
    sim = control_sim(frozen=False)
    grads = []
    for every in (None, 3, 7):
        a, s = actions().requires_grad_(), state0(sim).requires_grad_()
        loss(trajectory(sim, a, s, steps_per_action=SPA, checkpoint_every=every)).backward()
        grads.append((a.grad, s.grad))
    for g in grads[1:]:
        assert torch.equal(g[0], grads[0][0]) and torch.equal(g[1], grads[0][1])
    with pytest.raises(ValueError, match="checkpoint_every: must be at least 1"):
        trajectory(sim, actions(), checkpoint_every=0)


def test_policy_gradient_through_the_closed_loop():
    """A linear feedback policy (paddle velocity from the ball's offset) trained through the
    simulator: ∂L/∂gains against central differences of the closed loop."""
    sim = control_sim(frozen=True)

    def run(gains):
        stepper = Stepper(sim, steps_per_action=SPA)
        s = stepper.initial_state()
        for _ in range(4):
            d = s[1, X] - s[0, X]
            row = torch.stack([gains[0] * d[0], gains[2] * d[1], gains[1] * d[2]])
            a = torch.cat([row, torch.zeros(3, dtype=torch.float64)]).unsqueeze(0)
            a = torch.cat([a, torch.zeros(1, 6, dtype=torch.float64)])
            s = stepper.step(a, s)
        return ((s[1, X] - TARGET) ** 2).sum() + 0.1 * (s[0, V] ** 2).sum()

    g0 = torch.tensor([1.5, -0.7, 0.2], dtype=torch.float64)
    gains = g0.clone().requires_grad_()
    run(gains).backward()
    eps = 1e-6
    for i in range(3):
        p, m = g0.clone(), g0.clone()
        p[i] += eps
        m[i] -= eps
        with torch.no_grad():
            fd = (run(p) - run(m)).item() / (2 * eps)
        print(f"gain {i}: adjoint {gains.grad[i].item():+.10e} fd {fd:+.10e}")
        assert abs(gains.grad[i].item() - fd) <= 1e-4 * abs(fd) + 1e-9


def test_steps_the_loss_does_not_read_are_dropped():
    """A loss on the states after 2 of 4 actions: the gradients of a 2-action trajectory."""
    sim = control_sim()
    a1 = actions().requires_grad_()
    loss_2 = lambda st: ((st[-1, 1, X] - TARGET) ** 2).sum() + (st[-1, 0, V] ** 2).sum()
    loss_2(trajectory(sim, a1[:2], steps_per_action=SPA)).backward()
    a2 = actions().requires_grad_()
    stepper = Stepper(sim, steps_per_action=SPA)
    s, out = stepper.initial_state(), []
    for k in range(4):
        s = stepper.step(a2[k], s)
        out.append(s)
    loss_2(torch.stack(out[:2])).backward()
    assert torch.allclose(a1.grad[:2], a2.grad[:2], rtol=1e-12, atol=0)
    assert (a2.grad[2:] == 0).all()


def test_a_second_backward_is_an_error_and_a_stepper_goes_on_from_where_it_is():
    sim = control_sim()
    stepper = Stepper(sim, steps_per_action=2)
    s = stepper.initial_state(requires_grad=True)
    a = torch.zeros(2, 6, dtype=torch.float64, requires_grad=True)
    s1 = stepper.step(a, s)
    with pytest.raises(ValueError, match="not the states step 0 returned"):
        stepper.step(a, s1 + 1e-3)
    s2 = stepper.step(a, s1)
    total = s2[1, X].sum()
    total.backward(retain_graph=True)
    with pytest.raises(ValueError, match="already taken back"):
        total.backward()
    with pytest.raises(ValueError, match="takes no more actions"):
        stepper.step(a, s2)
    # Truncated backpropagation through time: a new stepper from where this one is.
    more = Stepper(stepper.simulation(), steps_per_action=2)
    assert torch.equal(more.initial_state(), s2.detach())
    more.step(a, more.initial_state())


def test_set_kinematic_and_motions():
    sim = control_sim(kinematic=False)
    assert sim.motions == ["fixed", "dynamic"]
    # A fixed paddle is not steered: its rows are ignored and get no gradient.
    a = actions().requires_grad_()
    st = trajectory(sim, a, steps_per_action=SPA)
    assert torch.equal(st[-1, 0], st[0, 0])
    st[-1, 1, X].sum().backward()
    assert (a.grad[:, 0] == 0).all() and (a.grad[:, 1] != 0).any()
    sim.set_kinematic("paddle")
    assert sim.motions == ["kinematic", "dynamic"]
    with pytest.raises(ValueError, match='no body named "oar"'):
        sim.set_kinematic("oar")


def test_bad_inputs_are_one_clear_error():
    sim = control_sim()
    a = actions()
    with pytest.raises(TypeError, match="dtype must be torch.float64"):
        trajectory(sim, a.float())
    with pytest.raises(TypeError, match="a torch.Tensor"):
        trajectory(sim, a.numpy())
    with pytest.raises(ValueError, match=r"actions: expected shape \(T ≥ 1, 2, 6\), got \[4, 2, 5\]"):
        trajectory(sim, a[:, :, :5])
    with pytest.raises(ValueError, match=r"actions: expected shape .* got \[2, 6\]"):
        trajectory(sim, a[0])
    with pytest.raises(ValueError, match=r"actions: expected shape .* got \[0, 2, 6\]"):
        trajectory(sim, a[:0])
    for bad, shown in ((float("nan"), "NaN"), (float("-inf"), "-inf")):
        b = a.clone()
        b[2, 1, 4] = bad
        with pytest.raises(ValueError, match=rf"actions\[2, 1, 4\] is {shown}, not a finite"):
            trajectory(sim, b)
    with pytest.raises(ValueError, match="steps_per_action: must be at least 1, got 0"):
        trajectory(sim, a, steps_per_action=0)
    with pytest.raises(ValueError, match=r"state0: expected shape \(2, 13\)"):
        trajectory(sim, a, torch.zeros(2, 7, dtype=torch.float64))
    with pytest.raises(ValueError, match='no body named "oar"'):
        trajectory(sim, a, bodies=["oar"])
    with pytest.raises(ValueError, match='no body named "oar"'):
        trajectory(sim, a, bodies="oar")
    with pytest.raises(ValueError, match="body index 5 out of range"):
        trajectory(sim, a, bodies=[5])
    fixed = control_sim(kinematic=False)
    with pytest.raises(ValueError, match="body paddle is fixed: it cannot be steered"):
        trajectory(fixed, a, bodies=["paddle", "ball"])
    with pytest.raises(ValueError, match='body "ball"'):
        s0 = body_states(sim)
        s0[1, 1] = 3.0  # out of the tank
        trajectory(sim, a, s0)
    with pytest.raises(ValueError, match="surface"):
        trajectory(sim, a, surface="melted")
    # The closed loop: the same checks.
    with pytest.raises(ValueError, match="steps_per_action: must be at least 1"):
        Stepper(sim, steps_per_action=0)
    with pytest.raises(ValueError, match="body paddle is fixed"):
        Stepper(fixed, bodies=["paddle"])
    stepper = Stepper(sim)
    s = stepper.initial_state()
    with pytest.raises(TypeError, match="dtype must be torch.float64"):
        stepper.step(a[0].float(), s)
    with pytest.raises(ValueError, match=r"action: expected shape \(2, 6\)"):
        stepper.step(a[:2], s)
    b = a[0].clone()
    b[0, 0] = float("nan")
    with pytest.raises(ValueError, match="action: element 0 is NaN"):
        stepper.step(b, s)
    assert stepper.steps_taken == 0, "nothing was run"
    # Weak coupling cannot be differentiated: GradientError at once.
    weak = diffluid.Simulation(diffluid.Scene.from_toml(
        CONTROL.replace("FROZEN", "true").replace("[solver]", '[solver]\ncoupling = "weak"')))
    with pytest.raises(diffluid.GradientError, match="monolithic"):
        trajectory(weak, a)
    with pytest.raises(diffluid.GradientError, match="monolithic"):
        Stepper(weak)
    # A scene with nothing to steer.
    still = control_sim(kinematic=False)
    with pytest.raises(ValueError, match="no body to steer"):
        Stepper(still, bodies=[])
