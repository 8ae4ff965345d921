"""value_and_grad against central differences of the same forward map; its options and
errors; the Rust optimiser seen from Python."""

import pickle

import numpy as np
import pytest

import diffluid


def loss_at(scene, state, loss=None):
    sim = diffluid.Simulation(scene)
    sim.set_body_state(0, **state)
    sim.run()
    return (loss or scene.loss).value(sim)


def test_gradient_matches_central_differences(box_scene):
    """Directional derivatives along v, w, x of the frozen-surface map: |AD − FD| within
    1e-6 relative (measured ~1e-8; the solve's 1e-12 tolerance bounds the FD's accuracy)."""
    value, g = diffluid.value_and_grad(box_scene, params=["v", "w", "x"])
    sim = diffluid.Simulation(box_scene)
    s0 = sim.body_state(0)
    assert value == pytest.approx(loss_at(box_scene, {}), rel=0, abs=0)
    rng = np.random.default_rng(7)
    h = 1e-6
    for p in ("v", "w", "x"):
        d = rng.standard_normal(3)
        plus = loss_at(box_scene, {p: s0[p] + h * d})
        minus = loss_at(box_scene, {p: s0[p] - h * d})
        fd = (plus - minus) / (2 * h)
        ad = g[p] @ d
        assert abs(ad - fd) <= 1e-10 + 1e-6 * abs(fd), (p, ad, fd)


def test_orientation_gradient_is_the_tangent_gradient(box_scene):
    """∂L/∂θ for q → exp(θ)·q, against central differences along a rotation."""
    _, g = diffluid.value_and_grad(box_scene, params=["q"])
    q0 = diffluid.Simulation(box_scene).body_state(0)["q"]
    d = np.array([0.3, -0.5, 0.8])

    def turned(s):
        a = s * d
        ang = np.linalg.norm(a)
        r = np.concatenate([[np.cos(ang / 2)], np.sin(ang / 2) * a / ang])
        w1, v1, w2, v2 = r[0], r[1:], q0[0], q0[1:]
        return np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])

    h = 1e-6
    fd = (loss_at(box_scene, {"q": turned(h)}) - loss_at(box_scene, {"q": turned(-h)})) / (2 * h)
    assert abs(g["q"] @ d - fd) <= 1e-10 + 1e-6 * abs(fd)


def test_fluid_velocity_gradient(box_scene):
    _, g = diffluid.value_and_grad(box_scene, params=["u"])
    sim = diffluid.Simulation(box_scene)
    gu = np.concatenate([a.ravel(order="F") for a in g["u"]])
    assert [a.shape for a in g["u"]] == [a.shape for a in sim.velocity]
    rng = np.random.default_rng(3)
    d = rng.standard_normal(gu.size) * 1e-2
    h = 1e-5

    def at(s):
        t = diffluid.Simulation(box_scene)
        t.set_velocity_flat(s * d)
        t.run()
        return box_scene.loss.value(t)

    fd = (at(h) - at(-h)) / (2 * h)
    assert abs(gu @ d - fd) <= 1e-10 + 1e-5 * abs(fd), (gu @ d, fd)


def test_checkpointing_gives_the_same_gradient_bit_for_bit(box_scene):
    a = diffluid.value_and_grad(box_scene)
    b = diffluid.value_and_grad(box_scene, checkpoint_every=2)
    assert a[0] == b[0] and all((a[1][k] == b[1][k]).all() for k in a[1])


def test_simulation_state_and_state_override(box_scene):
    sim = diffluid.Simulation(box_scene)
    sim.set_body_state(0, v=np.array([0.1, -0.2, 0.0]))
    a = diffluid.value_and_grad(sim)
    b = diffluid.value_and_grad(box_scene, state={"v": np.array([0.1, -0.2, 0.0])})
    assert a[0] == b[0] and (a[1]["v"] == b[1]["v"]).all()


def test_own_loss(box_scene):
    loss = diffluid.BodyTargetLoss("box", position=([0.4, 0.2, 0.4], 2.0), velocity=[0, 0, 0])
    value, g = diffluid.value_and_grad(box_scene, loss, ["x"])
    assert value == loss_at(box_scene, {}, loss)
    assert set(g) == {"x"}
    assert pickle.loads(pickle.dumps(loss)).position == loss.position


@pytest.mark.parametrize(
    "kwargs, error, message",
    [
        ({"params": ["z"]}, ValueError, 'unknown "z"'),
        ({"surface": "wet"}, ValueError, "surface"),
        ({"mode": "exact"}, ValueError, "mode"),
        ({"steps": 0}, ValueError, "steps"),
        ({"checkpoint_every": 0}, ValueError, "checkpoint_every"),
        ({"loss": diffluid.BodyTargetLoss("ghost", position=[0, 0, 0])}, ValueError, "ghost"),
        ({"state": {"v": np.array([np.nan, 0, 0])}}, ValueError, "NaN"),
        ({"state": {"v": np.zeros(2)}}, ValueError, "shape"),
    ],
)
def test_bad_arguments(box_scene, kwargs, error, message):
    with pytest.raises(error, match=message):
        diffluid.value_and_grad(box_scene, **kwargs)


def test_no_loss_is_a_value_error():
    with pytest.raises(ValueError, match=r"no \[loss\] section"):
        diffluid.value_and_grad(diffluid.Scene.builtin("still_water"), steps=1)


