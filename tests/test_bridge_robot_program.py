"""A servo's motion program on the robot link, for real: a served world (ticked lock-step by a brain), robot
emulator processes with their own simulations, all on loopback. The program reaches each robot as its
timed steps and the robot plays it on its own clock; a move or a program the robot would ignore is
reported as ignored; the enable window is named; a robot lost while it plays stops the brain, naming
the tick."""

from __future__ import annotations

import os
import re

import numpy as np
import pytest

from dynabrain.bridge import BrainClient, WorldRefusedError, frames
from dynabrain.bridge.errors import RobotLostError, RobotStoppedError
from dynabrain.bridge.protocol import ProtocolError
from dynabrain.bridge.robot_program import OP_PROGRAM, Program, program_cmd, read_program
from dynabrain.bridge.testing import EmulatorProcess, Process, ServerProcess, wait_for

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, "bridge", "arm.yaml")
SERVO = """
modules:
  - name: servo
    python: dynabrain.modules.servo:Servo
    targets: [yaw, shoulder, elbow]
    params: {kp: 60, kd: 3, tau_max: 40}
    connect:
      - [core.joint_q, servo.q]
      - [core.joint_qd, servo.qd]
      - [servo.tau, core.joint_force]
"""
PROGRAM = [{"pose": [30, 40, -50], "duration": "0.4s"}, {"pose": {"yaw": -20}, "duration": "0.3s"}]
"""Degrees; the second step moves the yaw only."""
LAST = np.radians([-20, 40, -50])


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """The arm on the robot modules' `Servo` (it plays programs), lock-step, with two robots on its servo:
    ``arm`` (an emulator of the same scenario: its own servo plays the program) and ``pd`` (an emulator of
    the arm on the bridge's `PDServo`, which has no programs: the emulator interpolates the steps)."""
    with open(ARM) as f:
        text = f.read()
    scenario = tmp_path_factory.mktemp("program") / "arm_servo.yaml"
    scenario.write_text(text[:text.index("modules:")] + SERVO.lstrip())
    with ServerProcess(str(scenario), "--robot", "arm=servo", "--robot", "pd=servo", "--decimate", "0",
                       "--deadline", "100ms", "--lease", "1s") as server:
        arm = EmulatorProcess(str(scenario), "arm", server.endpoint, "--noise", "0.001", "--seed", "5")
        pd = EmulatorProcess(ARM, "arm", server.endpoint, "--robot", "pd")
        with arm, pd, BrainClient("arm", connect=server.endpoint, brain="planner") as brain:
            wait_for(lambda: all(brain.robot_status(r)["mode"] == "disabled" for r in ("arm", "pd")),
                     what="both robots to report")
            yield server, arm, pd, brain
        assert "Traceback" not in arm.output + pd.output, arm.output + pd.output


def test_a_servo_program_reaches_the_robot_as_its_timed_steps(rig):
    brain = rig[3]
    for robot in ("arm", "pd"):
        assert brain.robot_enable(robot)["enable_window_ms"] == 100
    brain.set("servo.sequence", PROGRAM)  # the sim's servo and both robots get it
    brain.tick(400)  # 0.8 s of simulated time, lock-step: the robots keep their own time
    sim = np.asarray(brain.get("core.joint_q"))
    assert np.abs(sim - LAST).max() < 0.05, sim  # the shoulder sags under gravity (PD)
    for robot in ("arm", "pd"):
        end = brain.robot_wait(robot, timeout=20)
        program = end["program"]
        assert program["forwarded"] and program["steps"] == 2 and program["tick"] == 1, program
        assert abs(program["duration_s"] - 0.7) < 1e-9 and program["robot"]["state"] == "done", program
        # one program went, no stream of moves: the robot interpolated the steps itself
        assert end["counts"]["programs"] == 1 and end["counts"]["forwarded"] == 0, end["counts"]
        assert end["robot_counts"]["programs"] == 1 and end["robot_counts"]["moves"] == 0, end["robot_counts"]
        wait_for(lambda r=robot: np.abs(np.subtract(brain.robot_status(r)["last_state"]["q"], sim)).max() < 0.01,
                 what=f"robot {robot} to settle where the simulation did")
        assert brain.robot_status(robot)["mode"] == "enabled"  # a program is a whole command: no stream expected
    brain.backtick(50)  # the servo's program comes back with the state: not news to the robots
    brain.tick(60)
    assert all(brain.robot_status(r)["counts"]["programs"] == 1 for r in ("arm", "pd"))


