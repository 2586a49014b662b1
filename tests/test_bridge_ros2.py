"""ROS 2 interop for real, without ROS 2: a served world with ``ros2`` on loopback, and plain Zenoh sessions
that speak what an rmw_zenoh node (0.2.10, Jazzy) speaks. A raw subscriber on rmw_zenoh's key expressions
gets CDR that ``rosbags`` decodes to the world's joint states, body poses and time, each with rmw_zenoh's
attachment; raw CDR commands move the servo targets; bad ones are reported naming the field and change
nothing; the liveliness tokens have rmw_zenoh's layout. The type hashes are pinned to the values ROS 2
Jazzy itself reports (``ros2 topic info -v``), so a change of type store would show here."""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest

from dynabrain.bridge import BrainClient
from dynabrain.bridge import protocol as p
from dynabrain.bridge.ros2 import (
    CLOCK,
    JOINT_STATE,
    MULTI_ARRAY,
    TF,
    TRAJECTORY,
    Codec,
    Ros2Options,
    attachment,
    dds_type,
    qos_field,
    read_attachment,
    topic_key,
)
from dynabrain.bridge.server import BridgeServer, ServeOptions
from dynabrain.bridge.testing import ServerProcess, wait_for
from dynabrain.bridge.zenoh_io import Settings, open_session
from dynabrain.orchestrator.scenario import load_world

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, "bridge", "arm.yaml")
JAZZY_HASHES = {  # as `ros2 topic info -v` prints them on Jazzy
    JOINT_STATE: "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",
    TF: "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    CLOCK: "RIHS01_692f7a66e93a3c83e71765d033b60349ba68023a8c689a79e48078bcb5c58564",
    MULTI_ARRAY: "RIHS01_1025ddc6b9552d191f89ef1a8d2f60f3d373e28b283d8891ddcc974e8c55397f",
    TRAJECTORY: "RIHS01_179b33eba59d676f6d967ac71fe35e7ca2f64b2f3928f4a018cec115e213796e",
}
CODEC = Codec()
T = CODEC.types




class Peer:
    """A plain Zenoh session, as an rmw_zenoh node's: raw samples and the world's events."""

    def __init__(self, endpoints: list[str]):
        self.session, _ = open_session(Settings(connect=endpoints))
        self.samples: list[tuple[str, bytes, bytes | None]] = []
        self.events: list[dict] = []
        self._subs = [
            self.session.declare_subscriber("0/**", lambda s: self.samples.append(
                (str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes() if s.attachment else None))),
            self.session.declare_subscriber(p.key("arm", "events"), lambda s: self.events.append(
                json.loads(s.payload.to_bytes())))]
        self._pubs: dict[str, object] = {}

    def latest(self, msgtype: str):
        for key, payload, _ in reversed(self.samples):
            if key == topic_key(0, _TOPICS[msgtype], msgtype, JAZZY_HASHES[msgtype]):
                return CODEC.decode(payload, msgtype)
        return None

    def send(self, topic: str, msgtype: str, payload: bytes) -> None:
        """Put like an rmw_zenoh publisher (with its attachment), once the world's subscriber is matched."""
        key = topic_key(0, topic, msgtype, JAZZY_HASHES[msgtype])
        if key not in self._pubs:
            self._pubs[key] = pub = self.session.declare_publisher(key)
            wait_for(lambda: pub.matching_status.matching, what=f"a subscriber on {key}")
        self._pubs[key].put(payload, attachment=attachment(1, time.time_ns(), bytes(16)))

    def errors(self, kind: str = "input_error") -> list[str]:
        return [json.dumps(e["detail"]) for e in self.events if e["kind"] == kind]

    def close(self) -> None:
        self.session.close()


_TOPICS = {CLOCK: "/clock", TF: "/tf", JOINT_STATE: "/joint_states"}


@pytest.fixture(scope="module")
def served():
    world = load_world(ARM)
    server = BridgeServer(world, Settings(listen=["tcp/127.0.0.1:0"]),
                          ServeOptions(robots={"arm": "servo"}, ros2=Ros2Options(rate_hz=100.0)))
    try:
        server.open()
        yield server
    finally:
        server.close()
        world.close()


@pytest.fixture()
def peer(served):
    peer = Peer(served.endpoints)
    yield peer
    peer.close()


