"""Prediction benchmark: a batch of imagined futures of the humanoid, on each backend, in one run.

The world: `scenarios/humanoid_stand.yaml` (the humanoid, its servo, encoders, force sensors, IMU and
ZMP: 8 modules besides the core). Printed, each figure measured in this run, the machine's load beside
(the memory first, measured before the rest has grown the process):

1. rounds (``--rounds``), each timing in turn, interleaved: one world stepping alone (`world.tick`,
   history on: the baseline), then a Batch of ``--branches`` x ``--ticks`` (each branch with its own
   friction and servo offsets, recording the pelvis position and the ZMP) on ``serial``, ``processes``
   (every core), ``lockstep`` (every branch in this process, tick by tick together) and ``ray`` (a local
   Ray, with ``--ray``), each right after a baseline of its own, and `mujoco.rollout` of the same futures,
   physics only (the floor): the humanoid's model with each branch's friction, from the same state, driven
   by the motor controls the servos gave (recorded once), its trajectories checked bit for bit equal to
   the batch's, so that it does the very work of the batches' physics and nothing else.
   Each backend's ratio to one world is the median of its per-round ratios (a busy machine slows both
   sides of a round alike); lockstep's ratios to rollout and to processes likewise. Targets (issue 25):
   lockstep >= 0.85 of rollout, >= 1.6x processes; processes >= 1.7x one world on 2 cores. Beside them,
   what the cores give now: as many processes as cores, each stepping a world of its own (no Batch);
2. a fork of the humanoid world: time, the Python heap it adds (tracemalloc) and the resident memory
   it adds (RSS: MuJoCo's C memory too); and a lockstep batch's resident memory per branch against a
   bare MjData per branch stepped as many steps (MuJoCo's own data): target <= 1 MiB a branch beyond it;
3. the core-only humanoid on ``threads`` against `mujoco.rollout` called directly on the same models
   (each branch's friction set by the core), data (one per thread) and controls: steps per second of
   each, all branches together, and their ratio (target: threads >= 0.9x rollout).

The lockstep batch with its physics on MJWarp (``Batch(physics="mjwarp")``) has a bench of its own,
``bench/mjwarp.py`` (warp's compile and CPU device are slow enough to drown these rounds; its rows
print beside lockstep on C and `mujoco.rollout` there).

Run: ``.venv/bin/python bench/predict.py [--branches 64] [--ticks 500] [--rounds 3] [--ray]``
"""

from __future__ import annotations

import argparse
import copy
import os
import resource
import statistics
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


def alone(world, ticks: int, repeats: int = 5) -> float:
    """Ticks per second of the world stepping alone, from the same state each time."""
    snap = world.snapshot()

    def run() -> None:
        world.restore(snap)
        world.tick(ticks)

    seconds = best_of(run, repeats=repeats)
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

    world = core_only_world()
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


def rss_mib() -> float:
    """This process's resident memory now (MuJoCo's C memory and Python's alike), in MiB."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:  # not Linux: the peak instead
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def request_for(world, branches: int, ticks: int) -> dict:
    """The batch every backend runs: per-branch servo offsets and friction, the pelvis and ZMP recorded."""
    q_ref = np.zeros((branches, ticks, *np.shape(world.get("servo.q_ref"))))
    q_ref[:, :, :2] = np.linspace(-0.1, 0.1, branches)[:, None, None]
    return dict(branches=branches, inputs={"servo.q_ref": q_ref},
                params={"core.friction": np.linspace(0.5, 1.2, branches)}, record=RECORD)


def core_only_world():
    """The humanoid's model alone in a world (no module but the core), ticked 50 ticks."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "humanoid_core.yaml"
        path.write_text(f"name: humanoid_core\nworld: {{step: 2ms, core: mujoco}}\nscene: {{model: {MODEL}}}\n")
        world = load_world(path)
    world.tick(50)
    return world


