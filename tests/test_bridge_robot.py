"""The real-robot link for real: a served world, a robot emulator process (its own simulation, noise and
latency) and brains, all on loopback. Shadow mode, the watchdog at both ends, and safe stops when the
brain, the robot or the world goes away."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from dynabrain.bridge import BrainClient, WorldRefusedError, frames
from dynabrain.bridge import protocol as p
from dynabrain.bridge.testing import EmulatorProcess, Process, ServerProcess, wait_for
from dynabrain.bridge.zenoh_io import Settings, open_session

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, "bridge", "arm.yaml")




def drive(brain: BrainClient, robot: str, start, goal, seconds: float, route: str = "both", rate: float = 50.0):
    """Stream a straight-line motion from ``start`` to ``goal`` at ``rate``, as a brain's control loop does."""
    t0 = time.monotonic()
    while (s := (time.monotonic() - t0) / seconds) < 1.0:
        brain.send_motion(robot, list(np.add(start, s * np.subtract(goal, start))), route=route)
        time.sleep(1.0 / rate)
    brain.send_motion(robot, list(goal), route=route)


@pytest.fixture(scope="module")
def rig():
    """A world running in real time with two robot rigs: ``arm`` (noise 1 mrad, 5 ms latency) and ``slow``
    (commands reach its controller 150 ms late, over the 100 ms deadline)."""
    with ServerProcess(ARM, "--robot", "arm=servo", "--robot", "slow=servo", "--start", "--realtime",
                       "--decimate", "10", "--deadline", "100ms", "--lease", "1s") as server:
        arm = EmulatorProcess(ARM, "arm", server.endpoint, "--noise", "0.001", "--latency", "5ms", "--seed", "3")
        slow = EmulatorProcess(ARM, "arm", server.endpoint, "--robot", "slow", "--cmd-latency", "150ms")
        with arm, slow, BrainClient("arm", connect=server.endpoint, brain="pilot") as brain:
            wait_for(lambda: all(brain.robot_status(r)["mode"] == "disabled" for r in ("arm", "slow")),
                     what="both robots to report")
            yield server, arm, slow, brain
        assert "Traceback" not in arm.output + slow.output, arm.output + slow.output


def test_shadow_mode_compares_prediction_with_measurement(rig):
    brain = rig[3]
    shadow: list[frames.Frame] = []
    brain.subscribe_shadow("arm", shadow.append)
    brain.robot_enable("arm")
    wait_for(lambda: brain.robot_status("arm")["mode"] == "enabled", what="the robot to enable")
    goal = [0.5, 0.4, -0.7]
    drive(brain, "arm", [0.0, 0.0, 0.0], goal, seconds=0.8)
    for _ in range(15):  # hold the goal a little: the robot keeps getting fresh commands
        brain.send_motion("arm", goal, route="both")
        time.sleep(0.02)
    status = brain.robot_status("arm")
    assert status["counts"]["forwarded"] >= 40 and status["counts"]["dropped"] == 0, status
    measured = np.array(status["last_state"]["q"])
    assert np.abs(measured - brain.get("core.joint_q")).max() < 0.05, (measured, brain.get("core.joint_q"))
    assert abs(measured[0] - goal[0]) < 0.05  # the robot went where the brain sent it
    rms = np.array(status["shadow"]["rms"])
    assert status["shadow"]["samples"] > 100 and (rms < 0.03).all() and (rms > 0.0003).all(), status["shadow"]
    assert len(shadow) > 100
    last = shadow[-1]
    n = last.aux
    assert n == 3 and np.abs(last.values[:n] - last.values[n:]).max() < 0.05
    # the brain stops sending: the robot's own watchdog stops it within its deadline
    wait_for(lambda: brain.robot_status("arm")["mode"] == "safe_stop", timeout=2, what="the safe stop")
    assert "no fresh command" in wait_for(lambda: brain.robot_status("arm")["reason"], what="a reason")


def test_the_example_brain_plans_in_a_fork_retries_and_drives_sim_and_robot(rig):
    server = rig[0]
    brain = Process(["-m", "dynabrain.bridge.example_brain", "--connect", server.endpoint, "--route", "both"],
                    ready="stand:")
    with brain:
        code, out = brain.wait(60)
    assert code == 0, out
    assert "sweep over the cube: try 1 moves the cube" in out and "backtick" in out  # the prediction failed once
    assert "sweep over the cube: ok on try" in out
    moved = float(out.split("the cube moved ")[1].split(" mm")[0])
    assert moved < 1.0, out  # the executed plan left the cube alone
    forwarded = int(out.split("robot: ")[1].split(" commands")[0])
    assert forwarded > 80, out


def test_the_watchdog_forwards_no_stale_command(rig):
    brain = rig[3]
    before = brain.robot_status("arm")["counts"]
    old = brain.call("motion", robot="arm", targets=[0.1, 0.1, 0.1], route="robot",
                     sent_ns=time.time_ns() - 300_000_000)
    assert old["robot"]["forwarded"] is False and "over the 100 ms deadline" in old["robot"]["reason"]
    assert brain.robot_status("arm")["counts"]["dropped"] == before["dropped"] + 1
    with pytest.raises(WorldRefusedError, match="in the future"):
        brain.call("motion", robot="arm", targets=[0.1, 0.1, 0.1], route="robot", sent_ns=time.time_ns() + 5 * 10**9)
    with pytest.raises(WorldRefusedError, match="has 3 joints"):
        brain.motion("arm", [0.1, 0.2], route="both")
    with pytest.raises(WorldRefusedError, match="no robot 'lag'"):
        brain.motion("lag", [0.1, 0.2, 0.3])


