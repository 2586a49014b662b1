"""The humanoid keeps its balance by receding-horizon control on imagined futures, under pushes.

The world: `scenarios/humanoid_stand.yaml` (the kid in its crouch, servo, encoders, ZMP and force
sensors). A push is a horizontal force on the pelvis (``core.pelvis.wrench``) for 0.1 s, from one of
``--pushes`` directions spread round the robot. Each push is tried twice from the same standing state:

- without a brain: the servo holds the crouch;
- with MPC: every ``--every`` the brain imagines ``--samples`` futures of ``--horizon`` from the latest
  state, each with other ankle and hip offsets (pitch and roll, both legs alike), scores them by how far
  the pelvis strays from over the feet and how fast it moves (a fall costs a lot), and plays the best
  (`orchestrator/brain/mpc.py`).

It prints the falls out of the pushes each way, and how the planner kept up with simulated time.

    .venv/bin/python examples/balance_mpc.py [--force 21] [--pushes 20] [--samples 16] [--backend processes]
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from dynabrain.orchestrator import load_world
from dynabrain.orchestrator.brain.mpc import Control, Futures, Mpc, MpcStats

ROOT = Path(__file__).resolve().parents[1]
STAND = ROOT / "scenarios" / "humanoid_stand.yaml"
RECORD = ["core.pelvis.pos", "core.pelvis.linvel"]
STANDING_Z = 0.293
"""The pelvis's height in the crouch (m)."""
FALLEN_Z = 0.2
"""Below this the robot has fallen (m)."""
PUSH_S = 0.1
AFTER_S = 1.5
"""How long a trial lasts after the push begins (s)."""


def ankles_and_hips(reach: float = 0.35, spread: float = 0.1) -> dict[str, Control]:
    """Offsets added to the crouch's targets (rad), both legs alike: the ankle and hip strategies, sampled
    ``spread`` rad around the plan (a balance correction is small and quick)."""
    pair = {"ankle_pitch": ("l_ankle_pitch", "r_ankle_pitch"), "hip_pitch": ("l_hip_pitch", "r_hip_pitch"),
            "ankle_roll": ("l_ankle_roll", "r_ankle_roll"), "hip_roll": ("l_hip_roll", "r_hip_roll")}
    return {name: Control([f"servo.{j}.q_ref" for j in joints], -reach, reach, noise=spread)
            for name, joints in pair.items()}


def balance_cost(home_xy: np.ndarray):
    def cost(f: Futures) -> np.ndarray:
        pos, vel = f["core.pelvis.pos"], f["core.pelvis.linvel"]
        stray = np.sum((pos[..., :2] - home_xy) ** 2, axis=-1).mean(axis=1)
        sag = ((pos[..., 2] - STANDING_Z) ** 2).mean(axis=1)
        speed = np.sum(vel ** 2, axis=-1).mean(axis=1)
        fallen = (pos[..., 2].min(axis=1) < FALLEN_Z + 0.03) * 10.0
        effort = sum(np.mean(u ** 2, axis=1) for u in f.controls.values())  # act only as much as needed
        return 100 * stray + 100 * sag + speed + fallen + 0.5 * effort

    return cost


def trial(world, direction_rad: float, force_n: float, mpc: Mpc | None, every: float) -> bool:
    """Push, then let the robot (and its brain) react for `AFTER_S`; True if it fell."""
    dt = world.dt_ns * 1e-9
    push = [force_n * math.cos(direction_rad), force_n * math.sin(direction_rad), 0, 0, 0, 0]
    world.set("core.pelvis.wrench", push)
    if mpc is None:
        world.tick(round(PUSH_S / dt))
        world.set("core.pelvis.wrench", [0.0] * 6)
        world.tick(round((AFTER_S - PUSH_S) / dt))
    else:
        mpc.run(world, PUSH_S, every=every)
        world.set("core.pelvis.wrench", [0.0] * 6)
        mpc.run(world, AFTER_S - PUSH_S, every=every)
    return bool(world.get("core.pelvis.pos")[2] < FALLEN_Z)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--force", type=float, default=21.0, help="N, on the pelvis for 0.1 s")
    ap.add_argument("--pushes", type=int, default=20)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--horizon", type=float, default=0.6, help="seconds")
    ap.add_argument("--every", type=float, default=0.05, help="seconds between replans")
    ap.add_argument("--backend", default="auto")
    opts = ap.parse_args()
    directions = [2 * math.pi * k / opts.pushes for k in range(opts.pushes)]
    with load_world(STAND) as world:
        world.tick(500)  # into the crouch
        standing = world.snapshot()
        home = np.array(world.get("core.pelvis.pos")[:2])
        falls_alone = []
        for a in directions:
            world.restore(standing)
            falls_alone.append(trial(world, a, opts.force, None, opts.every))
        falls_mpc = []
        stats = MpcStats()
        t0 = time.perf_counter()
        world.restore(standing)
        with Mpc(world, ankles_and_hips(), balance_cost(home), record=RECORD, horizon=opts.horizon, knots=3,
                 samples=opts.samples, method="mppi", backend=opts.backend, name="balance",
                 assume={"core.pelvis.wrench": np.zeros(6)}) as mpc:  # it feels a push, cannot know it goes on
            standing = world.snapshot()  # the same state, with the plan's player added
            for a in directions:
                world.restore(standing)
                mpc.reset()  # each push from the standing state, with no plan yet
                falls_mpc.append(trial(world, a, opts.force, mpc, opts.every))
            stats = mpc.stats
        wall = time.perf_counter() - t0
    simulated = opts.pushes * AFTER_S
    print(f"{opts.pushes} pushes of {opts.force:g} N for {PUSH_S:g} s on the pelvis, directions all round:")
    print(f"  the servo holding the crouch: {sum(falls_alone)} falls "
          f"({', '.join(f'{math.degrees(a):.0f} deg' for a, f in zip(directions, falls_alone, strict=True) if f)})")
    print(f"  MPC on the ankles and hips:   {sum(falls_mpc)} falls "
          f"({', '.join(f'{math.degrees(a):.0f} deg' for a, f in zip(directions, falls_mpc, strict=True) if f)})")
    print(f"  MPC: {stats.summary()}; {stats.replans / simulated:.0f} replans a simulated second, "
          f"{wall / simulated:.1f} s of wall time a simulated second")


if __name__ == "__main__":
    main()
