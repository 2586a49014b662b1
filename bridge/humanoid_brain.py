"""An example brain for the humanoid: it stands, plans a motion sequence in a fork of the served world,
retries a keyframe that would topple the robot with a backtick, and then plays the plan on the world,
which does exactly what the plan predicted.

The world is ``scenarios/humanoid_stand.yaml`` (the 23-joint "kid" on PD servos that play timed
angle-vectors, a ZMP sensor under its soles). The brain drives the servo's motion program
(``servo.sequence``, see `dynabrain.modules.servo`):

1. *stand*: let the scenario's own program bring the robot into its crouch, and wait until it is still;
2. *a motion sequence*, planned in a fork: spread the arms, bow with the arms forward, stand up again.
   Each keyframe is tried in the fork and watched: the ZMP must stay ``MARGIN`` inside the support
   polygon and the pelvis must not drop (a fall). When the prediction fails, the brain goes back to
   before the keyframe (``backtick``) and tries a milder, slower version of it;
3. *execute*: the same keyframes at the same ticks on the served world (lock-step), then compare its
   state with the plan's prediction: with exact rollback they are identical, bit for bit.

    dynabrain serve scenarios/humanoid_stand.yaml --listen tcp/127.0.0.1:7447 &
    python -m dynabrain.bridge.humanoid_brain --connect tcp/127.0.0.1:7447
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .client import BrainClient
from .replies import View

CROUCH = {"l_hip_pitch": -15, "r_hip_pitch": -15, "l_knee": 30, "r_knee": 30, "l_ankle_pitch": -15,
          "r_ankle_pitch": -15, "l_shoulder_roll": 10, "r_shoulder_roll": -10, "l_elbow": -30, "r_elbow": -30}
"""The scenario's standing pose (degrees; the other joints at 0)."""
SEQUENCE = (
    ("spread the arms", {"l_shoulder_roll": 90, "r_shoulder_roll": -90}, 0.6),
    ("bow with the arms forward", {"l_hip_pitch": -60, "r_hip_pitch": -60, "l_shoulder_pitch": -90,
                                   "r_shoulder_pitch": -90, "l_shoulder_roll": 10, "r_shoulder_roll": -10}, 0.25),
    ("stand up again", {**CROUCH, "l_shoulder_pitch": 0, "r_shoulder_pitch": 0}, 0.6),
)
"""(name, {joint: degrees}, seconds) keyframes; joints a keyframe does not name keep their angle."""
MARGIN = 0.015
"""A keyframe fails when the ZMP comes closer than this (m) to the edge of the support polygon."""
FALLEN_Z = 0.25
"""... or when the pelvis drops below this height (m): the robot is falling."""
SETTLE = 0.4
"""Seconds watched after a keyframe's motion ends."""
MILDER, SLOWER = 0.6, 1.5
"""A retry moves this fraction of the failed keyframe's change, this many times slower."""
CHUNK = 10
"""Ticks per round trip while watching."""
WATCH = ["zmp.margin", "pelvis.pos", "pelvis.linvel"]
COMPARE = ["core.joint_q", "core.joint_qd", "pelvis.pos", "pelvis.quat"]


@dataclass
class Keyframe:
    name: str
    pose: dict[str, float]
    seconds: float
    tries: int = 1
    ticks: int = 0
    margin: float = 0.0
    history: list[str] = field(default_factory=list)

    def sequence(self) -> list[dict]:
        """The servo's ``sequence`` parameter for this keyframe."""
        return [{"pose": self.pose, "duration": f"{self.seconds:.3f}s"}]


def watch(world: BrainClient, view: View, ticks: int) -> tuple[float, float]:
    """Tick ``ticks`` steps in chunks; (smallest ZMP margin, lowest pelvis height) seen."""
    margin, low, done = np.inf, np.inf, 0
    while done < ticks:
        n = min(CHUNK, ticks - done)
        frame = world.tick(n, view=view)
        done += n
        margin, low = min(margin, frame["zmp.margin"]), min(low, frame["pelvis.pos"][2])
    return float(margin), float(low)


def stand(world: BrainClient, view: View, dt: float, log: Callable[[str], None]) -> int:
    """Tick until the scenario's program has brought the robot into its crouch and it is still; the ticks."""
    ticks = 0
    for _ in range(int(5.0 / (dt * CHUNK))):
        frame = world.tick(CHUNK, view=view)
        ticks += CHUNK
        if frame.tick * dt > 0.6 and np.linalg.norm(frame["pelvis.linvel"]) < 0.005:
            log(f"stand: still at t={frame.tick * dt:.2f} s, pelvis at {frame['pelvis.pos'][2]:.3f} m, "
                f"ZMP {frame['zmp.margin'] * 100:.1f} cm inside the soles")
            return ticks
    raise RuntimeError("the robot does not come to rest in its crouch")


