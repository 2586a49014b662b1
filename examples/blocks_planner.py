"""The paper's block-moving task, planned by simulating (EusDyna, Figs. 22-24).

Three blocks are stacked on a table (`scenarios/blocks.yaml`). The bottom block must end on the green
target on the left with no block on it, and no block may fall to the floor. The brain searches with
A* over pushes, every push tried in its simulator: an action moves one block 25 cm in one of four
directions, slowly and carefully or fast, through the block's velocity input (a hand that moves the
block and stops it where it wanted). The heuristic is the paper's: the distance to the target (in
pushes) plus the number of blocks on the target block; a block on the floor costs infinity. States
whose blocks stand in the same centimetre cells are one state to the search (its closed set); each
planner is run again without it, and the nodes it expanded printed beside.

A careful planner moves the upper blocks away one by one before it moves the bottom one. Allowed to
push fast, the brain finds the rougher plan a human would use: pull the bottom block out from under
the others, then push it on.

    .venv/bin/python examples/blocks_planner.py               # plan with fast pushes, compare, execute
    .venv/bin/python examples/blocks_planner.py --careful     # only the careful planner
    .venv/bin/python examples/blocks_planner.py --no-compare  # not again without the closed set
    .venv/bin/python examples/blocks_planner.py --log runs/blocks.mcap   # the run and the plan, in Foxglove

    .venv/bin/dynabrain serve scenarios/blocks.yaml &                   # a world served over Zenoh
    .venv/bin/python examples/blocks_planner.py --connect tcp/127.0.0.1:7447

With ``--connect`` the plan found is also executed on the served world over the Zenoh bridge (the
brain's inputs sent a tick at a time, as a remote brain drives its robot): it ends where the brain
predicted, bit for bit, because it is the same simulation.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from dynabrain.orchestrator import load_world
from dynabrain.orchestrator.brain.plan import Action, Outcome, Plan, search

SCENARIO = Path(__file__).resolve().parents[1] / "scenarios" / "blocks.yaml"
BLOCKS = ("base", "mid", "top")
TARGET = np.array([-0.35, 0.0])
STEP_M = 0.25
"""How far one push moves a block."""
TICKS = 600
"""Ticks of one action (1.2 s): the push, the stop, and the blocks settling."""
SPEEDS = {"slow": (0.4, 1.0), "fast": (2.5, 200.0)}
"""Top speed (m/s) and acceleration (m/s^2) of a push: a slow push speeds up gently (well under the
friction that holds the blocks on it, 0.6 g), a fast one at once."""
DIRECTIONS = {"left": (-1.0, 0.0), "right": (1.0, 0.0), "front": (0.0, -1.0), "back": (0.0, 1.0)}
SETTLE = 50
"""Ticks the stack settles before the brain plans."""
RECORD = [f"core.{b}.{q}" for b in BLOCKS for q in ("pos", "quat")]
"""What the search records: positions for the heuristic; with the orientations, a kept plan shows in
Foxglove as the blocks' predicted poses (``/imagined/blocks/0/tf``)."""
TABLE_TOP = 0.4


def push(block: str, direction: str, speed: str, dt_s: float) -> Action:
    """Move ``block`` one step in ``direction``: its velocity follows a trapezoid (speed up, travel,
    slow down), is held at zero for a few ticks (the hand stops it), then is left alone (NaN) while
    everything settles."""
    vx, vy = DIRECTIONS[direction]
    top, accel = SPEEDS[speed]
    duration = STEP_M / top + top / accel
    t = (np.arange(round(duration / dt_s)) + 0.5) * dt_s
    profile = np.minimum.reduce([accel * t, np.full_like(t, top), accel * (duration - t)])
    travel = len(profile)
    values = np.full((TICKS, 6), np.nan)
    values[:travel, 0], values[:travel, 1] = vx * profile, vy * profile
    values[travel:travel + 5, :2] = 0.0
    return Action(f"{block} {direction} {speed}", TICKS, inputs={f"core.{block}.velocity": values})


