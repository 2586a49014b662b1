"""The block task done by the humanoid (issue 23; the paper's Fig. 22 loop): see, model, plan, act.

The kid (`scenarios/models/kid.xml`) stands at a low table with three blocks stacked in front of it
(`scenarios/blocks_humanoid.yaml`). The blue block at the bottom must end on the pale target on its
left with no block on it; no block may fall to the floor. The brain:

1. *sees*: the scenario's servo program bows the kid over the table with its head down; its stereo eyes
   (`modules.stereo` on the head's camera) take a pair, and each block's size, pose and colour is
   recognised (`humanoid_eyes`, after `recognised_blocks`);
2. *models*: its own world is itself and its room without blocks (`scenarios/blocks_humanoid_brain.yaml`);
   the blocks it recognised it adds to it with `World.add_body` while it runs. Nothing of the scene's
   truth is copied;
3. *plans*: A* over hand pushes (`orchestrator.brain.plan.search`), each tried in its world: an action
   pushes one block left or right, slowly or fast, with a hand (`modules.pushing.HandPush`: the
   keyframes by whole-body IK, feet planted, the centre of mass over the soles; the servo drives the
   joints; hand and block meet through contact). The heuristic is the paper's: the blue block's distance
   to the target (in pushes) plus the blocks on it. A block on the floor, a fallen robot, the ZMP out of
   the soles or a keyframe the IK cannot reach makes a child of infinite cost, with its reason;
4. *acts*: the plan runs on the brain's own world (it ends as predicted, bit for bit), and, with
   ``--connect``, on a separate "real" world served over the bridge with a robot emulator on its robot
   link: each push's motion program, the servo ``sequence`` of its keyframes (`HandPush.program`), set
   on the served world's servo, which the robot link sends the robot as a program, in lock-step. The
   real blocks are not the recognised ones, so the outcome differs: the error is printed.

    .venv/bin/python examples/blocks_humanoid.py                 # see, plan (careful and dynamic), execute
    .venv/bin/python examples/blocks_humanoid.py --backend processes

    .venv/bin/dynabrain serve scenarios/blocks_humanoid.yaml --listen tcp/127.0.0.1:7447 --robot kid=servo &
    .venv/bin/dynabrain robot-emulator scenarios/blocks_humanoid.yaml --world blocks_humanoid --robot kid \\
        --connect tcp/127.0.0.1:7447 &
    .venv/bin/python examples/blocks_humanoid.py --connect tcp/127.0.0.1:7447

If the robot link is lost while the plan executes, the brain stops, names the tick and exits with 1.
It needs an offscreen renderer for the eyes; where none works it says so and stops.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from humanoid_eyes import blocks as recognise
from humanoid_eyes import faces
from recognised_blocks import Block

from dynabrain.modules.mujoco.offscreen import RendererUnavailableError
from dynabrain.modules.pushing import KEYFRAMES, PushCommand
from dynabrain.modules.stereo import StereoCamera
from dynabrain.orchestrator import World, load_world
from dynabrain.orchestrator.brain.plan import Action, Outcome, Plan, search

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "scenarios" / "blocks_humanoid.yaml"
BRAIN = ROOT / "scenarios" / "blocks_humanoid_brain.yaml"
ROBOT = "kid"
TABLE_TOP_M = 0.25
"""The table's top in the brain's own model of its room (models/blocks_humanoid_room.xml)."""
TARGET = np.array([0.16, 0.10])
"""The target's centre on the table, in the brain's model of its room."""
EYES = {"targets": ["eye"], "width": 320, "height": 240, "baseline": 0.06, "num_disparities": 128}
"""The head's stereo camera: 320 x 240 eyes 6 cm apart, about 15 cm above the stack while it looks."""
EYES_ON, LOOK = 880, 980
"""Ticks: the eyes open while the kid bows over the table (the servo program holds the bow 1.7-2.1 s),
and the pair is read."""
PLAN_AT = 1450
"""The tick the brain plans from: the kid is back in its crouch (2.7 s), the added blocks have settled."""
SETTLE_S = 0.3
"""Watched after a push's motion ends: the blocks come to rest."""
DIRECTIONS = ("left", "right")
"""The pushes the planner tries (`modules.pushing` also pushes away from the robot, but at this table
the hand cannot get between the robot and a block: every such push is out of reach)."""
PUSH_STEPS = 0.06
"""About how far a push moves a block (m): the heuristic counts the distance in pushes."""
FALLEN_Z = 0.2
"""The pelvis below this (m): the robot fell."""
ZMP_OUT_TICKS = 25
"""The ZMP outside the support polygon for more ticks than this (50 ms at the brain world's 2 ms step),
in all, during a push: the robot tips (a sample or two at the edge as the hand hits a block is not)."""
GOAL_M = 0.03
"""The blue block's centre within this of the target's."""
CHUNK_TICKS = 25
"""Ticks of the served world per lock-step call while a push plays (the robot's link is checked after each)."""


