"""The humanoid block task (examples/blocks_humanoid.py, issue 23): what the brain gets done per second,
and how the real world's outcome compares with the prediction, each figure measured in this run.

1. the eyes: recognising the stack (the look rendered and the blocks estimated), and the errors against
   the scene's truth;
2. the whole robot simulated: ticks per second of the brain's world (the kid's 23 joints, the servo,
   the hands, the ZMP sensor, three blocks) standing and while a hand pushes (the whole-body IK solved
   at the push's start is part of it), against a bare ``mj_step`` of the same model in the same run;
3. planning: the careful planner (slow pushes of free blocks) and the dynamic one (slow and fast pushes
   of any block), the children of a node evaluated on ``serial`` and as one batch on ``processes``:
   planning time, nodes expanded, children simulated per second, ticks per second, and the ratio of
   the two backends over both searches;
4. the real world: the plan executed on the brain's world (bit for bit) and sent as robot programs (each
   push's servo sequence) to a served world (``dynabrain serve`` with the robot rig and a robot
   emulator, on loopback, lock-step): the blocks' final positions against the prediction (cm), and the
   time it took.

The machine's load (1-minute average) is printed before and after: on a busy machine the ratios hold
better than the absolute figures.

Run: ``.venv/bin/python bench/blocks_humanoid.py [--max-expansions 12] [--no-remote]``
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
import blocks_humanoid as bh  # noqa: E402
import recognised_blocks as rb  # noqa: E402
from timing import best_of_each  # noqa: E402

from dynabrain.orchestrator import Batch, load_world  # noqa: E402


def load() -> str:
    return f"load {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores"


def eyes() -> list:
    scene = load_world(bh.SCENARIO)
    try:
        t0 = time.perf_counter()
        seen = bh.look(scene)
        wall = time.perf_counter() - t0
        errors = [np.abs(np.subtract(b.pos, rb.truth(scene, b.colour).pos)).max() * 1000 for b in seen]
        sizes = [np.abs(np.subtract(b.size, rb.truth(scene, b.colour).size)).max() * 1000 for b in seen]
    finally:
        scene.close()
    print(f"1. eyes: {len(seen)} blocks recognised in {wall:.2f} s (the look: {bh.LOOK} ticks simulated with the "
          f"eyes rendering at 10 Hz); worst centre error {max(errors):.1f} mm, worst size error {max(sizes):.1f} mm")
    return seen


def ticks_per_s(seen: list) -> None:
    """Best of 5 (the brain's world from the plan's start each time; the bare model copied from it)."""
    world = bh.brain_world(seen)
    try:
        start, n = world.export_state(), 1000
        m = world.core.mj.model
        d = mujoco.MjData(m)

        def stand() -> None:
            world.import_state(start)
            world.run(n)

        def push() -> None:
            world.import_state(start)
            world.set("hands.push", "blue left slow")
            world.run(n)

        def bare_steps() -> None:
            for _ in range(n):
                mujoco.mj_step(m, d)

        world.import_state(start)
        d.qpos[:], d.qvel[:] = world.core.mj.data.qpos, world.core.mj.data.qvel
        bare, standing, pushing = (n / t for t in best_of_each([bare_steps, stand, push], repeats=5))
    finally:
        world.close()
    print(f"2. the whole robot: {standing:.0f} ticks/s standing, {pushing:.0f} ticks/s while a hand pushes (IK "
          f"included); a bare mj_step of the same model {bare:.0f}/s: orchestrated/bare {bare / standing:.2f}x "
          "the time standing")


def planning(seen: list, max_expansions: int, remote: bool) -> None:
    names = [b.colour for b in seen]
    world = bh.brain_world(seen)
    plans, rates = {}, {}
    try:
        for backend in ("serial", "processes"):
            generated = wall = 0.0
            batch = Batch(world, backend=backend)  # its workers started once, kept for both searches
            try:
                for name, careful in (("careful", True), ("dynamic", False)):
                    plans[backend, name] = p = bh.plan(world, names, careful=careful, batch=batch,
                                                       max_expansions=max_expansions)
                    generated, wall = generated + p.stats.generated, wall + p.stats.wall_s
                    print(f"3. planning on {backend}: " + bh.describe(name, p).replace("\n", "\n   "))
            finally:
                batch.close()
            rates[backend] = generated / wall
        same = all([a.name for a in plans["serial", n].actions] == [a.name for a in plans["processes", n].actions]
                    for n in ("careful", "dynamic"))
        print(f"   processes / serial: {rates['processes'] / rates['serial']:.2f}x the children per second "
              f"({rates['serial']:.1f} and {rates['processes']:.1f}/s); the plans are "
              f"{'the same' if same else 'DIFFERENT'}")
        best = plans["processes", "dynamic"]
        t0 = time.perf_counter()
        same = bh.execute(world, best)
        print(f"4. executed on the brain's world in {time.perf_counter() - t0:.2f} s: "
              f"{'equals' if same else 'DIFFERS FROM'} the prediction bit for bit")
        if remote:
            served(world, best, names)
    finally:
        world.close()


def served(world, best, names: list[str]) -> None:
    from dynabrain.bridge.testing import EmulatorProcess, ServerProcess

    server = ServerProcess(str(bh.SCENARIO), "--robot", f"{bh.ROBOT}=servo", "--deadline", "2s")
    with server, EmulatorProcess(str(bh.SCENARIO), "blocks_humanoid", server.endpoint, "--robot", bh.ROBOT):
        t0 = time.perf_counter()
        real = bh.execute_remote(world, best, names, server.endpoint)
        wall = time.perf_counter() - t0
    ticks = sum(a.ticks for a in best.actions)
    errors = ", ".join(f"{b} {np.linalg.norm(real[b] - best.trajectory[f'core.{b}.pos'][-1]) * 100:.1f} cm"
                       for b in names)
    print(f"   sent as robot programs to the served world with the robot emulator ({bh.pushes(len(best.actions))}, "
          f"{ticks} ticks, lock-step) in {wall:.2f} s: the blocks end {errors} from the prediction")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--max-expansions", type=int, default=12)
    ap.add_argument("--no-remote", action="store_true", help="skip the served world")
    opts = ap.parse_args()
    print(load())
    seen = eyes()
    ticks_per_s(seen)
    planning(seen, opts.max_expansions, not opts.no_remote)
    print(load())


if __name__ == "__main__":
    main()