def actions(dt_s: float, speeds: tuple[str, ...]) -> list[Action]:
    return [push(b, d, s, dt_s) for b in BLOCKS for d in DIRECTIONS for s in speeds]


def blocks_on(block: str, pos: dict[str, np.ndarray]) -> int:
    """How many blocks stand on ``block`` (above it, over its top)."""
    under = pos[block]
    return sum(1 for b in BLOCKS if b != block and pos[b][2] > under[2] + 0.04
               and np.all(np.abs(pos[b][:2] - under[:2]) < 0.08))


def positions(o: Outcome, row: int = -1) -> dict[str, np.ndarray]:
    return {b: o.signals[f"core.{b}.pos"][row] for b in BLOCKS}


def blocks_on_base(o: Outcome) -> int:
    return blocks_on("base", positions(o))


def heuristic(o: Outcome) -> float:
    """The paper's: distance to the target (in pushes) plus the number of blocks on the target block."""
    return float(np.linalg.norm(o["core.base.pos"][:2] - TARGET)) / STEP_M + blocks_on_base(o)


def goal(o: Outcome) -> bool:
    return bool(np.linalg.norm(o["core.base.pos"][:2] - TARGET) < 0.05) and blocks_on_base(o) == 0


def fell(o: Outcome) -> str | bool:
    """A block on the floor: infinite cost."""
    for b in BLOCKS:
        if np.min(o.signals[f"core.{b}.pos"][:, 2]) < TABLE_TOP - 0.05:
            return f"{b} fell to the floor"
    return False


def careless(o: Outcome) -> str | bool:
    """The careful planner's rule: never move a block that has blocks on it (then as `fell`)."""
    block = o.action.name.split()[0]
    if blocks_on(block, start_positions(o)):
        return f"moved {block} with blocks on it"
    return fell(o)


def start_positions(o: Outcome) -> dict[str, np.ndarray]:
    """Where the blocks stood when the action began (what the parent node recorded last)."""
    return {b: o.parent.signals[f"core.{b}.pos"][-1] for b in BLOCKS}


GRID_M = 0.01
"""The closed set's grid: two states whose blocks stand in the same centimetre cells are one (a push
and its reverse bring the stack back to where it was, give or take a few millimetres)."""


def cells(o: Outcome) -> tuple:
    """The search's key of a state: each block's position on the `GRID_M` grid."""
    return tuple(tuple(np.round(o.signals[f"core.{b}.pos"][-1] / GRID_M).astype(int).tolist()) for b in BLOCKS)


def plan(world, speeds: tuple[str, ...], *, careful: bool = False, backend: str = "auto", batch=None,
         max_expansions: int = 300, closed: bool = True) -> Plan:
    """A* over pushes (one push costs 1). ``careful``: only blocks with nothing on them are moved, as a
    symbolic planner that does not simulate would insist. ``closed=False``: no closed set (a tree
    search, every sequence of pushes its own node), to compare."""
    return search(world, actions(world.dt_ns * 1e-9, speeds), record=RECORD, heuristic=heuristic, goal=goal,
                  failed=careless if careful else fell, cost=lambda o: 1.0, backend=backend, batch=batch,
                  max_expansions=max_expansions, key=cells, closed=closed)


def describe(name: str, p: Plan) -> str:
    steps = " -> ".join(a.name for a in p.actions) or "(none)"
    return (f"{name}: {'found' if p.found else 'NO PLAN (best node shown)'} in {p.stats.wall_s:.2f} s, "
            f"{len(p.actions)} pushes: {steps}\n"
            f"   {p.stats.expanded} nodes expanded, {p.stats.generated} simulated ({p.stats.nodes_per_s:.0f}/s) "
            f"in {p.stats.batches} batches, {len(p.stats.failed)} children refused (a block fell, or the careful "
            f"rule), {p.stats.duplicates} dropped (a state seen before)")


