"""The planner as A* (issue 26, item 5): what the closed set, the goal tested at pop and children of
different lengths in one batch give, each figure measured in this run on the slider
(`tests/scenarios/slider.yaml`: a 1 kg box on a damped slide).

1. the order of the actions: two pushes that both end past the goal, a quick one (0.1 s) and a slow
   one (0.4 s), listed in either order: the cost of the plan returned;
2. the closed set: pushes left, none and right, no heuristic (uniform cost): nodes expanded and
   children simulated without a closed set, with the default key (the signals rounded to 1 um) and
   with a coarse key of the user's (1 cm, 0.1 m/s);
3. children of different lengths (``--lengths``, two pushes each) evaluated from one state on
   ``processes`` as one batch, against one batch per length (what the planner did before): the
   wall time of each, the best of ``--repeats``, and their ratio;
4. the children of several frontier nodes in one batch (``nodes_per_batch``) on ``processes``: nodes
   expanded, batches and planning time (the best of ``--repeats``, interleaved), one node per batch
   against ``--nodes`` per batch.

The machine's load (1-minute average) is printed before and after.

Run: ``.venv/bin/python bench/astar.py [--workers 2] [--lengths 25 50 100] [--repeats 5] [--nodes 2]``
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
from timing import best_of_each

from dynabrain.orchestrator import Batch, load_world
from dynabrain.orchestrator.brain.plan import Action, search

SLIDER = Path(__file__).resolve().parents[1] / "tests" / "scenarios" / "slider.yaml"
RECORD = ["core.s.q", "core.s.qd"]
TARGET_M = 0.3


def load() -> str:
    return f"load {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores"


def order(world) -> None:
    quick = Action("quick", 50, inputs={"core.s.force": 40.0})
    slow = Action("slow", 200, inputs={"core.s.force": 10.0})
    for actions in ([quick, slow], [slow, quick]):
        plan = search(world, actions, record=["core.s.q"], heuristic=lambda o: 0.0, backend="serial",
                      goal=lambda o: o["core.s.q"] > 0.15)
        listed = ", ".join(a.name for a in actions)
        print(f"   actions [{listed}]: plan {[a.name for a in plan.actions]}, cost {plan.cost:.2f} s, "
              f"{plan.stats.batches} batch of {plan.stats.generated} children")


def closed_set(world) -> None:
    actions = [Action(f"push {f:+g} N", 50, inputs={"core.s.force": f}) for f in (-4.0, 0.0, 4.0)]
    request = dict(record=RECORD, heuristic=lambda o: 0.0, backend="serial", goal=lambda o: o["core.s.q"] > 0.12,
                   max_expansions=500)
    coarse = lambda o: (round(float(o["core.s.q"]), 2), round(float(o["core.s.qd"]), 1))  # noqa: E731
    for name, options in (("no closed set", dict(closed=False)), ("default key (1 um)", {}),
                          ("coarse key (1 cm, 0.1 m/s)", dict(key=coarse))):
        plan = search(world, actions, **request, **options)
        s = plan.stats
        print(f"   {name:<28} {s.expanded:4d} nodes expanded, {s.generated:4d} simulated, {s.duplicates:3d} dropped, "
              f"plan cost {plan.cost:.2f} s, {s.wall_s:.2f} s")


def lengths(world, counts: list[int], workers: int, repeats: int) -> None:
    start = world.export_state()
    ticks = [t for t in counts for _ in range(2)]
    forces = [np.full(t, f) for t, f in zip(ticks, np.tile([2.0, 4.0], len(counts)), strict=True)]
    with Batch(world, backend="processes", workers=workers) as batch:
        assert batch.run(2, branches=workers).ok  # the workers start

        def one() -> None:
            assert batch.run(ticks, starts=[start] * len(ticks), inputs={"core.s.force": forces}, record=RECORD).ok

        def per_length() -> None:
            for t in counts:
                rows = [i for i, n in enumerate(ticks) if n == t]
                pushes = np.stack([forces[i] for i in rows])
                assert batch.run(t, starts=[start] * len(rows), inputs={"core.s.force": pushes}, record=RECORD).ok

        t_one, t_per = best_of_each([one, per_length], repeats=repeats)
    print(f"   {len(ticks)} children of {counts} ticks: one batch {t_one * 1e3:.1f} ms, one batch per length "
          f"{t_per * 1e3:.1f} ms: {t_per / t_one:.2f}x")


def frontier(world, workers: int, nodes: int, repeats: int) -> None:
    pushes = [Action(f"push {f:+g} N", 50, inputs={"core.s.force": f}) for f in (-4.0, -1.0, 0.0, 1.0, 4.0)]
    request = dict(record=RECORD, heuristic=lambda o: abs(o["core.s.q"] - TARGET_M) / 0.5,
                   goal=lambda o: abs(o["core.s.q"] - TARGET_M) < 0.02 and abs(o["core.s.qd"]) < 0.1)
    plans = {}
    with Batch(world, backend="processes", workers=workers) as batch:
        assert batch.run(2, branches=workers).ok
        for _ in range(repeats):  # interleaved, the best time of each
            for per in (1, nodes):
                plan = search(world, pushes, batch=batch, nodes_per_batch=per, **request)
                if per not in plans or plan.stats.wall_s < plans[per].stats.wall_s:
                    plans[per] = plan
    for per, plan in plans.items():
        s = plan.stats
        print(f"   {per} node(s) a batch: {s.expanded:3d} nodes expanded in {s.batches:3d} batches, {s.generated} "
              f"simulated, plan cost {plan.cost:.2f} s, {s.wall_s:.3f} s")
    ratio = plans[1].stats.wall_s / plans[nodes].stats.wall_s
    print(f"   time of 1 node a batch / {nodes}: {ratio:.2f} (above 1: {nodes} a batch is faster)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--lengths", type=int, nargs="+", default=[25, 50, 100])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--nodes", type=int, default=2)
    opts = ap.parse_args()
    print(f"planner as A* ({load()})")
    world = load_world(SLIDER)
    try:
        print("1. two goal-reaching actions, either order (goal tested at pop):")
        order(world)
        print("2. closed set, uniform cost:")
        closed_set(world)
        print(f"3. children of different lengths on processes ({opts.workers} workers):")
        lengths(world, opts.lengths, opts.workers, opts.repeats)
        print(f"4. children of several frontier nodes in one batch ({opts.workers} workers):")
        frontier(world, opts.workers, opts.nodes, opts.repeats)
    finally:
        world.close()
    print(f"({load()})")


if __name__ == "__main__":
    main()
