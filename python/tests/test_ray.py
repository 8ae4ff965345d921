"""diffluid.ray: N independent rollouts and gradients as Ray tasks on a local Ray instance
give exactly what the same calls give one after another in this process."""

import numpy as np
import pytest
import ray

import diffluid
import diffluid.ray as dray


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def starts(n):
    rng = np.random.default_rng(11)
    return [{"v": np.array([0.2, -0.3, 0.1]) + 0.1 * rng.standard_normal(3)} for _ in range(n)]


def test_rollouts_are_the_serial_ones(local_ray, box_scene):
    states = starts(3)
    got = dray.rollouts(box_scene, states)
    want = [dray.rollout_one(box_scene, s) for s in states]
    assert len(got) == 3
    for g, w in zip(got, want):
        assert set(g) == {"v", "w", "x", "q", "t"}
        for k in g:
            assert np.array_equal(g[k], w[k]), k
    assert not np.array_equal(got[0]["x"], got[1]["x"]), "different starts, different ends"


def test_gradients_are_the_serial_ones(local_ray, box_scene):
    states = starts(3)
    got = dray.value_and_grads(box_scene, states, params=["v", "w"], threads_per_task=2)
    want = [diffluid.value_and_grad(box_scene, params=["v", "w"], state=s) for s in states]
    for (lg, gg), (lw, gw) in zip(got, want):
        assert lg == lw
        assert set(gg) == {"v", "w"} and all(np.array_equal(gg[k], gw[k]) for k in gg)


def test_errors_come_back_as_the_same_exceptions(local_ray, box_scene):
    bad = [{"v": np.array([0.0, 0.0, np.nan])}]
    with pytest.raises(ValueError, match="element 2 is NaN"):
        dray.rollouts(box_scene, bad)
