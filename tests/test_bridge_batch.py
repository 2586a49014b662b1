"""``batch`` over the bridge: a remote brain asks the served world for N futures in one call.

`dynabrain serve` runs in another process with worker processes for its batches; what the brain gets
back equals a local ``Batch(world, backend="serial")`` on a world loaded from the same scenario in the
same state, bit for bit; the served world is left as it was; a kept final state is a snapshot that
``restore`` continues from; bad requests are refused with the reason, and the server goes on.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from dynabrain.bridge import BadRequestError, BatchReply, BrainClient, WorldBusyError, WorldRefusedError, frames
from dynabrain.bridge import protocol as p
from dynabrain.bridge.batching import BatchSettings
from dynabrain.bridge.calls import WorldService
from dynabrain.bridge.testing import ServerProcess
from dynabrain.bridge.zenoh_io import Settings, open_session
from dynabrain.orchestrator import Batch, load_world

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, "bridge", "arm.yaml")
MAX_TICKS = 5000
TICKS = 60
RECORD = ["core.joint_q", "servo.force", "cube.pos"]
KP = [30.0, 60.0, 90.0]


@pytest.fixture(scope="module")
def server():
    with ServerProcess(ARM, "--batch-backend", "processes", "--batch-workers", "2",
                       "--batch-max-ticks", str(MAX_TICKS), timeout=60) as srv:
        yield srv
    assert "Traceback" not in srv.output, srv.output


@pytest.fixture(scope="module")
def start(server):
    """The served world as it was served: each test starts from there."""
    with BrainClient("arm", connect=server.endpoint, timeout=20) as b:
        return b.snapshot()


@pytest.fixture()
def brain(server, start):
    with BrainClient("arm", connect=server.endpoint, timeout=120) as b:
        b.restore(start)
        yield b


@pytest.fixture()
def local():
    world = load_world(ARM)
    yield world
    world.close()


def bits(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, dtype=np.float64).tobytes()


def targets() -> np.ndarray:
    """Per-branch, per-tick servo targets: each branch swings the shoulder to its own angle."""
    out = np.zeros((3, TICKS, 3))
    for b in range(3):
        out[b, :, 1] = (0.2 + 0.3 * b) * np.linspace(0, 1, TICKS)
        out[b, :, 2] = -0.4
    return out


def prepare(brain: BrainClient, local) -> None:
    """The same calls on the served world and the local one: the same state, bit for bit."""
    for target in (brain, local):
        target.set("servo.target", [0.3, 0.5, -0.8])
        target.tick(40)


def test_futures_equal_a_local_batch_and_the_served_world_is_unchanged(brain, local):
    prepare(brain, local)
    view = brain.view(["core.joint_q", "core.joint_qd", "cube.pos", "servo.target"])
    before = brain.read(view)
    reply = brain.batch(TICKS, branches=3, inputs={"servo.target": targets()}, params={"servo.kp": KP},
                        record=RECORD, keep_states=True)
    assert isinstance(reply, BatchReply) and reply.ok and reply.backend == "processes"
    assert reply.tick == 40 and reply.ticks == TICKS
    with Batch(local, backend="serial") as batch:
        ref = batch.run(TICKS, branches=3, inputs={"servo.target": targets()}, params={"servo.kp": KP},
                        record=RECORD)
    for name in RECORD:
        assert reply.signals[name].shape == ref.signals[name].shape == (3, TICKS, *np.shape(local.get(name)))
        assert bits(reply.signals[name]) == bits(ref.signals[name]), f"{name} differs from the local batch"
    assert not np.array_equal(reply.signals["core.joint_q"][0], reply.signals["core.joint_q"][2])  # three futures
    after = brain.read(view)  # the served world: same tick, same values
    assert after.tick == before.tick == 40 and bits(after.values) == bits(before.values)
    assert brain.get("servo.kp") == 60.0 and brain.status()["tick"] == 40
    assert [s.tick for s in reply.snapshots] == [40 + TICKS] * 3
    assert {s.id for s in reply.snapshots} <= set(brain.status()["snapshots"])


def test_a_kept_final_state_is_a_snapshot_to_continue_from(brain, local):
    prepare(brain, local)
    reply = brain.batch(TICKS, branches=3, inputs={"servo.target": targets()}, params={"servo.kp": KP},
                        record=["core.joint_q"], keep_states=True)
    with Batch(local, backend="serial") as batch:
        ref = batch.run(TICKS, branches=3, inputs={"servo.target": targets()}, params={"servo.kp": KP},
                        record=["core.joint_q"], keep_states=True)
    brain.restore(reply.snapshots[1])
    assert brain.status()["tick"] == 40 + TICKS and brain.get("servo.kp") == KP[1]
    assert bits(brain.get("core.joint_q")) == bits(reply.signals["core.joint_q"][1, -1])
    local.import_state(ref.states[1])
    view = brain.view(["core.joint_q", "core.joint_qd", "cube.pos"])
    frame = brain.tick(25, view=view)
    local.tick(25)
    assert frame.tick == local.tick_count == 40 + TICKS + 25
    assert bits(frame.values) == bits(np.concatenate([np.ravel(local.get(n)) for n in view.names]))
    # a kept state starts another batch, as does a snapshot of the world
    again = brain.batch(10, starts=[reply.snapshots[0], reply.snapshots[2]], record=["core.joint_q"])
    with Batch(local, backend="serial") as batch:
        ref2 = batch.run(10, starts=[ref.states[0], ref.states[2]], record=["core.joint_q"])
    assert bits(again.signals["core.joint_q"]) == bits(ref2.signals["core.joint_q"])
    assert again.snapshots == [None, None]  # keep_states is off by default


def test_starts_from_snapshots_of_the_served_world(brain, local):
    prepare(brain, local)
    first = brain.snapshot()
    brain.tick(15)
    local_first = local.snapshot()
    local.tick(15)
    reply = brain.batch(20, starts=[first.id, first.id, brain.snapshot().id], params={"servo.kd": [1.0, 2.0, 3.0]},
                        record=["core.joint_q"])
    with Batch(local, backend="serial") as batch:
        ref = batch.run(20, starts=[local_first, local_first, local.snapshot()], params={"servo.kd": [1.0, 2.0, 3.0]},
                        record=["core.joint_q"])
    assert bits(reply.signals["core.joint_q"]) == bits(ref.signals["core.joint_q"])
    assert reply.tick == brain.status()["tick"] == 55


def test_a_failing_branch_is_reported_and_the_others_return(brain):
    reply = brain.batch(10, branches=3, params={"servo.kp": [60.0, -1.0, 60.0]}, record=["core.joint_q"],
                        keep_states=True)
    assert reply.failed == [1] and not reply.ok
    assert "kp must be a finite number >= 0" in reply.status[1].reason
    assert np.isnan(reply.signals["core.joint_q"][1]).all() and np.isfinite(reply.signals["core.joint_q"][0]).all()
    assert reply.snapshots[1] is None and reply.snapshots[0] is not None


@pytest.mark.parametrize(("args", "kind", "message"), [
    ({"ticks": 10, "branches": 3, "record": ["core.joint_z"]}, "refused", r"no signal.*'core\.joint_z'"),
    ({"ticks": 10, "branches": 3, "inputs": {"servo.target": [[0.0, 0.0]] * 10}}, "refused", r"shape \(10, 2\)"),
    ({"ticks": 10, "branches": 2, "inputs": {"servo.kp": [1.0] * 10}}, "refused", "is a parameter"),
    ({"ticks": 10, "branches": 2, "params": {"servo.nope": 1.0}}, "refused", "nope"),
    ({"ticks": 10, "starts": [999]}, "refused", "no snapshot 999"),
    ({"ticks": 10, "branches": 2, "starts": [0, 0, 0]}, "bad_request", "3 starts for 2 branches"),
    ({"ticks": 10}, "bad_request", "say how many branches"),
    ({"ticks": 2000, "branches": 3}, "bad_request", rf"6000 branch-ticks, over this server's limit of {MAX_TICKS}"),
    ({"ticks": 1, "branches": 65, "keep_states": True}, "bad_request", "at most 64 snapshots"),
])
def test_bad_requests_are_refused_with_the_reason(brain, args, kind, message):
    tick = brain.status()["tick"]
    with pytest.raises(WorldRefusedError, match=message) as err:
        brain.call("batch", **args)
    assert err.value.kind == kind
    assert brain.status()["tick"] == tick and brain.tick(2) == tick + 2  # nothing ran; the server goes on


def test_malformed_commands_get_bad_request_from_the_client_and_the_server(server, brain):
    with pytest.raises(BadRequestError, match="branches: Input should be greater than or equal to 1"):
        brain.batch(10, branches=0)
    with pytest.raises(BadRequestError, match="ticks: Input should be less than or equal to 1000000"):
        brain.batch(2_000_000, branches=1)
    with pytest.raises(BadRequestError, match="NaN or infinite"):
        brain.batch(2, branches=1, inputs={"servo.target": np.full((2, 3), np.nan)})
    session, _ = open_session(Settings(connect=[server.endpoint]))
    try:  # the same commands sent raw reach the server, which refuses them the same way
        def refusal(payload: bytes) -> dict:
            reply = next(iter(session.get(p.call_key("arm", "batch"), payload=payload, timeout=20)))
            return json.loads(reply.err.payload.to_bytes())

        for args, kind, message in (
                ({"ticks": 10, "branches": 0}, "bad_request", "greater than or equal to 1"),
                ({"branches": 1}, "bad_request", "args.ticks: Field required"),
                ({"ticks": 10, "branches": 1, "inputs": {"servo.target": [["a"]]}}, "refused", "expected finite")):
            body = refusal(json.dumps({"v": 1, "brain": "raw", "args": args}).encode())
            assert body["error"] == kind and message in body["message"], body
        huge = b'{"v": 1, "args": {"ticks": 1, "branches": 1, "record": ["' + b"x" * p.MAX_BATCH_BYTES + b'"]}}'
        body = refusal(huge)
        assert body["error"] == "bad_request" and "over the limit of 8388608" in body["message"], body
    finally:
        session.close()
    assert server.alive() and brain.tick(1) == brain.status()["tick"]


def test_the_recorded_values_must_fit_one_reply():
    world = load_world(ARM)
    service = WorldService(world, instance=1, batch=BatchSettings("serial", max_ticks=10**6))
    try:
        with pytest.raises(p.ProtocolError, match=r"\d+ values, over the 1048576 one reply carries") as err:
            service.do_batch(p.BatchArgs(ticks=100_000, branches=10, record=["core.body_pos"]))
        assert err.value.kind == "bad_request" and world.tick_count == 0
    finally:
        service.close()
        world.close()


def test_a_batch_is_not_read_only_while_another_brain_holds_the_world(server, brain):
    with BrainClient("arm", connect=server.endpoint, timeout=20) as holder:
        holder.acquire(lease=30)
        try:
            with pytest.raises(WorldBusyError):
                brain.batch(5, branches=2)
            assert holder.batch(5, branches=2).ok
        finally:
            holder.release()


def test_a_fork_runs_its_batches_in_process(brain):
    fork = brain.fork()
    try:
        fork.tick(10)
        reply = fork.batch(10, branches=2, params={"servo.kp": [20.0, 80.0]}, record=["core.joint_q"])
        assert reply.ok and reply.backend == "serial" and reply.tick == 10
        assert fork.status()["batch"]["max_ticks"] == MAX_TICKS
    finally:
        fork.close()
    status = brain.status()["batch"]
    assert status == {"backend": "processes", "workers": 2, "max_ticks": MAX_TICKS}


def test_batch_frames_carry_their_description_after_the_values():
    data = frames.batch(np.arange(6.0), b'{"a":1}', source=3, seq=4, stamp=5)
    frame = frames.unpack(data, frames.BATCH)
    assert frame.values.tolist() == list(range(6)) and frame.meta == b'{"a":1}' and frame.aux == 7
    assert (frame.source, frame.seq, frame.stamp) == (3, 4, 5) and frame.pack() == data
    with pytest.raises(p.ProtocolError, match="6 values and 7 bytes of description"):
        frames.unpack(data[:-1])
    assert frames.unpack(frames.pack(frames.STATE, [1.0])).meta == b""


def test_serve_refuses_an_unknown_batch_backend():
    out = subprocess.run([sys.executable, "-m", "dynabrain.orchestrator.cli", "serve", ARM, "--batch-backend", "warp"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "batch backend 'warp' is unknown" in out.stderr, out.stderr