def test_a_robot_refuses_commands_that_arrive_after_their_deadline(rig):
    brain = rig[3]
    brain.robot_enable("slow")  # reaches the controller 150 ms late: stale, refused
    for _ in range(10):
        brain.send_motion("slow", [0.3, 0.0, 0.0], route="robot")
        time.sleep(0.02)
    time.sleep(0.3)
    status = brain.robot_status("slow")
    assert status["mode"] == "disabled" and status["reason"].startswith("enable refused: "), status
    # moves went while the enable was unanswered; once the robot said it stayed disabled, they were ignored
    counts = status["counts"]
    assert counts["forwarded"] + counts["ignored"] >= 10 and counts["ignored"] >= 1, counts
    assert status["robot_counts"]["moves"] == 0
    assert abs(status["last_state"]["q"][0]) < 0.01  # it never moved
    reply = brain.motion("slow", [0.3, 0.0, 0.0], route="robot")["robot"]
    assert reply["forwarded"] is False and reply["ignored"] is True and "enable refused" in reply["reason"], reply


def test_bad_robot_frames_are_counted_and_ignored(rig):
    server, brain = rig[0], rig[3]
    before = brain.robot_status("arm")["counts"]["bad_states"]
    session, _ = open_session(Settings(connect=[server.endpoint]))
    try:
        key = p.robot_key("arm", "arm", "state")
        for payload in (b"", b"DBF1" + bytes(50), frames.pack(frames.ROBOT_STATE, [np.nan] * 6, aux=3),
                        frames.pack(frames.ROBOT_STATE, [0.0] * 4, aux=2), frames.pack(frames.STATE, [0.0] * 6)):
            session.put(key, payload)
    finally:
        session.close()
    wait_for(lambda: brain.robot_status("arm")["counts"]["bad_states"] >= before + 5, what="bad frames counted")
    assert brain.robot_status("arm")["alive"]


def test_losing_the_brain_the_robot_or_the_world_stops_the_robot():
    with ServerProcess(ARM, "--robot", "arm=servo", "--start", "--realtime", "--decimate", "0", "--deadline", "2s",
                       "--lease", "1s") as server:
        emu = EmulatorProcess(ARM, "arm", server.endpoint, "--lease", "1s").start()
        try:
            with BrainClient("arm", connect=server.endpoint, brain="watcher") as watcher:
                events: list = []
                watcher.subscribe_events(events.append)
                wait_for(lambda: watcher.robot_status("arm")["mode"] == "disabled", what="the robot")
                # 1. a brain drives the robot, then dies: the link stops the robot at once (2 s deadline)
                code = ("import time; from dynabrain.bridge import BrainClient; "
                        f"b = BrainClient('arm', connect={server.endpoint!r}, brain='driver'); "
                        "b.robot_enable('arm'); time.sleep(0.2); print('ready', flush=True)\n"
                        "while True:\n    b.send_motion('arm', [0.2, 0.0, 0.0], route='both'); time.sleep(0.02)")
                with Process(["-c", code], ready="ready") as driver:
                    wait_for(lambda: watcher.robot_status("arm")["counts"]["forwarded"] > 5, what="driving")
                    assert watcher.robot_status("arm")["mode"] == "enabled"
                    driver.kill()
                wait_for(lambda: watcher.robot_status("arm")["mode"] == "safe_stop", what="the safe stop")
                wait_for(lambda: any(e["kind"] == "robot_stop" and "driver" in e["detail"]["reason"] for e in events),
                         what="the robot_stop event naming the driver")
                # the link's stop, not the robot's own 2 s deadline ("no fresh command ...")
                assert wait_for(lambda: watcher.robot_status("arm")["reason"]) == "stop command"
                # 2. the robot goes away: reported, and motion to it refused (the simulation still takes it)
                emu.kill()
                wait_for(lambda: not watcher.robot_status("arm")["alive"], what="the robot to be lost")
                wait_for(lambda: any(e["kind"] == "robot_lost" for e in events), what="the robot_lost event")
                with pytest.raises(WorldRefusedError, match="not connected"):
                    watcher.motion("arm", [0.0, 0.0, 0.0], route="both")
                assert watcher.motion("arm", [0.0, 0.0, 0.0], route="sim") == {"sim": "applied at the next step"}
                # 3. the world goes away: an enabled robot stops by itself
                emu = EmulatorProcess(ARM, "arm", server.endpoint, "--lease", "1s").start()
                wait_for(lambda: watcher.robot_status("arm")["alive"], what="the robot to come back")
                watcher.robot_enable("arm")
                wait_for(lambda: watcher.robot_status("arm")["mode"] == "enabled", what="enabled again")
                server.kill()  # while its driver is still there: only the world's token goes
                time.sleep(0.5)  # the robot notices the closed link and stops (checked in its final report)
                out = emu.stop()
                assert "safe_stop (world 'arm' lost" in out, out
        finally:
            emu.stop()


def test_the_example_brain_says_when_the_robot_stops_during_its_plan(rig):
    """A safe stop while the plan runs (here a stop command; a missed deadline or a lost brain alike) is
    told to the brain as an event, and its result says the robot stopped instead of reporting success."""
    server, brain = rig[0], rig[3]
    before = brain.robot_status("arm")["counts"]["forwarded"]
    runner = Process(["-m", "dynabrain.bridge.example_brain", "--connect", server.endpoint, "--route", "both"],
                     ready="stand:")
    with runner:
        wait_for(lambda: brain.robot_status("arm")["counts"]["forwarded"] > before + 20, timeout=30,
                 what="the plan to reach the robot")
        brain.robot_stop("arm")
        code, out = runner.wait(60)
    assert code == 1, out
    assert "the robot stopped during the plan" in out and "stopped:" in out, out
