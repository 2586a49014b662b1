"""Selection in the kitchen (the paper's Fig. 12): what simulating only the dishes, tray and board saves.

`scenarios/kitchen_tray.yaml` stacks four dishes on a tray and carries it, in a kitchen of 103
objects; the brain selects the dishes, the tray and the board (6 objects), and the other 97 stand
frozen, fused into static geometry. The baseline is the same scenario with the whole kitchen simulated
(`World.make` of every object at t=0: every cup, bowl, glass and pot resting on its counter). Both run
the whole scenario (12.5 s simulated) in this process, interleaved, best of ``--rounds`` (the wall time
of the ticks only: building a world is not counted); the speed-up is the ratio of the two. The
outcome is compared too: where the tray and the top dish end in both worlds (the frozen objects rest,
so the selection changes nothing the task sees).

Run: ``.venv/bin/python bench/selection_kitchen.py``
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dynabrain.orchestrator import load_scenario

SCENARIO = Path(__file__).resolve().parent.parent / "scenarios" / "kitchen_tray.yaml"
OUTCOME = ("core.tray.pos", "core.dish_3.pos")


@dataclass(frozen=True)
class Run:
    """One run of the scenario: wall time of its ticks (s), the model's size, where it ended."""

    wall_s: float
    bodies: int
    dof: int
    outcome: dict[str, np.ndarray]


def run(whole: bool) -> Run:
    """The whole scenario, with its selection or with every object selected at t=0."""
    scenario = load_scenario(SCENARIO)
    world = scenario.build()
    try:
        if whole:
            world.make(world.core.objects())
        ticks = scenario.duration_ns // world.dt_ns
        t0 = time.perf_counter()
        world.tick(ticks)
        wall = time.perf_counter() - t0
        model = world.core.mj.model
        return Run(wall, model.nbody - 1, model.nv, {k: world.get(k) for k in OUTCOME})
    finally:
        world.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2, help="rounds of both runs, interleaved (best of)")
    args = parser.parse_args()
    best: dict[bool, Run] = {}
    for _ in range(args.rounds):
        for whole in (False, True):
            r = run(whole)
            if whole not in best or r.wall_s < best[whole].wall_s:
                best[whole] = r
    sim_s = load_scenario(SCENARIO).duration_ns * 1e-9
    sel, all_ = best[False], best[True]
    print("kitchen tray: only the dishes, tray and board simulated, against the whole kitchen, in one run")
    for label, r in (("selected (6 of 103 objects)", sel), ("whole kitchen (103 objects)", all_)):
        print(f"   {label:<28} {r.bodies:4d} bodies {r.dof:4d} DoF: {r.wall_s:6.2f} s wall for {sim_s:g} s "
              f"simulated, real-time factor {sim_s / r.wall_s:5.1f}")
    print(f"   speed-up of the selection: {all_.wall_s / sel.wall_s:.1f}x")
    for key in OUTCOME:
        gap = float(np.linalg.norm(sel.outcome[key] - all_.outcome[key]))
        print(f"   {key} at the end: {np.round(sel.outcome[key], 4)} selected, {np.round(all_.outcome[key], 4)} "
              f"whole ({gap * 1000:.2f} mm apart)")


if __name__ == "__main__":
    main()
