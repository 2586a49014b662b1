"""MJWarp benchmark (issue 25, item 2): the humanoid's futures on MJWarp against MuJoCo's C, in one run.

The world: `scenarios/humanoid_stand.yaml` (the humanoid and its 8 modules). Printed, each figure measured
in this run with the machine's load beside it, in ``--rounds`` interleaved rounds (a busy machine slows
every row of a round alike; the ratios are medians of each round's own ratios):

- ``rollout``: `mujoco.rollout` of the core-only humanoid (the same model, no module: MuJoCo's C physics
  alone on every core, the floor), ``--branches`` x ``--ticks`` steps;
- ``lockstep C``: a lockstep Batch of the humanoid with its modules, the physics on C threads;
- ``lockstep warp``: the same batch with ``physics="mjwarp"`` (`modules.mujoco.warp_batch`): the physics on
  warp's device (``DYNABRAIN_WARP_DEVICE``, default its CPU), the modules batched as on C;
- ``warp physics``: `WarpWorlds.step` alone on the same model and worlds (no copy in or out, no
  module): what warp's physics gives on this device.

The first call compiles warp's kernels (printed apart: not in the rates). Run:
``.venv/bin/python bench/mjwarp.py [--branches 16] [--ticks 100] [--rounds 3]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import mujoco
import numpy as np
from mujoco import rollout

from dynabrain.modules.mujoco import warp_batch
from dynabrain.orchestrator import Batch, load_world

ROOT = Path(__file__).resolve().parents[1]
HUMANOID = ROOT / "scenarios" / "humanoid_stand.yaml"
MODEL = ROOT / "scenarios" / "models" / "humanoid.xml"
RECORD = ("core.pelvis.pos", "zmp.zmp")
last: dict[str, object] = {}  # each physics' last batch result (`batch_run`)


def core_only_model() -> tuple[mujoco.MjModel, mujoco.MjData]:
    """The humanoid's model as the core compiles it (no module but the core), and its data 50 ticks on."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "humanoid_core.yaml"
        path.write_text(f"name: humanoid_core\nworld: {{step: 2ms, core: mujoco}}\nscene: {{model: {MODEL}}}\n")
        world = load_world(path)
    world.tick(50)
    model = world.core.mj.model
    data = mujoco.MjData(model)
    mujoco.mj_copyData(data, model, world.core.mj.data)
    world.close()
    return model, data


def rollout_run(model: mujoco.MjModel, data: mujoco.MjData, branches: int, ticks: int):
    """A call that runs `mujoco.rollout` of ``branches`` x ``ticks`` steps on every core."""
    full = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state0 = np.empty((1, mujoco.mj_stateSize(model, full)))
    mujoco.mj_getState(model, data, state0[0], full)
    warm = data.qacc_warmstart.copy()[None]
    datas = [mujoco.MjData(model) for _ in range(os.cpu_count() or 1)]
    ctrl = np.zeros((branches, ticks, model.nu))

    def run() -> None:
        rollout.rollout([model] * branches, datas, state0, ctrl, initial_warmstart=warm, persistent_pool=True)

    run()
    return run


def batch_run(world, physics: str, branches: int, ticks: int):
    """A call that runs a lockstep batch of the humanoid with its modules on ``physics``, from the world's
    state (each branch its own servo offsets and friction, as in bench/predict.py), run once here (warp
    compiles its kernels); (the call, the batch to close, the seconds of that first run)."""
    batch = Batch(world, backend="lockstep")
    q_ref = np.zeros((branches, ticks, *np.shape(world.get("servo.q_ref"))))
    q_ref[:, :, :2] = np.linspace(-0.1, 0.1, branches)[:, None, None]

    def run() -> None:
        result = last[physics] = batch.run(ticks, branches=branches, inputs={"servo.q_ref": q_ref}, record=RECORD,
                                           params={"core.friction": np.linspace(0.5, 1.2, branches)})
        if not all(s.ok for s in result.status) or any("failed" in note for note in result.notes):
            sys.exit(f"the {physics} batch failed: {result.notes} {[s.reason for s in result.status if not s.ok]}")

    os.environ["DYNABRAIN_LOCKSTEP_PHYSICS"] = physics  # read when the batch makes its backend: on its first run
    try:
        first = timed(run)
    finally:
        os.environ.pop("DYNABRAIN_LOCKSTEP_PHYSICS")
    return run, batch, first


def warp_run(model: mujoco.MjModel, data: mujoco.MjData, branches: int, ticks: int):
    worlds = warp_batch.WarpWorlds(model, branches)
    worlds.put([data] * branches)

    def run() -> None:
        worlds.step(ticks)

    return run


def timed(run) -> float:
    t0 = time.perf_counter()
    run()
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--branches", type=int, default=16)
    parser.add_argument("--ticks", type=int, default=100)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    why = warp_batch.unavailable()
    if why is not None:
        print(f"MJWarp cannot run here: {why}")
        return
    n, ticks = args.branches, args.ticks
    print(f"== MJWarp: the humanoid, {n} branches x {ticks} ticks, warp device {warp_batch.default_device()!r}, "
          f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}")
    model, data = core_only_model()
    world = load_world(HUMANOID)
    world.tick(50)
    runs = {"rollout": rollout_run(model, data, n, ticks)}
    runs["lockstep C"], on_c, _ = batch_run(world, "threads", n, ticks)
    runs["lockstep warp"], on_warp, first = batch_run(world, "mjwarp", n, ticks)
    runs["warp physics"] = warp_run(model, data, n, ticks)
    print(f"   warp's first batch (its kernels compiled, or read from its cache {warp_batch.cache_dir()}): "
          f"{first:.1f} s; first physics call {timed(runs['warp physics']):.1f} s")
    rates: dict[str, list[float]] = {name: [] for name in runs}
    ratios: dict[str, list[float]] = {"lockstep warp / lockstep C": [], "lockstep warp / rollout": [],
                                      "warp physics / rollout": []}
    for k in range(args.rounds):
        load = os.getloadavg()[0]
        for name, run in runs.items():
            rates[name].append(n * ticks / timed(run))
        ratios["lockstep warp / lockstep C"].append(rates["lockstep warp"][-1] / rates["lockstep C"][-1])
        ratios["lockstep warp / rollout"].append(rates["lockstep warp"][-1] / rates["rollout"][-1])
        ratios["warp physics / rollout"].append(rates["warp physics"][-1] / rates["rollout"][-1])
        print(f"   round {k + 1} (load {load:.2f}): " + "  ".join(f"{name} {rates[name][-1]:7.0f}" for name in runs))
    print("   medians of the rounds (ticks/s, all branches together; ratios: of each round's own figures):")
    for name in runs:
        print(f"   {name:<14} {statistics.median(rates[name]):9.0f} ticks/s")
    for name, values in ratios.items():
        print(f"   {name:<27} {statistics.median(values):5.2f}x")
    gap = max(np.abs(last["mjwarp"].branch("core.pelvis.pos", b) - last["threads"].branch("core.pelvis.pos", b)).max()
              for b in range(n))
    print(f"   pelvis position, warp against C: largest gap {gap:.2e} m over the {ticks} ticks of every branch")
    print(f"   world-ticks stepped on warp {warp_batch.STEPPED['warp']}, on C instead {warp_batch.STEPPED['c']}; "
          f"load now {os.getloadavg()[0]:.2f}")
    on_c.close()
    on_warp.close()
    world.close()


if __name__ == "__main__":
    main()
