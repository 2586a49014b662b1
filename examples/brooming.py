"""The brain tunes its broom (the paper's Figs. 3-4): it imagines the sweep with several coefficients of
restitution for the broom's head, and sweeps with one that collects the garbage.

The world is `scenarios/brooming_default.yaml`: the broom's head has the world's restitution (0.8),
and the program's three strokes scatter the garbage (2 of 5 pieces end in the dustpan). Once the kid
holds the broom (1.3 s), the brain forks futures of its world, one per candidate value of the head's
own restitution (`Batch`, ``params={"core.broom_head.restitution": [...]}``), lets each future run
the rest of the motion program, and counts the pieces each leaves in the dustpan. It keeps the
candidate that collects the most (of those, the one closest to the default: the least change), sets
it on its world (``world.set("core.broom_head.restitution", e)``) and sweeps for real; with 0 this
is `scenarios/brooming_tuned.yaml`.

    .venv/bin/python examples/brooming.py                  # candidates 0.8 0.6 0.4 0.2 0
    .venv/bin/python examples/brooming.py --backend serial
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dynabrain.orchestrator import Batch, World, load_scenario

SCENARIO = Path(__file__).resolve().parents[1] / "scenarios" / "brooming_default.yaml"
HELD_S = 1.3
"""The broom is welded to the hand at 1.2 s; the brain starts imagining just after."""
CANDIDATES = (0.8, 0.6, 0.4, 0.2, 0.0)
PIECES = tuple(f"garbage_{k}" for k in range(5))
DUSTPAN = ((0.28, 0.47), (-0.1, 0.0))
"""The dustpan's inside (x, y ranges, m): models/brooming.xml."""


def in_dustpan(positions: np.ndarray) -> int:
    """How many of the positions (n, 3) lie inside the dustpan's walls."""
    (x0, x1), (y0, y1) = DUSTPAN
    x, y = positions[:, 0], positions[:, 1]
    return int(np.sum((x0 < x) & (x < x1) & (y0 < y) & (y < y1)))


@dataclass(frozen=True)
class Tuning:
    """What the brain imagined (candidate restitution -> pieces in the dustpan), what it chose, and
    how many pieces the real sweep left in the dustpan."""

    imagined: dict[float, int]
    chosen: float
    collected: int


def tune(world: World, end_tick: int, candidates: tuple[float, ...] = CANDIDATES, backend: str = "auto") -> Tuning:
    """From a world holding its broom: imagine the rest of the sweep for each candidate, choose, sweep."""
    record = [f"core.{p}.pos" for p in PIECES]
    ticks = end_tick - world.tick_count
    with Batch(world, backend=backend) as batch:
        result = batch.run(ticks, branches=len(candidates), params={"core.broom_head.restitution": list(candidates)},
                           record=record,
                           keep_states=False)
    imagined = {}
    for i, e in enumerate(candidates):
        imagined[e] = in_dustpan(np.array([result.signals[r][i, -1] for r in record]))
    best = max(imagined.values())
    chosen = next(e for e in candidates if imagined[e] == best)  # the least change that collects the most
    world.set("core.broom_head.restitution", chosen)
    world.tick(ticks)
    collected = in_dustpan(np.array([world.get(r) for r in record]))
    return Tuning(imagined, chosen, collected)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="auto", help="the futures' backend: serial, processes, auto")
    args = parser.parse_args()
    scenario = load_scenario(SCENARIO)
    world = scenario.build()
    try:
        world.tick(round(HELD_S / (world.dt_ns * 1e-9)))
        out = tune(world, scenario.duration_ns // world.dt_ns, backend=args.backend)
    finally:
        world.close()
    print("imagined sweeps (the broom head's restitution: pieces of garbage in the dustpan, of 5):")
    for e, n in out.imagined.items():
        print(f"  {e:3.1f}: {n}")
    print(f"chosen {out.chosen:g}; the real sweep left {out.collected} of 5 in the dustpan")


if __name__ == "__main__":
    main()
