"""ROS 2 checked by a third party: a node written with `zenoh-ros2-sdk` (PyPI; its own rmw_zenoh code, no
ROS 2 installed, the message definitions shipped in ``tests/ros2_msgs``) discovers ``serve --ros2``'s
topics with the type hashes ROS 2 Jazzy reports, receives /joint_states and /clock while the world runs
in real time, and moves the arm through /arm/joint_commands."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from dynabrain.bridge.ros2 import Ros2Options
from dynabrain.bridge.server import BridgeServer, ServeOptions
from dynabrain.bridge.testing import wait_for
from dynabrain.bridge.zenoh_io import Settings
from dynabrain.orchestrator.scenario import load_world

pytest.importorskip("zenoh_ros2_sdk", reason="zenoh-ros2-sdk (the dev extra) is not installed")

HERE = os.path.dirname(os.path.abspath(__file__))
ARM = os.path.join(os.path.dirname(HERE), "bridge", "arm.yaml")
JOINT_STATE_JAZZY = "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"


def test_a_third_party_ros2_node_discovers_reads_and_commands_the_served_world(tmp_path):
    world = load_world(ARM)
    server = BridgeServer(world, Settings(listen=["tcp/127.0.0.1:0"]),
                          ServeOptions(robots={"arm": "servo"}, ros2=Ros2Options(rate_hz=100.0)))
    try:
        server.open()
        port = int(server.endpoints[0].rsplit(":", 1)[1])
        server.loop.start(realtime=True, until=None)  # as `serve --start --realtime`: inputs apply between ticks
        env = {**os.environ, "ZENOH_ROS2_SDK_CACHE": str(tmp_path / "no-clones")}
        run = subprocess.run([sys.executable, os.path.join(HERE, "ros2_thirdparty_client.py"), str(port),
                              os.path.join(HERE, "ros2_msgs")], capture_output=True, text=True, timeout=90, env=env)
        assert run.returncode == 0, run.stderr[-2000:]
        seen = json.loads(run.stdout.strip().splitlines()[-1])
        assert seen["topics"]["/joint_states"] == ["sensor_msgs/msg/JointState"]
        assert seen["topics"]["/clock"] == ["rosgraph_msgs/msg/Clock"]
        assert seen["topics"]["/arm/joint_commands"] == ["std_msgs/msg/Float64MultiArray"]
        assert seen["joint_states_hash"] == JOINT_STATE_JAZZY and seen["joint_states_node"] == "dynabrain_arm"
        assert seen["received"] >= 3 and seen["clocks"] >= 1
        assert seen["names"] == ["yaw", "shoulder", "elbow"] and len(seen["positions"]) == 3
        wait_for(lambda: list(world.get("servo.target")) == [0.3, 0.5, -0.4], what="the command applied")
        assert not (tmp_path / "no-clones").exists()  # nothing was fetched from the network
    finally:
        server.loop.stop()
        server.close()
        world.close()