def physics_floor(world, request: dict, threads: int):
    """`mujoco.rollout` of the very futures the batches imagine, physics only: the humanoid's model with
    each branch's friction, from the world's state, driven by the motor controls its servos gave in a
    lockstep run of ``request`` (recorded from ``core.ctrl``), ``branches`` x ``ticks`` steps on
    ``threads`` threads. Returns a call that runs it, and whether its pelvis trajectories are bit for
    bit those of the batch (the same physics, so the same work: the floor of what any backend can do)."""
    import mujoco
    from mujoco import rollout

    record = dict(request, record=("core.pelvis.pos", "core.ctrl"))
    ticks = np.shape(request["inputs"]["servo.q_ref"])[1]
    with Batch(world, backend="lockstep") as batch:
        result = batch.run(ticks, **record)
    branches = len(result.status)
    ctrl = np.stack([result.branch("core.ctrl", b) for b in range(branches)])
    pelvis = np.stack([result.branch("core.pelvis.pos", b) for b in range(branches)])
    twin = world.fork()
    models = []
    for friction in request["params"]["core.friction"]:
        twin.set("core.friction", float(friction))
        models.append(copy.copy(twin.core.mj.model))
    twin.close()
    full, data = mujoco.mjtState.mjSTATE_FULLPHYSICS, world.core.mj.data
    state0 = np.empty((1, mujoco.mj_stateSize(models[0], full)))
    mujoco.mj_getState(models[0], data, state0[0], full)
    warm = data.qacc_warmstart.copy()[None]
    datas = [mujoco.MjData(models[0]) for _ in range(threads)]

    def run() -> np.ndarray:
        return rollout.rollout(models, datas, state0, ctrl, initial_warmstart=warm, persistent_pool=True)[0]

    same = np.array_equal(run()[:, :, 1:4], pelvis)  # (and its pool up)
    return run, same


def memory(world, branches: int) -> None:
    """Section 3: a fork's time and memory (Python heap and resident), and a lockstep batch's resident
    memory per branch against MuJoCo's own data for as many branches."""
    import mujoco

    ms, heap = fork_cost(world)
    before = rss_mib()
    forks = [world.fork() for _ in range(8)]
    for twin in forks:
        twin.tick(5)
    rss_fork = (rss_mib() - before) / len(forks)
    for twin in forks:
        twin.close()
    print(f"   fork: {ms:.2f} ms, {heap:.2f} MiB of Python heap, {rss_fork:.2f} MiB resident (stepped 5 ticks)   "
          f"target <= 1 ms: {'met' if ms <= 1 else 'MISSED'}")
    model = world.core.mj.model
    before = rss_mib()
    datas = [mujoco.MjData(model) for _ in range(branches)]
    for d in datas:
        mujoco.mj_step(model, d, 20)
    bare = (rss_mib() - before) / branches
    before = rss_mib()
    with Batch(world, backend="lockstep") as batch:
        assert batch.run(20, **request_for(world, branches, 20)).ok
        per_branch = (rss_mib() - before) / branches
    del datas
    extra = per_branch - bare
    print(f"   lockstep, {branches} branches: {per_branch:.2f} MiB resident a branch; a bare MjData stepped as long: "
          f"{bare:.2f} MiB; beyond it {extra:.2f} MiB   target <= 1 MiB: {'met' if extra <= 1 else 'MISSED'}")


