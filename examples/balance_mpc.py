"""The humanoid keeps its balance by receding-horizon control on imagined futures: pushes, and the earthquake.

**Pushes.** The world: `scenarios/humanoid_stand.yaml` (the kid in its crouch, servo, encoders, ZMP and
force sensors). A push is a horizontal force on the pelvis (``core.pelvis.wrench``) for 0.1 s, from one
of ``--pushes`` directions spread round the robot. Each push is tried twice from the same standing state:

- without a brain: the servo holds the crouch;
- with MPC: every ``--every`` the brain imagines ``--samples`` futures of ``--horizon`` from the latest
  state, each with other ankle and hip offsets (pitch and roll, both legs alike), scores them by how far
  the pelvis strays from over the feet and how fast it moves (a fall costs a lot), and plays the best
  (`orchestrator/brain/mpc.py`).

**The earthquake.** The world: `scenarios/balance_quake.yaml`, the paper's fast floor (tilting +-10 degrees
at 1 Hz, sliding +-4 cm at 2 Hz: EusDyna's robot fell there), and a milder one (7 degrees, 2 cm). Each is
tried with the servo alone, with the paper's stabilizer (the ankle strategy on the ZMP), with MPC in step
with the world (the world waits while the brain plans: 20 replans a simulated second, 16 futures of 0.5
s), and with MPC in real time (the world ticks at wall-clock speed while the brain replans in a thread
from the latest state, 10 replans a simulated second, 8 futures of 0.4 s, its delay compensated). The
brain's futures hold the floor too: it imagines the quake it stands on. The cost scores the pelvis's
stray from over the feet, its lean, its speed against the feet's, and a fall.

It prints the falls, when each fall came, and how the planner kept up with simulated time.

    .venv/bin/python examples/balance_mpc.py [--part pushes|quake|both] [--force 21] [--pushes 20]
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from dynabrain.modules.stabilizer import Stabilizer
from dynabrain.orchestrator import load_world
from dynabrain.orchestrator.brain.mpc import Control, Futures, Mpc, MpcStats

ROOT = Path(__file__).resolve().parents[1]
STAND = ROOT / "scenarios" / "humanoid_stand.yaml"
QUAKE = ROOT / "scenarios" / "balance_quake.yaml"
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


def pitch_strategies(reach: float = 0.4, spread: float = 0.1) -> dict[str, Control]:
    """Ankle and hip pitch offsets (rad), both legs alike: the floor tilts about y and slides along x."""
    pair = {"ankle_pitch": ("l_ankle_pitch", "r_ankle_pitch"), "hip_pitch": ("l_hip_pitch", "r_hip_pitch")}
    return {name: Control([f"servo.{j}.q_ref" for j in joints], -reach, reach, noise=spread)
            for name, joints in pair.items()}


QUAKE_RECORD = ["core.pelvis.pos", "core.pelvis.linvel", "core.pelvis.quat", "core.l_foot.pos", "core.r_foot.pos",
                "core.l_foot.linvel"]


def quake_cost(f: Futures) -> np.ndarray:
    """On a moving floor: the pelvis over the middle of the feet, upright, moving with the feet, not fallen."""
    pos = f["core.pelvis.pos"]
    mid = (f["core.l_foot.pos"][..., :2] + f["core.r_foot.pos"][..., :2]) / 2
    stray = np.sum((pos[..., :2] - mid) ** 2, axis=-1).mean(axis=1)
    q = f["core.pelvis.quat"]  # (w, x, y, z): the horizontal part of the pelvis's z axis is its lean
    lean_x = 2 * (q[..., 1] * q[..., 3] + q[..., 0] * q[..., 2])
    lean_y = 2 * (q[..., 2] * q[..., 3] - q[..., 0] * q[..., 1])
    lean = (lean_x ** 2 + lean_y ** 2).mean(axis=1)
    speed = np.sum((f["core.pelvis.linvel"] - f["core.l_foot.linvel"]) ** 2, axis=-1).mean(axis=1)
    fallen = (pos[..., 2].min(axis=1) < FALLEN_Z + 0.03) * 10.0
    effort = sum(np.mean(u ** 2, axis=1) for u in f.controls.values())
    return 100 * stray + 10 * lean + speed + fallen + 0.5 * effort


def quake_world(tilt_deg: float, slide_m: float, stabilizer: bool):
    """The quake's world just after the floor joined (1 s), the floor set to ``tilt_deg`` and ``slide_m``;
    with the paper's stabilizer added at 0.8 s, as earthquake_fast.yaml adds it."""
    world = load_world(QUAKE)
    world.tick(400)
    if stabilizer:
        world.add_module(Stabilizer("stabilizer", ki=8, filter=0.2), period="10ms", connect=[
            ("zmp.zmp", "stabilizer.zmp"), ("zmp.center", "stabilizer.center"),
            ("stabilizer.pitch", "servo.l_ankle_pitch.q_ref"), ("stabilizer.pitch", "servo.r_ankle_pitch.q_ref"),
            ("stabilizer.roll", "servo.l_ankle_roll.q_ref"), ("stabilizer.roll", "servo.r_ankle_roll.q_ref")])
    world.tick(101)
    world.set("quake.tilt_amplitude", math.radians(tilt_deg))
    world.set("quake.amplitude", slide_m)
    return world


