"""Prediction benchmark: a batch of imagined futures of the humanoid, on each backend, in one run.

The world: `scenarios/humanoid_stand.yaml` (the humanoid, its servo, encoders, force sensors, IMU and
ZMP: 8 modules besides the core). Printed, each figure measured in this run:

1. one world stepping alone (`world.tick`, history on): ticks per second (the baseline);
2. a Batch of 32 branches x 500 ticks, each branch with its own friction and servo offsets, recording
   the pelvis position and the ZMP: ticks per second on ``serial``, ``processes`` (every core) and
   ``ray`` (a local Ray, when it is installed), and each as a ratio to the baseline;
   targets: processes >= 1.7x the baseline on 2 cores; ray >= 0.8x processes;
3. a fork of the humanoid world: time and the memory it adds (target: 1 ms).

Run: ``.venv/bin/python bench/predict.py [--branches 32] [--ticks 500] [--no-ray]``
"""

from __future__ import annotations

import argparse
import os
import resource
import time
import tracemalloc
from pathlib import Path

import numpy as np
from timing import best_of

from dynabrain.orchestrator import Batch, load_world

ROOT = Path(__file__).resolve().parents[1]
HUMANOID = ROOT / "scenarios" / "humanoid_stand.yaml"
RECORD = ("core.pelvis.pos", "zmp.zmp")


def alone(world, ticks: int) -> float:
    """Ticks per second of the world stepping alone, from the same state each time."""
    snap = world.snapshot()

    def run() -> None:
        world.restore(snap)
        world.tick(ticks)

    seconds = best_of(run, repeats=5)
    world.restore(snap)
    return ticks / seconds


def batch_rate(world, backend: str, branches: int, ticks: int, repeats: int = 3, **options) -> tuple[float, float]:
    """(ticks per second of a batch run, start-up seconds of its workers)."""
    q_ref = np.zeros((branches, ticks, *np.shape(world.get("servo.q_ref"))))
    q_ref[:, :, :2] = np.linspace(-0.1, 0.1, branches)[:, None, None]
    request = dict(branches=branches, inputs={"servo.q_ref": q_ref},
                   params={"core.friction": np.linspace(0.5, 1.2, branches)}, record=RECORD)
    t0 = time.perf_counter()
    with Batch(world, backend=backend, **options) as batch:
        first = batch.run(2, branches=1)  # start the workers
        assert first.ok, first.status
        startup = time.perf_counter() - t0
        best = float("inf")
        for _ in range(repeats):
            result = batch.run(ticks, **request)
            assert result.ok, [str(s) for s in result.status if not s.ok]
            best = min(best, result.wall_s)
    return branches * ticks / best, startup


def fork_cost(world, repeats: int = 20) -> tuple[float, float]:
    """(ms per fork, MiB a fork adds)."""
    seconds = best_of(lambda: world.fork().close(), repeats=repeats)
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    twin = world.fork()
    added = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    twin.close()
    return seconds * 1e3, added / 2**20


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--branches", type=int, default=32)
    ap.add_argument("--ticks", type=int, default=500)
    ap.add_argument("--no-ray", action="store_true")
    opts = ap.parse_args()
    cores = os.cpu_count() or 1
    world = load_world(HUMANOID)
    world.tick(50)
    print(f"prediction: the humanoid ({len(world.modules)} modules), {opts.branches} branches x {opts.ticks} ticks; "
          f"machine: {cores} cores, load {os.getloadavg()[0]:.2f}")
    base = alone(world, opts.ticks)
    print(f"   one world alone (world.tick, history on):   {base:9.0f} ticks/s   1.00x")
    rates = {}
    backends = ["serial", "processes"] + ([] if opts.no_ray else ["ray"])
    for backend in backends:
        if backend == "ray":
            try:
                import ray  # noqa: F401
            except ImportError:
                print("   ray: not installed (pip install 'dynabrain[ray]')")
                continue
        rate, startup = batch_rate(world, backend, opts.branches, opts.ticks)
        rates[backend] = rate
        print(f"   batch on {backend:<10} {rate:9.0f} ticks/s   {rate / base:4.2f}x   (workers up in {startup:.2f} s)")
    if "processes" in rates:
        ratio = rates["processes"] / base
        print(f"   target processes >= 1.7x one world on 2 cores: {'met' if ratio >= 1.7 else 'MISSED'} ({ratio:.2f}x "
              f"on {cores} cores, {ratio / cores:.2f} per core)")
    if "ray" in rates and "processes" in rates:
        ratio = rates["ray"] / rates["processes"]
        print(f"   target ray >= 0.8x processes: {'met' if ratio >= 0.8 else 'MISSED'} ({ratio:.2f})")
    ms, mib = fork_cost(world)
    print(f"   fork: {ms:.2f} ms, {mib:.2f} MiB added   target <= 1 ms: {'met' if ms <= 1 else 'MISSED'}")
    print(f"   peak memory of this process: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
    world.close()


if __name__ == "__main__":
    main()