def look(scene: World) -> list[Block]:
    """The blocks the kid's eyes recognise in ``scene`` (at t=0: ticked to the look here)."""
    scene.tick(EYES_ON - scene.tick_count)
    scene.add_module(StereoCamera("eyes", **EYES), period="100ms")
    scene.tick(LOOK - scene.tick_count)
    return recognise(faces(scene), TABLE_TOP_M)


def see() -> list[Block]:
    """The blocks the kid recognises in the scene as it stands at t=0, or exit where no renderer works."""
    scene = load_world(SCENARIO)
    try:
        return look(scene)
    except RendererUnavailableError as exc:
        sys.exit(f"no offscreen renderer here, the kid's eyes cannot see: {exc}")
    finally:
        scene.close()


def brain_world(seen: list[Block], **overrides) -> World:
    """The brain's own world, run to the look, the blocks it saw added, run on to `PLAN_AT`."""
    world = load_world(BRAIN, **overrides)
    world.tick(LOOK)
    for block in seen:
        world.add_body(block.spec())
    world.tick(PLAN_AT - LOOK)
    return world


def actions(world: World, names: list[str], speeds=("slow", "fast"), directions=DIRECTIONS) -> list[Action]:
    """One action per block, direction and speed: the hand's push, then `SETTLE_S` of rest."""
    dt_s = world.dt_ns * 1e-9
    out = []
    for block in names:
        for direction in directions:
            for speed in speeds:
                name = f"{block} {direction} {speed}"
                ticks = round((PushCommand(block, direction, speed).seconds + SETTLE_S) / dt_s)
                out.append(Action(name, ticks, params={"hands.push": name}))
    return out


def record(names: list[str]) -> list[str]:
    """What the search records: the blocks, the pelvis, the ZMP, the hands (unreached keyframes, offsets)."""
    return [*(f"core.{b}.pos" for b in names), "core.pelvis.pos", "zmp.inside", "hands.unreached", "hands.q_ref"]


def blocks_on(block: str, pos: dict[str, np.ndarray]) -> int:
    """How many blocks stand on ``block`` (above its centre, within 3 cm of it sideways)."""
    under = pos[block]
    return sum(1 for b, p in pos.items()
               if b != block and p[2] > under[2] + 0.02 and np.all(np.abs(p[:2] - under[:2]) < 0.03))


def positions(o: Outcome) -> dict[str, np.ndarray]:
    return {name.split(".")[1]: o[name] for name in o.signals if name.endswith(".pos") and name != "core.pelvis.pos"}


def heuristic(o: Outcome) -> float:
    """The paper's: the blue block's distance to the target (in pushes) plus the blocks on it."""
    pos = positions(o)
    return float(np.linalg.norm(pos["blue"][:2] - TARGET)) / PUSH_STEPS + blocks_on("blue", pos)


def goal(o: Outcome) -> bool:
    pos = positions(o)
    return bool(np.linalg.norm(pos["blue"][:2] - TARGET) < GOAL_M) and blocks_on("blue", pos) == 0


