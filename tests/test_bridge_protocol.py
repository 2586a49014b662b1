"""The bridge's wire format and its world-side logic, without a network: frames, command validation
(fuzzed), the schema file, the PD servo, and `WorldService` on a real MuJoCo world."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dynabrain.bridge import frames
from dynabrain.bridge import protocol as p
from dynabrain.bridge.calls import WorldService
from dynabrain.bridge.schema import DEFAULT_PATH, render
from dynabrain.bridge.servo import PDServo
from dynabrain.orchestrator.kernel.checks import check_module
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.scenario import load_world

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, "bridge", "arm.yaml")


# -- frames --------------------------------------------------------------------------------------------------------
def test_frames_round_trip():
    data = frames.pack(frames.STATE, np.arange(5.0), source=7, seq=12, stamp=24_000_000, aux=3)
    f = frames.unpack(data, frames.STATE)
    assert (f.kind, f.source, f.seq, f.stamp, f.aux) == (frames.STATE, 7, 12, 24_000_000, 3)
    assert np.array_equal(f.values, np.arange(5.0)) and f.pack() == data
    q, qd = frames.split_robot_state(frames.unpack(frames.robot_state(
        np.array([1.0, 2.0]), np.array([3.0, 4.0]), mode=frames.ENABLED, source=1, seq=2, stamp_ns=3)))
    assert q.tolist() == [1.0, 2.0] and qd.tolist() == [3.0, 4.0]
    cmd = frames.unpack(frames.robot_cmd(frames.OP_MOVE, np.ones(3), seq=1, stamp_ns=5, deadline_ns=100_000_000))
    frames.check_robot_cmd(cmd, 3)
    assert cmd.aux == 100_000  # the deadline in microseconds


@pytest.mark.parametrize(("payload", "message"), [
    (b"DBF1", "shorter than its 40-byte header"),
    (b"XXXX" + bytes(36), "not a dynabrain frame"),
    (frames.HEADER.pack(frames.MAGIC, 9, 0, 0, 0, 0, 0, 0), "unknown frame kind 9"),
    (frames.HEADER.pack(frames.MAGIC, 2, 0, 0, 0, 0, 0, 2) + bytes(8), "declares 2 values"),
    (frames.HEADER.pack(frames.MAGIC, 2, 0, 0, 0, 0, 0, 2**30), "over the limit"),
    (frames.pack(frames.ROBOT_STATE, [np.nan, 0.0], aux=1), "NaN or infinite"),
    (frames.pack(frames.STATE, [0.0]), "expected a robot state frame"),
])
def test_malformed_frames_are_refused_with_the_reason(payload, message):
    with pytest.raises(p.ProtocolError, match=message):
        frames.unpack(payload, frames.ROBOT_STATE, finite=True)


def test_robot_frames_are_checked_against_their_joints():
    with pytest.raises(p.ProtocolError, match="carries 2 values, expected 3"):
        frames.check_robot_cmd(frames.unpack(frames.robot_cmd(frames.OP_MOVE, np.ones(2), seq=1, stamp_ns=1,
                                                               deadline_ns=10**8)), 3)
    with pytest.raises(p.ProtocolError, match="for 2 joints carries 3 values"):
        frames.split_robot_state(frames.unpack(frames.pack(frames.ROBOT_STATE, [0.0] * 3, aux=2)))


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=120))
def test_any_bytes_decode_to_a_frame_or_a_protocol_error(data):
    try:
        frame = frames.unpack(data)
    except p.ProtocolError:
        return
    assert len(data) == frames.HEADER_SIZE + 8 * frame.values.size + len(frame.meta)


# -- commands -----------------------------------------------------------------------------------------------------
EXAMPLES = {
    "batch": {"ticks": 10, "branches": 2, "params": {"servo.kp": [40, 60]}, "record": ["core.joint_q"]},
    "tick": {"n": 10, "view": 1}, "backtick": {"n": 3}, "start": {"realtime": True, "until": 2.5}, "stop": {},
    "make": {"objects": ["cube", "b_*"]}, "make_joint": {"a": "fore", "b": "cube"}, "remove_joint": {"name": "j"},
    "no_collision": {"objects": ["a", "b"]}, "place": {"body": "cube", "pos": [0, 0, 1]},
    "set": {"name": "servo.target", "value": [0.1, 0.2, 0.3]}, "get": {"name": "cube.pos"},
    "add_module": {"module": {"name": "k", "python": "dynabrain.modules.basic:Gain", "params": {"k": 2}}},
    "remove_module": {"name": "k"}, "connect": {"src": "a.y", "dst": "b.u"}, "disconnect": {"dst": "b.u"},
    "snapshot": {}, "restore": {"snapshot": 0}, "drop_snapshot": {"snapshot": 0}, "fork": {"name": "plan"},
    "close": {}, "status": {}, "view": {"signals": ["core.*.q"]}, "read": {"view": 1}, "drop_view": {"view": 1},
    "acquire": {"lease": 5}, "release": {}, "motion": {"robot": "arm", "targets": {"yaw": 0.1}, "route": "both"},
    "robot_enable": {"robot": "arm"}, "robot_stop": {"robot": "arm"}, "robot_status": {"robot": "arm"},
    "add_body": {"name": "lid", "shape": "box", "size": ["100mm", 0.1, 0.02], "pos": [0, 0, "0.2m"], "mass": "50g",
                 "color": "blue", "friction": 0.3},
    "remove_body": {"name": "lid"}, "set_material": {"body": "lid", "restitution": 0.4},
}


def test_every_call_has_an_example_that_validates():
    assert set(EXAMPLES) == set(p.CALLS)
    for call, args in EXAMPLES.items():
        env, parsed = p.decode_command(call, json.dumps({"v": 1, "brain": "b", "args": args}).encode())
        assert env.brain == "b" and parsed == p.CALLS[call].model_validate(args)


@pytest.mark.parametrize(("call", "payload", "message"), [
    ("tick", {"args": {"n": "3"}}, r"args\.n: Input should be a valid integer"),
    ("tick", {"args": {"n": 0}}, r"args\.n: Input should be greater than or equal to 1"),
    ("tick", {"args": {"n": 1}, "extra": 1}, "extra: Extra inputs are not permitted"),
    ("set", {"args": {"name": "x"}}, r"args\.value: Field required"),
    ("place", {"args": {"body": "a", "pos": [1, 2]}}, r"args\.pos: List should have at least 3 items"),
    ("motion", {"args": {"robot": "arm", "targets": [1], "route": "moon"}}, r"args\.route: Input should be"),
    ("tick", {"v": 2}, "v: Input should be 1"),
])
def test_bad_commands_name_the_field(call, payload, message):
    with pytest.raises(p.ProtocolError, match=message) as err:
        p.decode_command(call, json.dumps(payload).encode())
    assert err.value.kind == "bad_request"


def test_unknown_and_oversized_commands_are_refused():
    with pytest.raises(p.ProtocolError, match=r"did you mean 'backtick'") as err:
        p.decode_command("backtik", b"{}")
    assert err.value.kind == "unknown_call"
    with pytest.raises(p.ProtocolError, match="over the limit"):
        p.decode_command("status", b" " * (p.MAX_COMMAND_BYTES + 1))
    with pytest.raises(p.ProtocolError, match="Invalid JSON"):
        p.decode_command("status", b"{not json")


JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
                    max_leaves=12)


@settings(max_examples=150, deadline=None)
@given(st.sampled_from(sorted(p.CALLS)), st.dictionaries(st.sampled_from(["v", "brain", "args", "instance", "x"]),
                                                          JSON, max_size=4))
def test_any_json_command_validates_or_is_a_protocol_error(call, envelope):
    try:
        p.decode_command(call, json.dumps(envelope).encode())
    except p.ProtocolError as exc:
        assert exc.kind == "bad_request" and str(exc)


def test_error_replies_encode_non_finite_numbers_as_null():
    assert json.loads(p.encode({"x": [1.0, float("nan"), float("inf")]})) == {"x": [1.0, None, None]}


# -- the schema file ---------------------------------------------------------------------------------------------------
def test_the_schema_file_is_up_to_date():
    with open(DEFAULT_PATH, encoding="utf-8") as fh:
        assert fh.read() == render(), "bridge/protocol.schema.json is stale: run python -m dynabrain.bridge.schema"


def test_a_foreign_client_can_validate_with_the_schema_file():
    jsonschema = pytest.importorskip("jsonschema", reason="jsonschema is not installed")
    with open(DEFAULT_PATH, encoding="utf-8") as fh:
        schema = json.load(fh)

    validator = jsonschema.Draft202012Validator(schema)

    def check(ref: str, instance) -> None:
        validator.evolve(schema={"$ref": f"#/$defs/{ref}", "$defs": schema["$defs"]}).validate(instance)

    for call, args in EXAMPLES.items():
        check(schema["x-calls"][call]["$ref"].rsplit("/", 1)[1], args)
    check("Envelope", {"v": 1, "brain": "b", "args": {}})
    with pytest.raises(jsonschema.ValidationError):
        check("TickArgs", {"n": "3"})
    with pytest.raises(jsonschema.ValidationError):
        check("ErrorReply", {"error": "oops", "message": "m"})


# -- world-side logic, on a real world -------------------------------------------------------------------------------
def test_pd_servo_passes_check_module():
    world = load_world(ARM)
    try:
        check_module(PDServo("s2", targets=["yaw", "elbow"], kp=10.0), core=world.core).assert_ok()
    finally:
        world.close()
    with pytest.raises(DynabrainError, match="must name the joints"):
        PDServo("s3")


@pytest.fixture()
def service():
    world = load_world(ARM)
    yield WorldService(world, instance=42, stream=["core.joint_q"])
    world.close()


def test_views_follow_structure_changes(service):
    view = service.do_view(p.ViewArgs(signals=["servo.target", "cube.pos"]))
    assert [s["name"] for s in view["signals"]] == ["servo.target", "core.cube.pos"]
    service.world.set("servo.target", [0.1, 0.2, 0.3])
    service.do_add_module(p.AddModuleArgs(module=p.ModuleSpec(name="k", python="dynabrain.modules.basic:Counter")))
    frame = frames.unpack(service.do_read(p.ViewRef(view=view["view"])), frames.STATE)
    assert frame.values[:3].tolist() == [0.1, 0.2, 0.3] and frame.source == 42  # re-resolved on the new bus
    k_view = service.do_view(p.ViewArgs(signals=["k.count"]))
    service.do_remove_module(p.NameArgs(name="k"))
    with pytest.raises(DynabrainError, match=r"no signal 'k\.count'"):
        service.do_read(p.ViewRef(view=k_view["view"]))
    with pytest.raises(DynabrainError, match=r"pattern 'nothing\.\*' matches no signal"):
        service.do_view(p.ViewArgs(signals=["nothing.*"]))


def test_inputs_wait_for_the_step_boundary(service):
    service.submit({"servo.target": [0.5, 0.0, 0.0]})
    assert service.world.get("servo.target")[0] == 0.0
    service.do_tick(p.TickArgs(n=1))
    assert service.world.get("servo.target")[0] == 0.5
    errors: list[str] = []
    service.on_input_error = errors.append
    service.submit({"servo.nope": 1.0, "core.friction": 0.3})
    service.do_tick(p.TickArgs(n=1))
    assert service.world.get("core.friction") == 0.3 and "servo.nope" in errors[0]


def test_snapshots_are_bounded_and_modules_allow_listed(service):
    service.max_snapshots = 2
    ids = [service.do_snapshot(p.NoArgs())["snapshot"] for _ in range(3)]
    with pytest.raises(DynabrainError, match=f"no snapshot {ids[0]}"):
        service.do_restore(p.SnapshotRef(snapshot=ids[0]))
    service.do_restore(p.SnapshotRef(snapshot=ids[2]))
    with pytest.raises(DynabrainError, match="not allowed on this server"):
        service.make_module(p.ModuleSpec(name="x", python="subprocess:Popen"))
    with pytest.raises(DynabrainError, match="relative to the scenario's folder"):
        service.make_module(p.ModuleSpec(name="x", fmu="/etc/passwd"))


def test_motion_commands_set_the_rig_servo(service):
    rig = service.add_rig("arm", "servo")
    assert rig.joints == ("yaw", "shoulder", "elbow")
    assert service.motion_inputs(rig, {"elbow": 0.3}) == {"servo.elbow.target": 0.3}
    with pytest.raises(DynabrainError, match="has 3 joints"):
        service.motion_inputs(rig, [0.1])
    with pytest.raises(DynabrainError, match="not finite"):
        service.motion_inputs(rig, [0.1, float("inf"), 0.0])
    with pytest.raises(DynabrainError, match="no joint 'wrist'"):
        service.motion_inputs(rig, {"wrist": 0.1})
