"""Selection in the kitchen (the paper's Fig. 12): what simulating only the kid, the dishes, the tray and
the board saves.

In `scenarios/kitchen_tray.yaml` the humanoid kid stacks four dishes on a tray and carries it, in a
kitchen of 103 objects; the brain selects the kid, the dishes, the tray and the board (7 objects), and
the other 97 stand frozen, fused into static geometry. The baseline is the same scenario with the
whole kitchen simulated (`World.make` of every object at t=0: every cup, bowl, glass and pot resting on
its counter). Both run the whole scenario in this process, interleaved, best of ``--rounds`` (the wall
time of the ticks only: building a world is not counted); the speed-up is the ratio of the two. The
ticks at which the scenario's events fire (a grasp adds a grip body and welds it, a release removes it:
each such edit compiles the model again) are timed apart, and the speed-up of the stepping alone is
printed beside the whole run's. The outcome is compared too: where the tray and the top dish end in
both worlds (the frozen objects rest, so the selection changes nothing the task sees).

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
    """One run of the scenario: wall time of its ticks (s), of those the ones with events, the model's
    size, where it ended."""

    wall_s: float
    events_s: float
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
        wall = events = 0.0
        for start, stop in _stretches(world.scheduled_ticks(), world.tick_count, ticks):
            t0 = time.perf_counter()
            world.tick(stop - start)
            dt = time.perf_counter() - t0
            wall += dt
            events += dt if stop - start == 1 and start in world.scheduled_ticks() else 0.0
        model = world.core.mj.model
        return Run(wall, events, model.nbody - 1, model.nv, {k: world.get(k) for k in OUTCOME})
    finally:
        world.close()


def _stretches(event_ticks: list[int], start: int, end: int) -> list[tuple[int, int]]:
    """[start, end) cut into runs of ticks without events and single ticks with one."""
    out, at = [], start
    for tick in sorted(t for t in event_ticks if start <= t < end):
        if tick > at:
            out.append((at, tick))
        out.append((tick, tick + 1))
        at = tick + 1
    if at < end:
        out.append((at, end))
    return out


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
    print("kitchen tray by the humanoid: only the kid, dishes, tray and board simulated, against the whole "
          "kitchen, in one run")
    for label, r in (("selected (7 of 104 objects)", sel), ("whole kitchen (104 objects)", all_)):
        print(f"   {label:<28} {r.bodies:4d} bodies {r.dof:4d} DoF: {r.wall_s:6.2f} s wall for {sim_s:g} s "
              f"simulated (of which {r.events_s:.2f} s at the ticks with events), real-time factor "
              f"{sim_s / r.wall_s:5.1f}")
    print(f"   speed-up of the selection: {all_.wall_s / sel.wall_s:.1f}x the whole run, "
          f"{(all_.wall_s - all_.events_s) / (sel.wall_s - sel.events_s):.1f}x the stepping alone (the ticks "
          "without events)")
    for key in OUTCOME:
        gap = float(np.linalg.norm(sel.outcome[key] - all_.outcome[key]))
        print(f"   {key} at the end: {np.round(sel.outcome[key], 4)} selected, {np.round(all_.outcome[key], 4)} "
              f"whole ({gap * 1000:.2f} mm apart)")


if __name__ == "__main__":
    main()
