"""N block-drop rollouts (50 steps each, frozen surface) on Ray against the same N run one
after another in one process.

The serial runs are timed in subprocesses with RAYON_NUM_THREADS=1 and =2 (diffluid's own
threads: with 2 a single rollout already uses both cores of this machine); the Ray runs use
one task per rollout, one thread each, on a local Ray instance with all cores (the instance
is started and warmed up before the clock starts). Prints medians over --repeats and checks
that Ray's results equal the serial ones.

    python bench/ray_speedup.py [--n 8] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

import numpy as np

SERIAL = """
import sys, time, pickle
import diffluid, diffluid.ray as dray
scene = diffluid.Scene.builtin("block_drop"); scene.freeze_surface = True
states = pickle.loads(bytes.fromhex(sys.argv[1]))
t = time.perf_counter()
out = [dray.rollout_one(scene, s) for s in states]
sys.stdout.write(pickle.dumps((time.perf_counter() - t, out)).hex())
"""


def serial(states, threads):
    import pickle

    env = dict(os.environ, RAYON_NUM_THREADS=str(threads))
    out = subprocess.run(
        [sys.executable, "-c", SERIAL, pickle.dumps(states).hex()],
        env=env, capture_output=True, text=True, check=True,
    ).stdout
    return pickle.loads(bytes.fromhex(out))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    import ray

    import diffluid
    import diffluid.ray as dray

    rng = np.random.default_rng(0)
    states = [{"v": rng.uniform([-2, -2, -1], [1, 0, 2])} for _ in range(args.n)]
    scene = diffluid.Scene.builtin("block_drop")
    scene.freeze_surface = True
    ray.init(include_dashboard=False, log_to_driver=False)
    dray.rollouts(scene, states[:2])  # start the workers

    times = {"serial, 1 thread": [], "serial, 2 threads": [], "ray": []}
    reference = None
    for _ in range(args.repeats):
        for threads in (1, 2):
            t, out = serial(states, threads)
            times[f"serial, {threads} thread{'s' if threads > 1 else ''}"].append(t)
            reference = out
        t = time.perf_counter()
        got = dray.rollouts(scene, states)
        times["ray"].append(time.perf_counter() - t)
        assert all(np.array_equal(a[k], b[k]) for a, b in zip(got, reference) for k in a)
    ray.shutdown()
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"{args.n} block-drop rollouts, {os.cpu_count()} cores, medians of {args.repeats}")
    for k, v in med.items():
        print(f"  {k:18s} {v:7.2f} s")
    print(f"  speedup of Ray over serial with 1 thread:  {med['serial, 1 thread'] / med['ray']:.2f}x")
    print(f"  speedup of Ray over serial with 2 threads: {med['serial, 2 threads'] / med['ray']:.2f}x")
    print("  Ray's results equal the serial ones")


if __name__ == "__main__":
    main()
