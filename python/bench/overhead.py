"""What Python and torch add to a block-drop epoch.

An epoch is 50 steps forward and the backward pass, with the liquid surface held fixed (as
``diffluid optimize block_drop`` runs it). Three ways, interleaved round by round so that a
change of load on the machine falls on all of them alike:

- rust:  ``diffluid.value_and_grad`` (one call into Rust: forward, loss, backward), timed
  around the call, and the time Rust itself reports for the forward and backward passes;
- torch: ``diffluid.torch.rollout`` forward, the loss in torch, ``loss.backward()``.

Prints the median of each, the overhead of torch over the Rust call from those medians, and
the median of the per-round ratios (each round's pair ran back to back, so a slow drift of the
machine's load cancels in it).

    python bench/overhead.py [--rounds 31]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import diffluid
from diffluid.torch import initial_state, rollout, target_loss


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=31)
    ap.add_argument("--scene", default="block_drop")
    args = ap.parse_args()
    scene = diffluid.Scene.load(args.scene)
    scene.freeze_surface = True
    sim = diffluid.Simulation(scene)
    loss = scene.loss
    s0 = initial_state(sim)

    def rust() -> float:
        value, _ = diffluid.value_and_grad(sim, loss, ["v", "w"])
        return value

    def torch_epoch() -> float:
        v = s0.v[0].clone().requires_grad_()
        w = s0.w[0].clone().requires_grad_()
        final = rollout(sim, v, w, s0.x[0], s0.q[0])
        value = target_loss(loss, sim, final)
        value.backward()
        return value.item()

    assert rust() == torch_epoch(), "both compute the same loss"
    times: dict[str, list[float]] = {"rust": [], "torch": []}
    for _ in range(args.rounds):
        for name, f in (("rust", rust), ("torch", torch_epoch)):
            t = time.perf_counter()
            f()
            times[name].append(time.perf_counter() - t)
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"scene {scene.name}, {scene.steps} steps, frozen surface, {args.rounds} rounds (medians)")
    print(f"rust  value_and_grad          {med['rust'] * 1e3:8.1f} ms")
    print(f"torch rollout + backward      {med['torch'] * 1e3:8.1f} ms")
    print(f"overhead (ratio of medians)   {100 * (med['torch'] / med['rust'] - 1):+8.2f} %")
    ratio = statistics.median(t / r for t, r in zip(times["torch"], times["rust"]))
    print(f"overhead (median of ratios)   {100 * (ratio - 1):+8.2f} %")


if __name__ == "__main__":
    main()