def rounds(world, backends: list[str], branches: int, ticks: int, count: int) -> dict[str, list[float]]:
    """Section 1: ``count`` rounds, each backend timed right after a baseline of its own, then rollout
    (see the module docstring); per round: ticks per second of each and ratios. Returns the ratios."""
    request = request_for(world, branches, ticks)
    batches, ready = {}, {}
    for name in backends:
        t0 = time.perf_counter()
        batches[name] = Batch(world, backend=name)
        assert batches[name].run(2, **request_for(world, branches, 2)).ok  # workers, forks, threads up
        ready[name] = time.perf_counter() - t0
    floor, same = physics_floor(world, request, os.cpu_count() or 1)
    ratios: dict[str, list[float]] = {name: [] for name in [*backends, "lockstep/rollout", "lockstep/processes"]}
    rates: dict[str, list[float]] = {name: [] for name in ["one world", *backends, "rollout"]}
    try:
        for r in range(count):
            load = os.getloadavg()[0]
            for name, batch in batches.items():
                base = alone(world, ticks, repeats=3)
                result = batch.run(ticks, **request)
                assert result.ok, [str(s) for s in result.status if not s.ok]
                rate = branches * ticks / result.wall_s
                rates["one world"].append(base)
                rates[name].append(rate)
                ratios[name].append(rate / base)
            t0 = time.perf_counter()
            floor()
            rates["rollout"].append(branches * ticks / (time.perf_counter() - t0))
            if "lockstep" in batches:
                ratios["lockstep/rollout"].append(rates["lockstep"][-1] / rates["rollout"][-1])
            if "lockstep" in batches and "processes" in batches:
                ratios["lockstep/processes"].append(rates["lockstep"][-1] / rates["processes"][-1])
            cells = "  ".join(f"{name} {rates[name][-1]:7.0f}" for name in [*backends, "rollout"])
            print(f"   round {r + 1}: load {load:5.2f}   one world {rates['one world'][-1]:6.0f}  {cells}  ticks/s")
    finally:
        for batch in batches.values():
            batch.close()
    print("   medians of the rounds (ratios: of each round's own figures):")
    base = statistics.median(rates["one world"])
    print(f"   one world alone (world.tick, history on):   {base:9.0f} ticks/s   1.00x")
    for name in backends:
        print(f"   batch on {name:<10} {statistics.median(rates[name]):9.0f} ticks/s   "
              f"{statistics.median(ratios[name]):4.2f}x   (up in {ready[name]:.2f} s)")
    floor = statistics.median(rates["rollout"])
    print(f"   mujoco.rollout of the same futures, physics only (the floor): {floor:9.0f} steps/s   "
          f"{floor / base:4.2f}x   (same trajectories as the batch: {'yes' if same else 'NO'})")
    return ratios


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--branches", type=int, default=64)
    ap.add_argument("--ticks", type=int, default=500)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--ray", action="store_true", help="time a local Ray too (slow to start)")
    opts = ap.parse_args()
    cores = os.cpu_count() or 1
    world = load_world(HUMANOID)
    world.tick(50)
    print(f"prediction: the humanoid ({len(world.modules)} modules), {opts.branches} branches x {opts.ticks} ticks; "
          f"machine: {cores} cores, load {os.getloadavg()[0]:.2f}")
    print(f"memory (load {os.getloadavg()[0]:.2f}):")
    memory(world, opts.branches)
    backends = ["serial", "processes", "lockstep"]
    if opts.ray:
        try:
            import ray  # noqa: F401

            backends.append("ray")
        except ImportError:
            print("   ray: not installed (pip install 'dynabrain[ray]')")
    print(f"interleaved rounds, {opts.rounds} of them:")
    ratios = rounds(world, backends, opts.branches, opts.ticks, opts.rounds)
    median = {name: statistics.median(values) for name, values in ratios.items() if values}
    print(f"   target lockstep >= 0.85 of rollout: {'met' if median['lockstep/rollout'] >= 0.85 else 'MISSED'} "
          f"({median['lockstep/rollout']:.2f})")
    print(f"   target lockstep >= 1.6x processes: {'met' if median['lockstep/processes'] >= 1.6 else 'MISSED'} "
          f"({median['lockstep/processes']:.2f}x)")
    print(f"   target processes >= 1.7x one world on 2 cores: {'met' if median['processes'] >= 1.7 else 'MISSED'} "
          f"({median['processes']:.2f}x on {cores} cores)")
    if "ray" in median:
        print(f"   target ray >= 0.8x processes: {'met' if median['ray'] / median['processes'] >= 0.8 else 'MISSED'} "
              f"({median['ray'] / median['processes']:.2f})")
    base = alone(world, opts.ticks, repeats=3)
    floor = parallel_floor(cores, opts.ticks * opts.branches // cores)
    print(f"   the cores now (load {os.getloadavg()[0]:.2f}): {cores} processes each stepping a world of its own, no "
          f"batch, {floor:.0f} ticks/s = {floor / base:.2f}x one world timed just before")
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