def failed(o: Outcome) -> str | bool:
    """Infinite cost, with the reason: the IK could not reach, the robot fell or tipped, a block fell."""
    unreached = int(o["hands.unreached"])
    if unreached:
        return f"IK: the hand cannot reach the {KEYFRAMES[unreached - 1]} keyframe"
    if np.min(o.signals["core.pelvis.pos"][:, 2]) < FALLEN_Z:
        return "the robot fell"
    outside = int(np.count_nonzero(o.signals["zmp.inside"] < 1))
    if outside > ZMP_OUT_TICKS:
        return f"the ZMP left the support polygon (over {ZMP_OUT_TICKS} ticks)"
    for name, values in o.signals.items():
        if name.endswith(".pos") and name != "core.pelvis.pos" and np.min(values[:, 2]) < TABLE_TOP_M - 0.05:
            return f"{name.split('.')[1]} fell to the floor"
    return False


def careless(o: Outcome) -> str | bool:
    """The careful planner's rule: never move a block that has blocks on it, and only slowly."""
    block = o.action.name.split()[0]
    start = {name.split(".")[1]: o.parent.signals[name][-1] for name in o.signals
             if name.endswith(".pos") and name != "core.pelvis.pos"}
    if blocks_on(block, start):
        return f"moved {block} with blocks on it"
    return failed(o)


def plan(world: World, names: list[str], *, careful: bool = False, backend: str = "auto", batch=None,
         max_expansions: int = 40, movers: list[str] | None = None, speeds=None,
         directions=DIRECTIONS) -> Plan:
    """A* over hand pushes (one push costs 1) of the blocks ``names`` (``movers``: those pushed; default
    all); ``careful``: slow pushes of blocks with nothing on them."""
    speeds = speeds or (("slow",) if careful else ("slow", "fast"))
    return search(world, actions(world, movers or names, speeds, directions), record=record(names),
                  heuristic=heuristic,
                  goal=goal, failed=careless if careful else failed, cost=lambda o: 1.0, backend=backend,
                  batch=batch, max_expansions=max_expansions, max_depth=6)


def pushes(n: int) -> str:
    return f"{n} push" if n == 1 else f"{n} pushes"


def describe(name: str, p: Plan) -> str:
    steps = " -> ".join(a.name for a in p.actions) or "(none)"
    reasons = sorted({reason for _path, reason in p.stats.failed})
    return (f"{name}: {'found' if p.found else 'NO PLAN (best node shown)'} in {p.stats.wall_s:.2f} s, "
            f"{pushes(len(p.actions))}: {steps}\n"
            f"   {p.stats.expanded} nodes expanded, {p.stats.generated} simulated ({p.stats.nodes_per_s:.1f}/s, "
            f"{p.stats.ticks / max(p.stats.wall_s, 1e-9):.0f} ticks/s) in {p.stats.batches} batches; "
            f"{len(p.stats.failed)} children refused" + (f" ({'; '.join(reasons)})" if reasons else ""))


def execute(world: World, p: Plan) -> bool:
    """Run the plan on ``world`` from its start state; whether it recorded what was predicted, bit for bit."""
    world.import_state(p.states[0])
    done = p.execute(world)
    return all(done[k].tobytes() == p.trajectory[k].tobytes() for k in p.trajectory)


def programs(world: World, p: Plan) -> list[tuple[Action, list[dict]]]:
    """Each action of the plan with the servo ``sequence`` its push played in the brain's world: the
    whole-body IK keyframes solved when the push began (`HandPush.program`), in absolute joint angles."""
    out = []
    for action, state in zip(p.actions, p.states, strict=False):
        world.import_state(state)
        for name, value in action.params.items():
            world.set(name, value)
        world.tick(1)  # the push begins at the step after its parameter is set
        out.append((action, world.modules["hands"].program))
    return out