def test_a_program_frame_round_trips_and_a_bad_one_is_refused_naming_the_fault():
    program = Program((400_000_000, 300_000_001), np.radians([[30, 40, -50], [-20, 40, -50]]), loop=True,
                      smooth=False)
    frame = frames.unpack(program_cmd(program, seq=7, stamp_ns=1, deadline_ns=100_000_000), frames.ROBOT_CMD,
                          finite=True)
    assert frame.flags == OP_PROGRAM and frame.seq == 7 and frame.aux == 100_000
    back = read_program(frame, 3)
    assert back.durations_ns == program.durations_ns and np.array_equal(back.poses, program.poses)
    assert back.loop is True and back.smooth is False and back.times_ns() == (0, 400_000_000, 700_000_001)

    def bad(values, joints=3, aux=100):
        return read_program(frames.Frame(frames.ROBOT_CMD, OP_PROGRAM, 0, 1, 1, aux, np.asarray(values, float), b""),
                            joints)

    with pytest.raises(ProtocolError, match=r"not 2 \+ steps \* \(1 \+ 3 joints\)"):
        bad([0, 0, 1e8, 0.1, 0.2])
    with pytest.raises(ProtocolError, match=r"step 1: duration 0\.5 ns is not a whole number"):
        bad([0, 0, 1e8, 0, 0, 0, 0.5, 0, 0, 0])
    with pytest.raises(ProtocolError, match="step 0: duration -1 ns"):
        bad([0, 0, -1, 0, 0, 0])
    with pytest.raises(ProtocolError, match="loop 2 and interpolation 0 must each be 0 or 1"):
        bad([2, 0, 1e8, 0, 0, 0])
    with pytest.raises(ProtocolError, match="no deadline"):
        bad([0, 0, 1e8, 0, 0, 0], aux=0)


def test_a_move_or_program_the_robot_ignores_is_reported_ignored_and_the_enable_window_named(rig):
    brain = rig[3]
    brain.robot_enable("arm")  # and nothing within the enable window: the robot safe-stops, saying so
    wait_for(lambda: brain.robot_status("arm")["mode"] == "safe_stop", what="the safe stop")
    status = brain.robot_status("arm")
    assert status["reason"] == "no move or program within the enable window (100 ms after robot_enable)", status
    before, robot_before = status["counts"], status["robot_counts"]
    reply = brain.motion("arm", [0.0, 0.3, 0.0], route="both")
    assert reply["robot"]["forwarded"] is False and reply["robot"]["ignored"] is True, reply
    assert "safe stop" in reply["robot"]["reason"] and "enable window" in reply["robot"]["reason"], reply
    brain.set("servo.sequence", [{"pose": [0, 0, 0], "duration": "0.2s"}])
    brain.tick(10)
    with pytest.raises(RobotStoppedError, match=r"the program of tick \d+ was ignored: .*enable window") as info:
        brain.robot_wait("arm", timeout=5)
    assert info.value.tick is not None
    after = brain.robot_status("arm")
    assert after["counts"]["ignored"] == before["ignored"] + 2 and after["counts"]["forwarded"] == before["forwarded"]
    assert after["counts"]["programs"] == before["programs"]
    assert after["robot_counts"]["moves"] == robot_before["moves"], after["robot_counts"]


def test_a_robot_lost_while_it_plays_stops_the_brain_naming_the_tick(rig):
    brain = rig[3]
    brain.robot_enable("pd")
    brain.set("servo.sequence", [{"pose": [0, 10, 0], "duration": "3s"}])
    start = brain.tick(20)
    wait_for(lambda: (brain.robot_status("pd")["program"]["robot"] or {}).get("state") == "playing",
             what="the robot to play")
    rig[2].kill()
    wait_for(lambda: not brain.robot_status("pd")["alive"], what="the robot to be lost")
    brain.tick(5)
    with pytest.raises(RobotLostError, match=r"robot 'pd': link lost at tick (\d+)") as info:
        brain.robot_wait("pd", timeout=5)
    assert info.value.tick == start, (info.value.tick, start)  # the brain ticked 5 more after the loss
    with pytest.raises(WorldRefusedError, match=re.escape(f"lost at tick {start}")):
        brain.motion("pd", [0.0, 0.0, 0.0], route="robot")


def test_the_example_brain_exits_1_naming_the_tick_when_the_robot_is_lost():
    with ServerProcess(ARM, "--robot", "arm=servo", "--start", "--realtime", "--decimate", "0",
                       "--deadline", "100ms", "--lease", "1s") as server:
        emu = EmulatorProcess(ARM, "arm", server.endpoint, "--lease", "1s")
        with emu, BrainClient("arm", connect=server.endpoint, brain="watcher") as watcher:
            wait_for(lambda: watcher.robot_status("arm")["mode"] == "disabled", what="the robot")
            runner = Process(["-m", "dynabrain.bridge.example_brain", "--connect", server.endpoint, "--route",
                              "both"], ready="stand:")
            with runner:
                wait_for(lambda: watcher.robot_status("arm")["counts"]["forwarded"] > 10, timeout=30,
                         what="the plan to reach the robot")
                emu.kill()
                code, out = runner.wait(60)
    assert code == 1, out
    match = re.search(r"the robot stopped during the plan \(the robot was lost at tick (\d+)\)", out)
    assert match and int(match.group(1)) > 0, out