def tick(server: BridgeServer, n: int) -> None:
    server.main.service.call("tick", p.TickArgs(n=n))


def float64s(values) -> bytes:
    layout = T["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
    return CODEC.encode(T[MULTI_ARRAY](layout=layout, data=np.asarray(values, dtype=np.float64)))


def trajectory(names, points) -> bytes:
    """``points``: (positions, seconds from start) pairs."""
    header = T["std_msgs/msg/Header"](stamp=CODEC.stamp(0), frame_id="")
    point, duration = T["trajectory_msgs/msg/JointTrajectoryPoint"], T["builtin_interfaces/msg/Duration"]
    empty = np.zeros(0)
    return CODEC.encode(T[TRAJECTORY](header=header, joint_names=list(names), points=[
        point(positions=np.asarray(pos, dtype=np.float64), velocities=empty, accelerations=empty, effort=empty,
              time_from_start=duration(sec=int(s), nanosec=round((s % 1) * 1e9))) for pos, s in points]))


def test_names_keys_and_qos_follow_rmw_zenoh():
    assert dds_type(JOINT_STATE) == "sensor_msgs::msg::dds_::JointState_"
    assert topic_key(3, "/arm/joint_commands", MULTI_ARRAY, "H") == \
        "3/arm/joint_commands/std_msgs::msg::dds_::Float64MultiArray_/H"
    assert qos_field(10) == "::,10:,:,:,,"
    assert qos_field(42) == "::,:,:,:,,"  # rmw_zenoh's default depth leaves the field empty
    assert {t: CODEC.hash(t) for t in JAZZY_HASHES} == JAZZY_HASHES
    seq, source_ns, gid = read_attachment(attachment(7, 123, bytes(range(16))))
    assert (seq, source_ns, gid) == (7, 123, bytes(range(16)))
    assert len(attachment(7, 123, bytes(16)).to_bytes()) == 8 + 8 + 1 + 16  # int64, int64, length, GID


def test_liveliness_tokens_announce_the_node_and_its_topics(served, peer):
    zid = str(served.session.info.zid())
    replies = peer.session.liveliness().get("@ros2_lv/0/**", timeout=5)
    tokens = sorted(str(r.ok.key_expr) for r in replies if r.ok is not None)
    prefix = f"@ros2_lv/0/{zid}/0/"
    node = "%/%/dynabrain_arm"
    endpoints = {("MP", "%clock", CLOCK, "1"), ("MP", "%tf", TF, "100"), ("MP", "%joint_states", JOINT_STATE, "10"),
                 ("MS", "%arm%joint_commands", MULTI_ARRAY, "10"), ("MS", "%arm%joint_trajectory", TRAJECTORY, "10")}
    assert f"{prefix}0/NN/{node}" in tokens
    found, ids = set(), set()
    for token in tokens:
        parts = token.split("/")
        assert token.startswith(prefix) and "" not in parts
        if parts[5] == "NN":
            assert len(parts) == 9
            continue
        assert len(parts) == 13, token  # admin, domain, zid, node id, entity id, kind, enclave, ns, node, topic...
        ids.add(parts[4])
        qos = parts[12].split(":")
        assert qos[0] == qos[1] == "" and qos[3:] == [",", ",", ",,"]
        found.add((parts[5], parts[9], parts[10].replace("::dds_::", "/").replace("::", "/")[:-1], qos[2][1:]))
        assert parts[11] == JAZZY_HASHES[next(t for t in JAZZY_HASHES if dds_type(t) == parts[10])]
        assert "/".join(parts[6:9]) == node
    assert found == endpoints
    assert len(ids) == len(endpoints)


def test_raw_subscriber_decodes_joint_states_tf_and_clock(served, peer):
    world = served.world
    served.main.service.call("set", p.SetArgs(name="servo.target", value=[0.4, 0.6, -0.5]))
    wait_for(lambda: peer.latest(JOINT_STATE), what="a JointState", between=lambda: tick(served, 5))
    tick(served, 100 - world.tick_count % 5)  # ends on a published tick (every 5 ticks at 100 Hz, 2 ms steps)
    assert world.tick_count % 5 == 0
    t_ns = world.time_ns
    clock = wait_for(lambda: (c := peer.latest(CLOCK)) and c.clock.sec * 10**9 + c.clock.nanosec == t_ns and c,
                     what="the last tick's clock")
    assert clock.clock.sec * 10**9 + clock.clock.nanosec == t_ns
    js = wait_for(lambda: (m := peer.latest(JOINT_STATE)) and m.header.stamp == clock.clock and m, what="JointState")
    assert js.name == ["yaw", "shoulder", "elbow"]
    for i, joint in enumerate(js.name):
        assert js.position[i] == world.get(f"core.{joint}.q")
        assert js.velocity[i] == world.get(f"core.{joint}.qd")
        assert js.effort[i] == world.get(f"core.{joint}.force")
    assert abs(js.position[1]) > 0.05  # the arm moves toward its targets
    tf = wait_for(lambda: (m := peer.latest(TF)) and m.transforms[0].header.stamp == clock.clock and m, what="TF")
    assert [t.child_frame_id for t in tf.transforms] == ["floor", "base", "turret", "upper", "fore", "cube"]
    for t in tf.transforms:
        assert t.header.frame_id == "world"
        r, v = t.transform.rotation, t.transform.translation
        assert [v.x, v.y, v.z] == list(world.get(f"core.{t.child_frame_id}.pos"))
        assert [r.w, r.x, r.y, r.z] == list(world.get(f"core.{t.child_frame_id}.quat"))  # ROS: x y z w
    by_key: dict[str, list[int]] = {}
    for key, _, att in peer.samples:
        assert att is not None and len(att) == 33
        seq, source_ns, gid = read_attachment(_zbytes(att))
        assert abs(source_ns - time.time_ns()) < 60e9 and len(gid) == 16
        by_key.setdefault(key, []).append(seq)
    assert set(by_key) == {topic_key(0, _TOPICS[t], t, JAZZY_HASHES[t]) for t in (CLOCK, TF, JOINT_STATE)}
    for seqs in by_key.values():
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)


