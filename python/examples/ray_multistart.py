"""A multi-start search on Ray: the block drop's loss and gradient from N initial velocities,
one Ray task each, then a few steps of gradient descent from the best start, its gradients
again on Ray.

    python examples/ray_multistart.py [--starts 8] [--address auto]

Without --address the script starts a local Ray instance (``ray.init()``); with
``--address auto`` (on a node of a Ray cluster) or ``--address ray://head:10001`` it runs the
same tasks on the cluster (so does ``RAY_ADDRESS=... python examples/ray_multistart.py``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import ray

import diffluid
import diffluid.ray as dray


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--starts", type=int, default=8)
    ap.add_argument("--address", default=None, help="a Ray cluster (default: a local instance)")
    args = ap.parse_args()
    ray.init(address=args.address)

    scene = diffluid.Scene.builtin("block_drop")
    scene.freeze_surface = True  # as `diffluid optimize block_drop` runs its epochs
    rng = np.random.default_rng(0)
    starts = [{"v": rng.uniform([-2, -2, -1], [1, 0, 2])} for _ in range(args.starts)]

    t = time.perf_counter()
    results = dray.value_and_grads(scene, starts, params=["v"])
    print(f"{len(starts)} starts in {time.perf_counter() - t:.1f} s")
    for s, (loss, g) in zip(starts, results):
        print(f"  v0 = {np.array2string(s['v'], precision=3)}  loss {loss:.4e}  |∂L/∂v| {np.linalg.norm(g['v']):.3e}")
    best = min(range(len(starts)), key=lambda i: results[i][0])
    v = starts[best]["v"]
    for it in range(5):
        # Four step sizes at once: one Ray task each.
        rates = [0.5, 1.0, 2.0, 4.0]
        loss, g = dray.value_and_grads(scene, [{"v": v}], params=["v"])[0]
        trials = [{"v": v - r * g["v"]} for r in rates]
        losses = [l for l, _ in dray.value_and_grads(scene, trials, params=["v"])]
        k = int(np.argmin(losses))
        print(f"iteration {it}: loss {loss:.4e} -> {losses[k]:.4e} (step {rates[k]})")
        if losses[k] >= loss:
            break
        v = trials[k]["v"]
    print("best initial velocity", np.array2string(v, precision=4))
    ray.shutdown()


if __name__ == "__main__":
    main()