def quake_trial(tilt_deg: float, slide_m: float, brain: str, seconds: float, backend: str = "lockstep",
                futures: tuple[int, float, float] | None = None) -> tuple[float | None, str]:
    """``seconds`` of the quake with ``brain`` ("servo", "stabilizer", "mpc", "mpc-realtime"): (the time of
    the fall, or None; what the planner said). ``futures``: (samples, horizon s, every s) of the MPC."""
    world = quake_world(tilt_deg, slide_m, brain == "stabilizer")
    heights: list[tuple[float, float]] = []
    said = ""
    try:
        if brain in ("servo", "stabilizer"):
            for _ in range(round(seconds / 0.1)):
                world.tick(50)
                heights.append((world.time, world.get("core.pelvis.pos")[2]))
        else:
            realtime = brain == "mpc-realtime"
            samples, horizon, every = futures or ((8, 0.4, 0.1) if realtime else (16, 0.5, 0.05))
            with Mpc(world, pitch_strategies(), quake_cost, record=QUAKE_RECORD, horizon=horizon, knots=3,
                     samples=samples, method="mppi", backend=backend, name="quake") as mpc:
                if realtime:
                    world.start(realtime=True, until=world.time + seconds)
                    mpc.start(every=every)
                    while not world.wait(0.1):
                        heights.append((world.time, world.get("core.pelvis.pos")[2]))
                    stats = mpc.stop()
                else:
                    for _ in range(round(seconds / 0.1)):
                        mpc.run(world, 0.1, every=every)
                        heights.append((world.time, world.get("core.pelvis.pos")[2]))
                    stats = mpc.stats
                said = (f"{samples} futures of {horizon:g} s, {stats.replans / seconds:.0f} replans a simulated "
                        f"second; {stats.summary()}")
        heights.append((world.time, world.get("core.pelvis.pos")[2]))
    finally:
        world.close()
    return next((t for t, z in heights if z < FALLEN_Z), None), said


def quake(opts: argparse.Namespace) -> None:
    seconds = 3.0
    print(f"the earthquake floor (scenarios/balance_quake.yaml), {seconds:g} s from when it joins:")
    for tilt, slide in ((10.0, 0.04), (7.0, 0.02)):
        print(f"  tilting +-{tilt:g} deg at 1 Hz, sliding +-{slide * 100:g} cm at 2 Hz:")
        for brain in ("servo", "stabilizer", "mpc", "mpc-realtime"):
            fell, said = quake_trial(tilt, slide, brain, seconds, opts.backend)
            what = f"falls at {fell:.1f} s" if fell is not None else "stands"
            print(f"    {brain:<13} {what:<16} {said}")


def pushes(opts: argparse.Namespace) -> None:
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=("pushes", "quake", "both"), default="both")
    ap.add_argument("--force", type=float, default=21.0, help="N, on the pelvis for 0.1 s")
    ap.add_argument("--pushes", type=int, default=20)
    ap.add_argument("--samples", type=int, default=16, help="futures a replan (pushes)")
    ap.add_argument("--horizon", type=float, default=0.6, help="seconds (pushes)")
    ap.add_argument("--every", type=float, default=0.05, help="seconds between replans (pushes)")
    ap.add_argument("--backend", default="lockstep")
    opts = ap.parse_args()
    if opts.part in ("pushes", "both"):
        pushes(opts)
    if opts.part in ("quake", "both"):
        quake(opts)


if __name__ == "__main__":
    main()
