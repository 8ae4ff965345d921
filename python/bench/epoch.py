"""A block-drop epoch (50 steps forward and the backward pass, frozen surface) N times, as the
Rust call or through diffluid.torch, after one of each as a warm-up; `none` runs only the
warm-up. For overhead_instructions.sh."""

import sys

import torch

import diffluid
from diffluid.torch import initial_state, rollout, target_loss

mode, n = sys.argv[1], int(sys.argv[2])
scene = diffluid.Scene.builtin("block_drop")
scene.freeze_surface = True
sim = diffluid.Simulation(scene)
loss = scene.loss
s0 = initial_state(sim)


def rust() -> None:
    diffluid.value_and_grad(sim, loss, ["v", "w"])


def torch_epoch() -> None:
    v = s0.v[0].clone().requires_grad_()
    w = s0.w[0].clone().requires_grad_()
    target_loss(loss, sim, rollout(sim, v, w, s0.x[0], s0.q[0])).backward()


rust()
torch_epoch()
for _ in range(n if mode != "none" else 0):
    rust() if mode == "rust" else torch_epoch()