def execute_remote(world: World, p: Plan, names: list[str], connect: str, served: str = "blocks_humanoid",
                   chunk: int = CHUNK_TICKS, ticked: Callable[[int], None] | None = None) -> dict[str, np.ndarray]:
    """Run the plan on the world served at ``connect`` (blocks_humanoid.yaml at t=0, with the robot rig
    ``kid``): tick it to the plan's start, then, for each push, set its servo's ``sequence`` to the push's
    motion program (`programs`; the link sends it to the robot as a program, which the robot plays on
    its own clock) and tick the push's length, in lock-step, ``chunk`` ticks at a time (``ticked``, if
    given, is called with the served world's tick after each chunk); the next push waits until the robot
    has played this one. Returns the blocks' final positions there. Raises the bridge's `RobotLostError`
    (naming the tick) when the robot goes away, `RobotStoppedError` when it does not play a push."""
    from dynabrain.bridge import BrainClient
    from dynabrain.bridge.errors import RobotLostError

    motions = programs(world, p)
    client = BrainClient(served, connect=connect)
    try:
        client.acquire()
        tick = client.status()["tick"]
        if tick > PLAN_AT:
            raise SystemExit(f"the served world is at tick {tick}, past the plan's start ({PLAN_AT}): serve it afresh")
        if tick < PLAN_AT:
            tick = client.tick(PLAN_AT - tick)
        client.robot_enable(ROBOT)
        for action, steps in motions:
            client.set("servo.sequence", steps)
            for done in range(0, action.ticks, chunk):
                tick = client.tick(min(chunk, action.ticks - done))
                if ticked is not None:
                    ticked(tick)
                status = client.robot_status(ROBOT)
                if not status["alive"]:
                    lost = status.get("lost_tick") or tick
                    raise RobotLostError(ROBOT, lost, f"the robot link was lost at tick {lost}, in '{action.name}' "
                                                      "(its liveliness token went away): the brain stops")
            client.robot_wait(ROBOT, timeout=action.ticks * world.dt_ns * 1e-9 + 10.0)  # on its own clock
        return {b: np.asarray(client.get(f"core.{b}.pos")) for b in names}
    finally:
        client.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--backend", default="auto", help="batch backend for the search (serial, processes, ...)")
    ap.add_argument("--careful", action="store_true", help="only the careful planner")
    ap.add_argument("--max-expansions", type=int, default=40)
    ap.add_argument("--connect", help="also execute on the blocks_humanoid world served at this Zenoh endpoint")
    opts = ap.parse_args()
    seen = see()
    print(f"seen {len(seen)} blocks: " + "; ".join(
        f"{b.colour} {np.round(np.multiply(b.size, 1000)).astype(int).tolist()} mm at "
        f"{np.round(b.pos, 3).tolist()}" for b in seen))
    names = [b.colour for b in seen]
    world = brain_world(seen)
    try:
        found = {}
        for name, careful in (("careful (one free block at a time, slowly)", True),
                              ("with the simulator (slow and fast, any block)", False)):
            if opts.careful and not careful:
                continue
            found[name] = p = plan(world, names, careful=careful, backend=opts.backend,
                                   max_expansions=opts.max_expansions)
            print(describe(name, p))
        if len(found) == 2:
            polite, dynamic = found.values()
            wins = dynamic.found and (not polite.found or len(dynamic.actions) < len(polite.actions))
            print(f"the dynamic plan takes {pushes(len(dynamic.actions))}, the careful one "
                  f"{pushes(len(polite.actions))}{'' if polite.found else ' (not found)'}: "
                  f"{'the dynamic plan wins' if wins else 'no gain'}")
        best = min(found.values(), key=lambda p: (not p.found, len(p.actions)))
        t0 = time.perf_counter()
        same = execute(world, best)
        print(f"executed on the brain's world in {time.perf_counter() - t0:.2f} s: the outcome "
              f"{'equals' if same else 'DIFFERS FROM'} the prediction bit for bit")
        if opts.connect:
            predicted = {b: best.trajectory[f"core.{b}.pos"][-1] for b in names}
            from dynabrain.bridge.errors import RobotLostError, RobotStoppedError

            try:
                real = execute_remote(world, best, names, opts.connect)
            except (RobotLostError, RobotStoppedError) as exc:
                print(f"stopped: {exc}")
                sys.exit(1)
            print("executed on the served world with the robot: the blocks end " + ", ".join(
                f"{b} {np.linalg.norm(real[b] - predicted[b]) * 100:.1f} cm" for b in names) + " from the prediction")
    finally:
        world.close()


if __name__ == "__main__":
    main()