def test_bad_loss_targets():
    with pytest.raises(ValueError, match="weight"):
        diffluid.BodyTargetLoss(0, position=([0, 0, 0], -1.0))
    with pytest.raises(ValueError, match="NaN"):
        diffluid.BodyTargetLoss(0, velocity=[0, float("nan"), 0])
    with pytest.raises(TypeError):
        diffluid.BodyTargetLoss(0, position=[0, 0])


def test_weak_coupling_is_a_gradient_error(small_toml):
    scene = diffluid.Scene.from_toml(small_toml.replace("[solver]", '[solver]\ncoupling = "weak"'))
    loss = diffluid.BodyTargetLoss(0, position=[0.2, 0.2, 0.2])
    with pytest.raises(diffluid.GradientError, match="monolithic"):
        diffluid.value_and_grad(scene, loss)


def test_optimize_runs_the_rust_optimiser(box_scene):
    text = box_scene.to_json()
    s = diffluid.Scene.builtin("recover_box")
    s.steps = 4
    out = diffluid.optimize(s, epochs=3)
    assert [h["epoch"] for h in out["history"]] == [0, 1, 2]
    assert out["stopped"] is None and out["evaluations"] == 3
    assert out["final_loss"] < out["history"][0]["loss"]
    assert set(out["params"]) == {"v", "w", "x", "q"}
    assert box_scene.to_json() == text
    with pytest.raises(ValueError, match=r"no \[optimize\] section"):
        diffluid.optimize(box_scene)


def test_the_cli_rules_hold_in_python(box_scene):
    """What the CLI refuses, Python refuses with its words (issue 39, item 13): no epochs
    (`--epochs 0`), a loss with no term (the scene's `[loss]` without position, orientation
    or velocity)."""
    s = diffluid.Scene.builtin("recover_box")
    for bad in (0, -2):
        with pytest.raises(ValueError, match=f"epochs: must be at least 1, got {bad}"):
            diffluid.optimize(s, epochs=bad)
    with pytest.raises(ValueError, match="give at least one of position, orientation, velocity"):
        diffluid.BodyTargetLoss(0)
    with pytest.raises(ValueError, match="give at least one of position, orientation, velocity"):
        diffluid.BodyTargetLoss("box", position=None)


def test_smoothed_gradient_is_the_mean_of_perturbed_gradients(box_scene):
    """smoothing: the loss is the mean of the perturbed runs' losses, the gradient the mean of
    their exact gradients, each with its standard error; with a small σ it is within a few
    standard errors (and 1e-3 relative) of the exact gradient on this smooth map; bad keys,
    odd sample counts and "u" are ValueErrors naming them."""
    exact_value, exact = diffluid.value_and_grad(box_scene, params=["v", "x"])
    how = {"samples": 4, "sigma": {"v": 1e-4, "x": 1e-5}, "seed": 3}
    value, g = diffluid.value_and_grad(box_scene, params=["v", "x"], smoothing=how)
    se = g["standard_error"]
    assert set(se) == {"v", "x"}
    for p in ("v", "x"):
        assert se[p].shape == (3,) and np.all(se[p] >= 0.0)
        gap = np.abs(g[p] - exact[p])
        assert np.all(gap <= 1e-3 * np.abs(exact[p]) + 4 * se[p] + 1e-12), (p, g[p], exact[p])
    assert value == pytest.approx(exact_value, rel=1e-3)
    again = diffluid.value_and_grad(box_scene, params=["v", "x"], smoothing=how)
    assert again[0] == value and np.array_equal(again[1]["v"], g["v"])
    for bad, word in [
        ({"samples": 3, "sigma": {"v": 1e-3}}, "samples"),
        ({"samples": 4, "sigma": {"speed": 1e-3}}, "speed"),
        ({"runs": 4}, "runs"),
    ]:
        with pytest.raises(ValueError, match=word):
            diffluid.value_and_grad(box_scene, params=["v"], smoothing=bad)
    with pytest.raises(ValueError, match='"u"'):
        diffluid.value_and_grad(box_scene, params=["u"], smoothing=how)


def test_smoothed_gradient_from_the_losses_alone(box_scene):
    """smoothing's estimator "values": forward runs only, (L+ - L-)·ξ/(2σ) per pair; on this
    smooth map within four standard errors of the exact gradient; a parameter it does not
    perturb (σ = 0, or the mass) and an unknown estimator are ValueErrors."""
    _, exact = diffluid.value_and_grad(box_scene, params=["v"])
    how = {"samples": 32, "sigma": {"v": 1e-4}, "seed": 3, "estimator": "values"}
    value, g = diffluid.value_and_grad(box_scene, params=["v"], smoothing=how)
    se = g["standard_error"]["v"]
    assert np.all(se > 0.0)
    assert np.all(np.abs(g["v"] - exact["v"]) <= 4 * se), (g["v"], se, exact["v"])
    for params in (["v", "x"], ["mass"]):
        with pytest.raises(ValueError, match="no gradient from the losses alone"):
            diffluid.value_and_grad(box_scene, params=params, smoothing=how)
    with pytest.raises(ValueError, match="gradients, values"):
        diffluid.value_and_grad(
            box_scene, params=["v"], smoothing={"sigma": {"v": 1e-3}, "estimator": "guess"}
        )
