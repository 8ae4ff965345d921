"""The block drop optimised with torch.optim.Adam through diffluid.torch.rollout.

The same problem as ``diffluid optimize python/examples/block_drop_adam.toml``: find the
block's initial velocity v and angular velocity ω (the scene's ``optimize.params``) that
bring it to the target at the last step, with Adam at the scene's learning rate and betas,
the liquid surface held fixed during the epochs (``optimize.freeze_surface``). Each epoch is
one forward run (50 steps) and one backward pass through diffluid's adjoint; torch only sees
the final state. The script then runs diffluid's own Adam on the same scene
(:func:`diffluid.optimize`, what the CLI runs) and prints both final losses.

    python examples/torch_adam.py [--epochs N]

Adam's ε: diffluid uses 1e-12 in ``m̂ / (√v̂ + ε)``; torch.optim.Adam is given the same.
"""

from __future__ import annotations

import argparse
import pathlib
import time

import torch

import diffluid
from diffluid.torch import initial_state, rollout, target_loss

SCENE = pathlib.Path(__file__).with_name("block_drop_adam.toml")


def torch_adam(scene: diffluid.Scene, epochs: int) -> tuple[float, list[float]]:
    """Adam in torch over the scene's optimised parameters; the final loss (one more forward
    run at the last parameters, as diffluid's optimiser reports it) and the loss per epoch."""
    spec = scene.optimize_spec
    assert spec["optimizer"]["kind"] == "adam", "the scene's optimiser is Adam"
    if "q" in spec["params"]:
        # diffluid steps q on the rotation group (q <- exp(-s)·q), not additively.
        raise NotImplementedError("this example optimises v, w and x")
    scene.freeze_surface = spec["freeze_surface"]
    sim = diffluid.Simulation(scene)
    loss_spec = scene.loss
    body = loss_spec.body_index(sim)
    s0 = initial_state(sim)
    state = {k: getattr(s0, k)[body].clone() for k in ("v", "w", "x", "q")}
    params = [state[p].requires_grad_() for p in spec["params"]]
    opt = spec["optimizer"]
    adam = torch.optim.Adam(
        params, lr=opt["learning_rate"], betas=(opt["beta1"], opt["beta2"]), eps=1e-12
    )
    history = []
    for _ in range(epochs):
        adam.zero_grad()
        loss = target_loss(loss_spec, sim, rollout(sim, **state))
        loss.backward()
        history.append(loss.item())
        adam.step()
    with torch.no_grad():
        final = target_loss(loss_spec, sim, rollout(sim, **state)).item()
    return final, history


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=None, help="default: the scene's")
    args = ap.parse_args()
    scene = diffluid.Scene.from_file(SCENE)
    epochs = args.epochs or scene.optimize_spec["epochs"]

    t = time.perf_counter()
    final, history = torch_adam(scene.__copy__(), epochs)
    t_torch = time.perf_counter() - t
    for e, l in enumerate(history):
        print(f"epoch {e:3d}  loss {l:.12e}")

    t = time.perf_counter()
    rust = diffluid.optimize(scene, epochs=epochs)
    t_rust = time.perf_counter() - t
    rel = abs(final - rust["final_loss"]) / abs(rust["final_loss"])
    print(f"torch.optim.Adam final loss   {final:.15e}  ({t_torch:.1f} s)")
    print(f"diffluid optimize (Adam)      {rust['final_loss']:.15e}  ({t_rust:.1f} s)")
    print(f"relative difference           {rel:.2e}")


if __name__ == "__main__":
    main()