def _zbytes(data: bytes):
    import zenoh

    return zenoh.ZBytes(data)


def test_float64_multi_array_moves_the_servo_targets(served, peer):
    peer.send("/arm/joint_commands", MULTI_ARRAY, float64s([0.2, -0.3, 0.25]))
    wait_for(lambda: served.main.service.has_pending, what="the command held for the next step")
    tick(served, 1)
    assert list(served.world.get("servo.target")) == [0.2, -0.3, 0.25]
    tick(served, 300)
    assert abs(served.world.get("core.shoulder.q") + 0.3) < 0.05


def test_joint_trajectory_is_followed_in_simulated_time(served, peer):
    peer.send("/arm/joint_commands", MULTI_ARRAY, float64s([0.0, 0.0, 0.0]))
    wait_for(lambda: served.main.service.has_pending, what="the command")
    tick(served, 1)
    before = served.ros2.counts.trajectories
    peer.send("/arm/joint_trajectory", TRAJECTORY, trajectory(["elbow", "yaw"], [([0.5, -0.2], 0.1)]))
    wait_for(lambda: served.ros2.counts.trajectories > before, what="the trajectory taken")
    tick(served, 26)  # 50 ms of 100: about half way (the target set by a tick applies before the next)
    elbow, yaw = served.world.get("servo.elbow.target"), served.world.get("servo.yaw.target")
    assert 0.22 < elbow < 0.26 and -0.105 < yaw < -0.085
    assert served.world.get("servo.shoulder.target") == 0.0  # a joint the trajectory does not name
    tick(served, 40)
    assert list(served.world.get("servo.target")) == [-0.2, 0.0, 0.5]


