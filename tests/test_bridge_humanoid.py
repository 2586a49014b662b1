"""The humanoid example brain for real: `dynabrain serve scenarios/humanoid_stand.yaml` in one process,
the brain (`dynabrain.bridge.humanoid_brain`) in another, on loopback. It stands, plans a motion
sequence in a fork, retries the keyframe that topples the robot with a backtick, and the served world
then does exactly what the plan predicted."""

from __future__ import annotations

import os
import re

import numpy as np

from dynabrain.bridge import BrainClient
from dynabrain.bridge.testing import Process, ServerProcess

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
HUMANOID = os.path.join(ROOT, "scenarios", "humanoid_stand.yaml")


def test_the_humanoid_brain_stands_retries_a_fall_with_a_backtick_and_executes_the_plan():
    with ServerProcess(HUMANOID, "--decimate", "0") as server:
        brain = Process(["-m", "dynabrain.bridge.humanoid_brain", "--connect", server.endpoint], ready="stand:")
        with brain:
            code, out = brain.wait(120)
        assert code == 0, out
        assert "spread the arms: ok on try 1" in out, out
        assert re.search(r"bow with the arms forward: try 1 falls .*; backtick \d+ and try", out), out
        assert re.search(r"bow with the arms forward: ok on try [2-6] ", out), out
        assert "the world did exactly what the plan predicted (largest difference 0)" in out, out
        tick = int(re.search(r"done at tick (\d+)", out).group(1))
        with BrainClient("humanoid_stand", connect=server.endpoint) as world:
            status = world.status()
            assert status["tick"] == tick and status["server"]["forks"] == []  # the plan's fork is closed
            assert world.get("zmp.inside") == 1.0 and world.get("zmp.margin") > 0.015
            assert abs(world.get("pelvis.pos")[2] - 0.293) < 0.005  # standing in the crouch again
            assert np.abs(world.get("core.pelvis.linvel")).max() < 0.05
    assert "Traceback" not in server.output, server.output