def try_keyframe(plan: BrainClient, view: View, kf: Keyframe, dt: float) -> tuple[bool, float, float]:
    """Play ``kf`` in the fork and watch it; (balanced, smallest margin, lowest pelvis)."""
    plan.set("servo.sequence", kf.sequence())
    kf.ticks = round((kf.seconds + SETTLE) / dt)
    margin, low = watch(plan, view, kf.ticks)
    return margin >= MARGIN and low >= FALLEN_Z, margin, low


def milder(here: dict[str, float], kf: Keyframe) -> Keyframe:
    """The keyframe again, moving ``MILDER`` of its change from ``here``, ``SLOWER`` times slower."""
    pose = {j: round(here.get(j, 0.0) + MILDER * (v - here.get(j, 0.0)), 3) for j, v in kf.pose.items()}
    return Keyframe(kf.name, pose, kf.seconds * SLOWER, kf.tries + 1, history=kf.history)


def make_plan(world: BrainClient, log: Callable[[str], None], max_tries: int = 6) -> tuple[list[Keyframe], int,
                                                                                        np.ndarray]:
    """Plan in a fork: stand, then each keyframe, backticking to retry one that fails. Returns the
    keyframes, the ticks standing took, and the predicted final state (the `COMPARE` signals)."""
    plan = world.fork()
    try:
        dt = plan.status()["step_ns"] * 1e-9
        view = plan.view(WATCH)
        stood = stand(plan, view, dt, log)
        keyframes, here = [], {**CROUCH}
        for name, pose, seconds in SEQUENCE:
            kf = Keyframe(name, dict(pose), seconds)
            while True:
                ok, margin, low = try_keyframe(plan, view, kf, dt)
                kf.margin = margin
                if ok:
                    log(f"{name}: ok on try {kf.tries} (ZMP at least {margin * 100:.1f} cm inside, pelvis at least "
                        f"{low:.3f} m)")
                    break
                if kf.tries >= max_tries:
                    raise RuntimeError(f"{name}: the robot loses its balance after {max_tries} tries")
                plan.backtick(kf.ticks)  # the prediction failed: back to before the keyframe, exactly
                what = "falls" if low < FALLEN_Z else "nearly tips over"
                log(f"{name}: try {kf.tries} {what} (ZMP margin {margin * 100:.1f} cm, pelvis down to {low:.3f} m); "
                    f"backtick {kf.ticks} and try {MILDER:g} of the motion, {SLOWER:g} times slower")
                kf.history.append(f"try {kf.tries}: margin {margin:.4f}, pelvis {low:.3f}")
                kf = milder(here, kf)
            keyframes.append(kf)
            here.update(kf.pose)
        predicted = plan.read(plan.view(COMPARE))
        return keyframes, stood, predicted.values.copy()
    finally:
        plan.close()


def execute(world: BrainClient, keyframes: list[Keyframe], stood: int, log: Callable[[str], None]) -> dict:
    """Play the plan on the served world, lock-step, at the ticks the plan used; watch it too."""
    view = world.view(WATCH)
    world.tick(stood)
    lowest = np.inf
    for kf in keyframes:
        world.set("servo.sequence", kf.sequence())
        margin, low = watch(world, view, kf.ticks)
        lowest = min(lowest, low)
        log(f"executed {kf.name}: ZMP at least {margin * 100:.1f} cm inside")
    final = world.read(world.view(COMPARE))
    return {"tick": final.tick, "values": final.values.copy(), "lowest_pelvis": float(lowest),
            "pelvis_z": float(final["pelvis.pos"][2])}


def run(world: BrainClient, log: Callable[[str], None] = print) -> dict:
    keyframes, stood, predicted = make_plan(world, log)
    report = execute(world, keyframes, stood, log)
    report["tries"] = {kf.name: kf.tries for kf in keyframes}
    report["as_predicted"] = bool(np.array_equal(report["values"], predicted))
    report["max_difference"] = float(np.abs(report["values"] - predicted).max())
    log(f"done at tick {report['tick']}: tries {report['tries']}; the robot stands, pelvis at "
        f"{report['pelvis_z']:.3f} m; the world did {'exactly' if report['as_predicted'] else 'NOT'} what the plan "
        f"predicted (largest difference {report['max_difference']:.3g})")
    return report


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="An example brain for the humanoid (scenarios/humanoid_stand.yaml).")
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447", help="the server's endpoint")
    ap.add_argument("--world", default="humanoid_stand")
    args = ap.parse_args(argv)
    with BrainClient(args.world, connect=args.connect, brain="humanoid-brain", timeout=30) as world:
        report = run(world, log=lambda msg: print(msg, flush=True))
    if not report["as_predicted"]:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
