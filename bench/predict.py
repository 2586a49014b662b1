"""Prediction benchmark: a batch of imagined futures of the humanoid, on each backend, in one run.

The world: `scenarios/humanoid_stand.yaml` (the humanoid, its servo, encoders, force sensors, IMU and
ZMP: 8 modules besides the core). Printed, each figure measured in this run:

1. one world stepping alone (`world.tick`, history on): ticks per second (the baseline);
2. a Batch of 32 branches x 500 ticks, each branch with its own friction and servo offsets, recording
   the pelvis position and the ZMP: ticks per second on ``serial``, ``processes`` (every core) and
   ``ray`` (a local Ray, when it is installed), and each as a ratio to the baseline;
   targets: processes >= 1.7x the baseline on 2 cores; ray >= 0.8x processes; beside them, what the
   cores give now: as many processes as cores, each stepping a world of its own (no Batch), together
   (other processes on the machine take their share of the cores from both);
3. a fork of the humanoid world: time and the memory it adds (target: 1 ms);
4. the core-only humanoid (its model, no module) on ``threads`` against `mujoco.rollout` called directly
   on the same models (each branch's friction set by the core), data (one per thread) and controls:
   steps per second of each, all branches together, and their ratio (target: threads >= 0.9x rollout).

Run: ``.venv/bin/python bench/predict.py [--branches 32] [--ticks 500] [--no-ray]``
"""

from __future__ import annotations

import argparse
import copy
import os
import resource
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
from timing import best_of, best_of_each

from dynabrain.orchestrator import Batch, load_world

ROOT = Path(__file__).resolve().parents[1]
HUMANOID = ROOT / "scenarios" / "humanoid_stand.yaml"
RECORD = ("core.pelvis.pos", "zmp.zmp")
MODEL = ROOT / "scenarios" / "models" / "humanoid.xml"


def alone(world, ticks: int) -> float:
    """Ticks per second of the world stepping alone, from the same state each time."""
    snap = world.snapshot()

    def run() -> None:
        world.restore(snap)
        world.tick(ticks)

    seconds = best_of(run, repeats=5)
    world.restore(snap)
    return ticks / seconds


_WORLD = None


def _load() -> None:
    global _WORLD
    _WORLD = load_world(HUMANOID)
    _WORLD.tick(50)


def _tick_span(ticks: int) -> tuple[float, float]:
    """In a worker: tick its own world ``ticks`` times; (start, end) on the machine's monotonic clock."""
    start = time.monotonic()
    _WORLD.tick(ticks)
    return start, time.monotonic()


def parallel_floor(cores: int, ticks: int, repeats: int = 3) -> float:
    """Ticks per second of ``cores`` processes each stepping a world of its own at once (no Batch: what
    the machine's cores give now, other processes' load included), over the whole span."""
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    best = 0.0
    with ProcessPoolExecutor(cores, mp_context=get_context("spawn"), initializer=_load) as pool:
        list(pool.map(_tick_span, [10] * cores))  # every worker up, its world loaded
        for _ in range(repeats):
            spans = list(pool.map(_tick_span, [ticks] * cores))
            best = max(best, cores * ticks / (max(e for _s, e in spans) - min(s for s, _e in spans)))
    return best


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


def threads_against_rollout(branches: int, ticks: int, threads: int) -> tuple[float, float, bool]:
    """(steps per second of a ``threads`` batch of the core-only humanoid, of `mujoco.rollout` called directly
    on the same models, data and controls, whether both give the same pelvis trajectories). Each branch:
    its own torques and friction; the batch records the pelvis position and the joints, keeps final states."""
    import mujoco
    from mujoco import rollout

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "humanoid_core.yaml"
        path.write_text(f"name: humanoid_core\nworld: {{step: 2ms, core: mujoco}}\nscene: {{model: {MODEL}}}\n")
        world = load_world(path)
    world.tick(50)
    ctrl = np.random.default_rng(0).normal(0.0, 0.3, (branches, ticks, *np.shape(world.get("core.ctrl"))))
    frictions = np.linspace(0.5, 1.2, branches)
    twin = world.fork()  # the models: the core's own, each friction set by the core (as the backend makes them)
    models = []
    for friction in frictions:
        twin.set("core.friction", float(friction))
        models.append(copy.copy(twin.core.mj.model))
    twin.close()
    order = [p.name for p in world.core.inputs() if p.view_of is not None and p.view_of[0] == "ctrl"]
    assert order == [f"{models[0].actuator(a).name}.ctrl" for a in range(models[0].nu)]  # ctrl is in MuJoCo's order
    full, data = mujoco.mjtState.mjSTATE_FULLPHYSICS, world.core.mj.data
    state0 = np.empty((1, mujoco.mj_stateSize(models[0], full)))
    mujoco.mj_getState(models[0], data, state0[0], full)
    warm = data.qacc_warmstart.copy()[None]
    datas = [mujoco.MjData(models[0]) for _ in range(threads)]

    def direct() -> tuple[np.ndarray, np.ndarray]:
        return rollout.rollout(models, datas, state0, ctrl, initial_warmstart=warm, persistent_pool=True)

    request = dict(branches=branches, inputs={"core.ctrl": ctrl}, params={"core.friction": frictions},
                   record=("core.pelvis.pos", "core.joint_q"))
    results = []
    with Batch(world, backend="threads", workers=threads) as batch:
        assert batch.run(2, branches=1).ok  # its threads and scratch world
        direct()  # rollout's pool
        t_threads, t_direct = best_of_each([lambda: results.append(batch.run(ticks, **request)), direct], repeats=5)
    states, _ = direct()
    same = all(r.ok for r in results) and np.array_equal(states[:, :, 1:4], results[-1].signals["core.pelvis.pos"])
    world.close()
    return branches * ticks / t_threads, branches * ticks / t_direct, same


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
        floor = parallel_floor(cores, opts.ticks * opts.branches // cores)
        print(f"   target processes >= 1.7x one world on 2 cores: {'met' if ratio >= 1.7 else 'MISSED'} ({ratio:.2f}x "
              f"on {cores} cores, {ratio / cores:.2f} per core)")
        print(f"   the cores now: {cores} processes each stepping a world of its own, no batch, {floor:.0f} ticks/s = "
              f"{floor / base:.2f}x one world; the batch on processes gets {rates['processes'] / floor:.2f} of that")
    if "ray" in rates and "processes" in rates:
        ratio = rates["ray"] / rates["processes"]
        print(f"   target ray >= 0.8x processes: {'met' if ratio >= 0.8 else 'MISSED'} ({ratio:.2f})")
    ms, mib = fork_cost(world)
    print(f"   fork: {ms:.2f} ms, {mib:.2f} MiB added   target <= 1 ms: {'met' if ms <= 1 else 'MISSED'}")
    world.close()
    threads, direct, same = threads_against_rollout(opts.branches, opts.ticks, cores)
    print(f"core-only humanoid (the model, no module), {opts.branches} branches x {opts.ticks} ticks, {cores} threads; "
          f"load {os.getloadavg()[0]:.2f}")
    print(f"   batch on threads:                           {threads:9.0f} steps/s")
    print(f"   mujoco.rollout called directly (same models, data, controls): {direct:9.0f} steps/s")
    ratio = threads / direct
    print(f"   target threads >= 0.9x mujoco.rollout: {'met' if ratio >= 0.9 else 'MISSED'} ({ratio:.2f}x); "
          f"same trajectories: {'yes' if same else 'NO'}")
    print(f"   peak memory of this process: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
