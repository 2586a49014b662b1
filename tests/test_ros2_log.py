"""Logs with ROS 2 message schemas (``run --log FILE --ros2-schemas``, ``log: {ros2_schemas: true}``,
``McapLogger(ros2=True)``), for rosbag2 users: ``/clock``, ``/joint_states`` and ``/tf`` in CDR with ``ros2msg``
schemas, read back with the ``mcap`` reader and decoded by ``mcap-ros2-support`` (which parses the schema
text itself) to the world's joint names, positions, poses and simulated time; the rest of the log is as
it was, so rollbacks, ``replay --verify`` and strict message order still hold."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.verify import verify
from dynabrain.orchestrator.scenario.model import load_scenario

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, "bridge", "arm.yaml")
DT = 2_000_000
JOINTS = ["yaw", "shoulder", "elbow"]


def decoded(path) -> dict[str, list]:
    """topic -> [(log time, publish time, sequence, message)], in file order, and each channel's encodings."""
    out: dict[str, list] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, message, value in reader.iter_decoded_messages(
                topics=["/clock", "/joint_states", "/tf", "/discarded/joint_states"], log_time_order=False):
            assert (schema.encoding, channel.message_encoding) == ("ros2msg", "cdr"), channel.topic
            out.setdefault(channel.topic, []).append((message.log_time, message.publish_time, message.sequence,
                                                      value))
        times = [m.log_time for _s, _c, m in reader.iter_messages(log_time_order=False)]
    assert times == sorted(times)  # strict readers' message order holds
    return out


def test_a_log_with_ros2_schemas_decodes_to_the_world(tmp_path):
    path = tmp_path / "arm.mcap"
    sc = load_scenario(ARM)
    world = sc.build()
    logger = McapLogger(path, ros2=True).attach(world, sc)
    seen = {}

    def tick(n: int) -> None:
        for _ in range(n):
            world.tick()
            seen[world.tick_count] = ([float(world.get(f"core.{j}.q")) for j in JOINTS],
                                      [float(v) for v in world.get("core.fore.pos")])

    seen[0] = ([float(world.get(f"core.{j}.q")) for j in JOINTS], [float(v) for v in world.get("core.fore.pos")])
    world.set("servo.target", [0.4, 0.7, -1.0])
    tick(40)
    world.backtick(10)  # ticks 31..40 are discarded: their ROS 2 messages go to /discarded/...
    tick(20)
    world.close()
    assert logger.stats["epoch"] == 1
    got = decoded(path)
    states, clock, tf = got["/joint_states"], got["/clock"], got["/tf"]
    assert [c[3].clock.sec * 1_000_000_000 + c[3].clock.nanosec for c in clock] == [t * DT for t in range(51)]
    assert len(got["/discarded/joint_states"]) == 10
    origin = int(logger.origin_ns)
    for tick_no, (log_time, publish_time, epoch, msg) in enumerate(states):
        assert msg.name == JOINTS and publish_time == tick_no * DT and log_time == origin + tick_no * DT
        assert msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == tick_no * DT  # simulated time
        assert list(msg.position) == seen[tick_no][0] and len(msg.velocity) == 3
        assert epoch == (0 if tick_no <= 30 else 1)
        fore = next(t for t in tf[tick_no][3].transforms if t.child_frame_id == "fore")
        assert fore.header.frame_id == "world"
        assert [fore.transform.translation.x, fore.transform.translation.y, fore.transform.translation.z] == \
            seen[tick_no][1]
    assert seen[50][0] != seen[0][0]  # the arm moved: the positions compared are not all the start's
    assert verify(path).ok  # the bus and events are as they were


def short_arm(tmp_path, log: str = "") -> str:
    """The arm for 0.1 s (its expectations are at 4 s), with a ``log:`` section when given."""
    text = Path(ARM).read_text().split("expect:")[0].replace("duration: 4s", "duration: 100ms")
    path = tmp_path / "arm.yaml"
    path.write_text(text + (f"log: {log}\n" if log else ""))
    return str(path)


@pytest.mark.parametrize("how", ["option", "scenario"])
def test_run_writes_ros2_schemas_by_option_or_scenario_and_verify_passes(tmp_path, how):
    path = tmp_path / "run.mcap"
    scenario = short_arm(tmp_path, "{ros2_schemas: true}" if how == "scenario" else "")
    args = ["--ros2-schemas"] if how == "option" else []
    runner = CliRunner()
    result = runner.invoke(app, ["run", scenario, "--log", str(path), "-q", *args])
    assert result.exit_code == 0, result.output
    assert "with ROS 2 messages" in result.output
    states = decoded(path)["/joint_states"]
    assert len(states) == 51 and states[-1][3].name == JOINTS
    if how == "scenario":
        return
    result = runner.invoke(app, ["replay", str(path), "--verify"])
    assert result.exit_code == 0 and "verify: identical" in result.output, result.output
    assert "sensor_msgs/msg/JointState (ros2msg)" in result.output


def test_a_bad_ros2_schemas_value_in_the_scenario_names_the_field(tmp_path):
    scenario = short_arm(tmp_path, "{ros2_schemas: maybe}")
    result = CliRunner().invoke(app, ["run", scenario, "--log", str(tmp_path / "x.mcap"), "-q"])
    assert result.exit_code == 2 and "ros2_schemas" in result.output, result.output
    assert not (tmp_path / "x.mcap").exists()