def execute_remote(p: Plan, connect: str, settle_ticks: int) -> dict[str, np.ndarray]:
    """Run the plan on the world served at ``connect`` (the blocks scenario at t=0): settle as the brain
    did, then each action's inputs a tick at a time; returns the blocks' final positions."""
    from dynabrain.bridge import BrainClient

    client = BrainClient("blocks", connect=connect)
    try:
        client.acquire()
        if client.status()["tick"] != 0:
            raise SystemExit("the served world has ticked already: serve scenarios/blocks.yaml afresh")
        client.tick(settle_ticks)
        for action in p.actions:
            (name, values), = action.inputs.items()
            for row in values:
                client.set(name, row)
                client.tick(1)
        return {b: np.asarray(client.get(f"core.{b}.pos")) for b in BLOCKS}
    finally:
        client.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--careful", action="store_true", help="only the careful planner")
    ap.add_argument("--backend", default="auto", help="batch backend for the search (serial, processes, ...)")
    ap.add_argument("--log", type=Path, help="record the executed run and the plan to this MCAP file")
    ap.add_argument("--connect", help="also execute the plan on the blocks world served at this Zenoh endpoint")
    ap.add_argument("--no-compare", dest="compare", action="store_false",
                    help="do not plan again without the closed set (a tree search) to compare")
    opts = ap.parse_args()
    world = load_world(SCENARIO)
    try:
        logger = None
        if opts.log is not None:
            from dynabrain.orchestrator.logs.logger import McapLogger

            opts.log.parent.mkdir(parents=True, exist_ok=True)
            logger = McapLogger(opts.log).attach(world)
        world.tick(SETTLE)  # the stack settles
        found = {}
        for name, careful in (("careful (one block at a time, slowly)", True),
                              ("with the simulator (slow and fast, any block)", False)):
            if opts.careful and not careful:
                continue
            speeds = ("slow",) if careful else ("slow", "fast")
            found[name] = p = plan(world, speeds, careful=careful, backend=opts.backend)
            print(describe(name, p))
            if opts.compare:
                tree = plan(world, speeds, careful=careful, backend=opts.backend, closed=False)
                print(f"   without the closed set: {tree.stats.expanded} nodes expanded, {tree.stats.generated} "
                      f"simulated, {len(tree.actions)} pushes (cost {tree.cost:g}; with it {p.cost:g})")
        best = min(found.values(), key=lambda p: (not p.found, len(p.actions)))
        if len(found) == 2:
            polite, dynamic = found.values()
            print(f"planning with the simulator takes {len(dynamic.actions)} pushes where the careful plan takes "
                  f"{len(polite.actions)}: {'it wins' if len(dynamic.actions) < len(polite.actions) else 'no gain'}")
        if logger is not None:
            best.imagine(world, "blocks")
        t0 = time.perf_counter()
        world.import_state(best.states[0])
        done = best.execute(world)
        same = all(done[k].tobytes() == best.trajectory[k].tobytes() for k in RECORD)
        base = world.get("core.base.pos")
        verdict = "equals" if same else "DIFFERS FROM"
        print(f"executed on the world in {time.perf_counter() - t0:.2f} s: outcome {verdict} the prediction bit "
              f"for bit; the base block ends at ({base[0]:+.3f}, {base[1]:+.3f}), "
              f"{np.linalg.norm(base[:2] - TARGET) * 100:.1f} cm from the target")
        if opts.connect:
            t0 = time.perf_counter()
            remote = execute_remote(best, opts.connect, SETTLE)
            same = all(remote[b].tobytes() == best.trajectory[f"core.{b}.pos"][-1].tobytes() for b in BLOCKS)
            print(f"executed on the served world over Zenoh in {time.perf_counter() - t0:.2f} s: the blocks end "
                  f"{'where predicted, bit for bit' if same else 'ELSEWHERE than predicted'}")
    finally:
        world.close()


if __name__ == "__main__":
    main()