@pytest.mark.parametrize(("topic", "msgtype", "payload", "field"), [
    ("/arm/joint_commands", MULTI_ARRAY, float64s([0.1, 0.2]), "field data has 2 values"),
    ("/arm/joint_commands", MULTI_ARRAY, float64s([0.1, float("nan"), 0.2]), "field data[1] (shoulder)"),
    ("/arm/joint_commands", MULTI_ARRAY, b"\x00\x01\x00\x00\xff\xff", "not CDR of std_msgs/msg/Float64MultiArray"),
    ("/arm/joint_trajectory", TRAJECTORY, trajectory(["wrist"], [([0.1], 1.0)]), "field joint_names"),
    ("/arm/joint_trajectory", TRAJECTORY, trajectory(["elbow"], [([0.1, 0.2], 1.0)]), "field points[0].positions"),
    ("/arm/joint_trajectory", TRAJECTORY, trajectory(["elbow"], [([0.1], 1.0), ([0.2], 0.5)]),
     "field points[1].time_from_start"),
])
def test_bad_commands_are_reported_naming_the_field(served, peer, topic, msgtype, payload, field):
    tick(served, 1)
    target = served.world.get("servo.target").copy()
    peer.send(topic, msgtype, payload)
    message = wait_for(lambda: next((e for e in peer.errors() if field in e), None), what=f"an error naming {field}")
    assert topic in message
    tick(served, 5)
    assert list(served.world.get("servo.target")) == list(target)


def test_commands_are_refused_while_a_brain_holds_the_world(served, peer):
    with BrainClient("arm", connect=served.endpoints[0], timeout=10) as brain:
        brain.acquire(lease=10)
        tick(served, 1)
        target = served.world.get("servo.target").copy()
        peer.send("/arm/joint_commands", MULTI_ARRAY, float64s([1.0, 1.0, 1.0]))
        refusal = wait_for(lambda: peer.errors("input_refused"), what="input_refused")
        assert '"brain": "ros2"' in refusal[0]
        brain.release()
    tick(served, 2)
    assert list(served.world.get("servo.target")) == list(target)


@pytest.fixture()
def own():
    """A served world of its own, without a rig, and a peer."""
    world = load_world(ARM)
    server = BridgeServer(world, Settings(listen=["tcp/127.0.0.1:0"]), ServeOptions(ros2=Ros2Options()))
    try:
        server.open()
        peer = Peer(server.endpoints)
        yield server, peer
        peer.close()
    finally:
        server.close()
        world.close()


def test_a_body_added_while_serving_appears_on_tf(own):
    server, peer = own
    wait_for(lambda: peer.latest(TF), what="a TFMessage", between=lambda: tick(server, 5))
    server.world.add_body(name="ball", shape="sphere", size=["40mm"], mass="50g", pos=[0.3, 0, "1m"])
    tick(server, 5)
    tf = wait_for(lambda: (m := peer.latest(TF)) and len(m.transforms) == 7 and m, what="the ball on /tf")
    ball = tf.transforms[-1]
    assert ball.child_frame_id == "ball"
    v = ball.transform.translation
    assert [v.x, v.y, v.z] == list(server.world.get("core.ball.pos"))


def test_tokens_leave_with_the_server(own):
    server, peer = own
    seen: dict[str, str] = {}
    peer.session.liveliness().declare_subscriber(
        "@ros2_lv/0/**", lambda s: seen.__setitem__(str(s.key_expr), str(s.kind)), history=True)
    wait_for(lambda: len(seen) == 4, what="node and three publisher tokens")  # no rig: no subscriptions
    assert not any("/MS/" in k for k in seen)
    server.close()
    wait_for(lambda: all(v == "SampleKind.DELETE" for v in seen.values()), what="tokens undeclared")


def test_serve_ros2_flag_on_the_domain_of_ros_domain_id():
    env = {"ROS_DOMAIN_ID": "7"}
    with ServerProcess(ARM, "--robot", "arm=servo", "--ros2", "--start", "--realtime", env=env) as server:
        session, _ = open_session(Settings(connect=[server.endpoint]))
        got: list[bytes] = []
        key = topic_key(7, "/joint_states", JOINT_STATE, JAZZY_HASHES[JOINT_STATE])
        session.declare_subscriber(key, lambda s: got.append(s.payload.to_bytes()))
        wait_for(lambda: got, timeout=10, what="a JointState on domain 7")
        assert CODEC.decode(got[-1], JOINT_STATE).name == ["yaw", "shoulder", "elbow"]
        session.close()
        with BrainClient("arm", connect=server.endpoint, timeout=10) as brain:
            ros2 = brain.status()["server"]["ros2"]
        assert (ros2["node"], ros2["domain_id"], ros2["rmw_zenoh"]) == ("/dynabrain_arm", 7, "0.2.10")
        assert ros2["counts"]["published"] > 0 and ros2["every_ticks"] == 5
    assert "Traceback" not in server.output
