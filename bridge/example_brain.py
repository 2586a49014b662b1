"""An example brain: it plans a motion in a fork of the world it is served, retries with a backtick
when the prediction goes wrong, and then executes the plan on the world, on the robot, or both.

The world is ``bridge/arm.yaml`` (a three-joint arm and a cube, with a robot rig; the humanoid's brain is
`humanoid_brain`):

1. *stand*: bring the arm upright and wait until it is still;
2. *a motion sequence*: reach down beside the cube, sweep over it, come back. Each keyframe is tried in the fork first;
   when the prediction says the arm disturbs the cube, the brain goes back to before the keyframe
   (``backtick``) and tries again with the shoulder raised;
3. *execute*: stream the plan at 50 Hz as motion commands (``--route sim|robot|both``) while the world
   runs in real time, then report how the world (and the robot, in shadow mode) followed it.

    dynabrain serve bridge/arm.yaml --robot arm=servo --listen tcp/127.0.0.1:7447 &
    dynabrain robot-emulator bridge/arm.yaml --world arm --connect tcp/127.0.0.1:7447 &
    python -m dynabrain.bridge.example_brain --connect tcp/127.0.0.1:7447 --route both
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .client import BrainClient

STAND = (0.0, 0.0, 0.0)
SEQUENCE = (("reach beside the cube", (-0.6, 1.45, 0.9), 0.6), ("sweep over the cube", (0.6, 1.45, 0.9), 0.8),
            ("come back", STAND, 0.6))
"""(name, (yaw, shoulder, elbow) in rad, seconds) keyframes."""
DISTURBED = 0.001
"""The plan fails when the cube moves more than this (m)."""
STEP = 5
"""Ticks between two set points while planning (10 ms at a 2 ms step)."""


@dataclass
class Keyframe:
    name: str
    pose: np.ndarray
    seconds: float
    tries: int = 1


def stand(plan: BrainClient, dt: float, log: Callable[[str], None]) -> None:
    plan.set("servo.target", list(STAND))
    view = plan.view(["core.joint_qd"])
    for _ in range(400):
        if np.abs(plan.tick(STEP, view=view)["core.joint_qd"]).max() < 0.01:
            log(f"stand: still at t={plan.status()['time']:.2f} s")
            return
    raise RuntimeError("the arm does not come to rest upright")


def try_keyframe(plan: BrainClient, start: np.ndarray, kf: Keyframe, dt: float) -> tuple[bool, int, float]:
    """Move from ``start`` to ``kf.pose`` in the fork; (cube undisturbed, ticks used, cube displacement)."""
    cube0 = np.asarray(plan.get("cube.pos"))
    steps = max(int(kf.seconds / (dt * STEP)), 1)
    view = plan.view(["cube.pos"])
    moved = 0.0
    for i in range(1, steps + 1):
        plan.set("servo.target", list(start + (kf.pose - start) * i / steps))
        moved = max(moved, float(np.linalg.norm(plan.tick(STEP, view=view)["cube.pos"] - cube0)))
    plan.drop_view(view)
    return moved <= DISTURBED, steps * STEP, moved


def make_plan(world: BrainClient, log: Callable[[str], None], max_tries: int = 4) -> list[Keyframe]:
    """Plan the sequence in a fork: stand, then each keyframe, backticking to retry a failed one."""
    plan = world.fork()
    try:
        dt = plan.status()["step_ns"] * 1e-9
        stand(plan, dt, log)
        keyframes, here = [], np.array(STAND)
        for name, pose, seconds in SEQUENCE:
            kf = Keyframe(name, np.array(pose), seconds)
            while True:
                ok, ticks, moved = try_keyframe(plan, here, kf, dt)
                if ok:
                    log(f"{name}: ok on try {kf.tries} (cube moved {moved * 1000:.2f} mm)")
                    break
                if kf.tries >= max_tries:
                    raise RuntimeError(f"{name}: the cube is disturbed after {max_tries} tries")
                plan.backtick(ticks)  # the prediction failed: back to before the keyframe, exactly
                log(f"{name}: try {kf.tries} moves the cube {moved * 1000:.1f} mm; backtick {ticks} and raise the "
                    "shoulder")
                kf.pose = kf.pose + np.array([0.0, -0.15, 0.0])
                kf.tries += 1
            keyframes.append(kf)
            here = kf.pose
        return keyframes
    finally:
        plan.close()


def execute(world: BrainClient, keyframes: list[Keyframe], route: str, robot: str,
            log: Callable[[str], None], rate: float = 50.0) -> dict:
    """Stream the plan in real time as motion commands (or input values when the world has no rig)."""
    status = world.status()
    rigged = robot in status.get("robots", {})
    started = not status["server"]["loop"]["running"]
    if started:
        world.start(realtime=True)
    if route != "sim":
        world.robot_enable(robot)
        time.sleep(0.05)

    def send(targets: np.ndarray) -> None:
        if rigged:
            world.send_motion(robot, list(targets), route=route)
        else:
            world.set_inputs({"servo.target": list(targets)})

    here = np.array(STAND)
    cube0 = np.asarray(world.get("cube.pos"))
    stops: list[str] = []  # the robot's safe stops while the plan runs (a missed deadline, a lost brain)

    def on_event(event: dict) -> None:
        detail = event.get("detail") or {}
        if event.get("kind") == "robot_status" and detail.get("robot") == robot and detail.get("mode") == "safe_stop":
            stops.append(str(detail.get("reason")))
        elif event.get("kind") == "robot_lost" and detail.get("robot") == robot:
            stops.append(f"the robot was lost at tick {event.get('tick')}")

    events = world.subscribe_events(on_event) if route != "sim" else None
    try:
        for kf in keyframes:
            t0 = time.monotonic()
            while (s := (time.monotonic() - t0) / kf.seconds) < 1.0 and not stops:
                send(here + (kf.pose - here) * s)
                time.sleep(1.0 / rate)
            if stops:  # the robot stopped or was lost: the plan is not carried out, the brain stops here
                break
            here = kf.pose
            log(f"executed {kf.name}")
        for _ in range(int(0.3 * rate) if not stops else 0):  # hold the last pose a moment
            send(here)
            time.sleep(1.0 / rate)
    finally:
        if started:
            world.stop()
    report = {"joint_q": np.asarray(world.get("core.joint_q")).round(3).tolist(),
              "cube_moved_mm": float(np.linalg.norm(np.asarray(world.get("cube.pos")) - cube0)) * 1000}
    if route != "sim":
        report["robot"] = world.robot_status(robot)
        time.sleep(0.05)  # events still on their way
        events.undeclare()
        report["robot_stopped"] = stops[0] if stops else None
    return report


def run(world: BrainClient, route: str = "sim", robot: str = "arm", log: Callable[[str], None] = print) -> dict:
    keyframes = make_plan(world, log)
    report = execute(world, keyframes, route, robot, log)
    report["tries"] = {kf.name: kf.tries for kf in keyframes}
    if report.get("robot_stopped"):
        log(f"the robot stopped during the plan ({report['robot_stopped']}): the plan was not carried out on it")
    log(f"{'done' if not report.get('robot_stopped') else 'stopped'}: {report['tries']}, joints at "
        f"{report['joint_q']}, the cube moved {report['cube_moved_mm']:.2f} mm")
    if "robot" in report:
        shadow = report["robot"]["shadow"]
        log(f"robot: {report['robot']['counts']['forwarded']} commands forwarded, shadow rms "
            f"{np.round(shadow['rms'], 4).tolist() if shadow['rms'] else None} rad")
    return report


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="An example brain for the bridge's arm world.")
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447", help="the server's endpoint")
    ap.add_argument("--world", default="arm")
    ap.add_argument("--route", choices=("sim", "robot", "both"), default="sim")
    ap.add_argument("--robot", default="arm", help="the robot rig's name (dynabrain serve --robot NAME=SERVO)")
    args = ap.parse_args(argv)
    with BrainClient(args.world, connect=args.connect, brain="example-brain") as world:
        report = run(world, args.route, args.robot, log=lambda msg: print(msg, flush=True))
    if report.get("robot_stopped"):
        raise SystemExit(1)  # the robot did not carry the plan out: not a success


if __name__ == "__main__":
    main()
