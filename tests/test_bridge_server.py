"""The bridge for real: `dynabrain serve` in another process on loopback, brains calling it over Zenoh.

A brain's calls give bit-identical states to the same calls made in-process; errors say who refused
and why; holds, forks, snapshots, inputs by subscription, the state stream and the loop work; the
server survives thousands of malformed payloads and a brain that dies while holding the world.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from dynabrain.bridge import (
    BadRequestError,
    BrainClient,
    CallTimeoutError,
    NoWorldError,
    WorldBusyError,
    WorldRefusedError,
    WorldRestartedError,
)
from dynabrain.bridge import protocol as p
from dynabrain.bridge.testing import Process, ServerProcess, wait_for
from dynabrain.bridge.zenoh_io import Settings, open_session
from dynabrain.orchestrator.kernel.world import World
from dynabrain.orchestrator.scenario import load_world

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, "bridge", "arm.yaml")
EVERYTHING = ["core.body_pos", "core.body_quat", "core.body_linvel", "core.body_angvel", "core.joint_q",
              "core.joint_qd", "servo.force", "servo.target"]


@pytest.fixture(scope="module")
def server():
    with ServerProcess(ARM, "--lease", "1s") as srv:
        yield srv
    assert "Traceback" not in srv.output, srv.output


@pytest.fixture()
def brain(server):
    with BrainClient("arm", connect=server.endpoint, timeout=20) as b:
        yield b




def local_values(world: World, names) -> np.ndarray:
    return np.concatenate([np.atleast_1d(world.get(n)).ravel() for n in names])


SCRIPT = [
    ("set", "servo.target", [0.4, 0.7, -1.0]),
    ("tick", 150),
    ("backtick", 60),
    ("tick", 40),
    ("make", ["base", "cube"]),
    ("tick", 30),
    ("add_module", {"name": "count", "python": "dynabrain.modules.basic:Counter"}),
    ("set", "core.friction", 0.5),
    ("no_collision", ["fore", "cube"]),
    ("tick", 25),
    ("make_joint", ("fore", "cube")),
    ("tick", 20),
    ("backtick", 30),
    ("set", "servo.target", [-0.3, 0.2, 0.5]),
    ("tick", 35),
]


def apply(target, op, arg) -> None:
    if op == "add_module":
        if isinstance(target, World):
            from dynabrain.modules.basic import Counter

            target.add_module(Counter(arg["name"]))
        else:
            target.add_module(arg)
    elif op == "make_joint":
        target.make_joint(*arg)
    else:
        getattr(target, op)(arg)


def test_brain_calls_give_the_same_states_as_in_process_calls(brain):
    local = load_world(ARM)
    try:
        view = brain.view(EVERYTHING)
        for op, *args in SCRIPT:
            if op == "set":
                brain.set(*args)
                local.set(*args)
            else:
                apply(brain, op, args[0])
                apply(local, op, args[0])
            frame = brain.read(view)
            assert frame.tick == local.tick_count, op
            assert np.array_equal(frame.values, local_values(local, view.names)), f"states differ after {op}"
        assert brain.get("count.count") == local.get("count.count") == 50.0
        assert brain.get("core.friction") == 0.5
        assert np.array_equal(brain.get("cube.pos"), local.get("cube.pos"))
        frame = brain.tick(5, view=view)  # ticks and the state after them in one round trip
        local.tick(5)
        assert frame.tick == local.tick_count and np.array_equal(frame.values, local_values(local, view.names))
        assert np.array_equal(frame["core.body_pos"][5], local.get("cube.pos"))
    finally:
        local.close()
        brain.remove_module("count")


def test_snapshot_restore_and_fork(brain):
    view = brain.view(["core.joint_q", "cube.pos"])
    snap = brain.snapshot()
    before = brain.read(view)
    brain.tick(50)
    brain.restore(snap)
    again = brain.read(view)
    assert again.tick == before.tick and np.array_equal(again.values, before.values)
    plan = brain.fork()
    try:
        plan.set("servo.target", [1.0, 0.5, 0.5])
        plan.tick(100)
        assert brain.read(view).tick == before.tick  # the fork is independent
        assert plan.get("core.joint_q")[0] > 0.3
        assert plan.world in brain.status()["server"]["forks"]
        other = brain.fork()
        other.tick(100)
        brain.tick(100)
        assert np.array_equal(other.get("core.joint_q"), brain.get("core.joint_q"))
        other.close()
    finally:
        plan.close()
    assert brain.status()["server"]["forks"] == []
    with pytest.raises(WorldRefusedError, match="no snapshot 99999"):
        brain.restore(99999)


def test_errors_say_who_refused_and_why(server, brain):
    with pytest.raises(BadRequestError, match=r"unknown call 'tikc' \(did you mean 'tick'\?\)"):
        brain.call("tikc")
    with pytest.raises(BadRequestError, match=r"args\.n: Input should be a valid integer"):
        brain.call("tick", n="3")
    with pytest.raises(BadRequestError, match="Extra inputs are not permitted"):
        brain.call("make", objects=["cube"], colour="red")
    with pytest.raises(WorldRefusedError, match=r"did you mean 'servo.target'") as err:
        brain.set("servo.targt", [0, 0, 0])
    assert err.value.kind == "refused" and err.value.call == "set"
    with pytest.raises(WorldRefusedError, match="has shape"):
        brain.set("servo.target", [1, 2])
    with pytest.raises(WorldRefusedError, match="not allowed on this server"):
        brain.add_module(name="x", python="os.path:join")
    with pytest.raises(WorldRefusedError, match="unknown object 'cubee'"):
        brain.make(["cubee"])
    with pytest.raises(CallTimeoutError, match=r"alive but did not answer tick within 0\.05 s"):
        brain.call("tick", 0.05, n=20000)  # runs on: read-only calls answer meanwhile, the next tick waits for it
    assert brain.tick() >= 20001
    with BrainClient("elsewhere", connect=server.endpoint) as lost, \
            pytest.raises(NoWorldError, match="nothing serves 'elsewhere'"):
        lost.status()
    assert brain.status()["tick"] >= 0  # the server goes on


def test_holds_keep_other_brains_read_only_until_released(server, brain):
    with BrainClient("arm", connect=server.endpoint, brain="other") as other:
        brain.acquire(lease=5)
        try:
            with pytest.raises(WorldBusyError, match="held by brain"):
                other.tick()
            assert other.status()["server"]["holder"] == brain.brain  # read-only calls still answer
            other.set_inputs({"servo.target": [9, 9, 9]})  # refused too, and reported as an event
            brain.tick(3)
            assert brain.get("servo.target")[0] != 9
        finally:
            brain.release()
        other.tick()
        other.acquire(lease=0.3)
        time.sleep(0.4)
        brain.tick()  # the lease ended without a call from `other`


def test_a_brain_that_dies_holding_the_world_releases_it(server, brain):
    code = ("import sys, time; from dynabrain.bridge import BrainClient; "
            f"b = BrainClient('arm', connect={server.endpoint!r}, brain='doomed'); b.acquire(lease=600); "
            "print('ready', flush=True); time.sleep(600)")
    with Process(["-c", code], ready="ready") as doomed:
        with pytest.raises(WorldBusyError, match="doomed"):
            brain.tick()
        doomed.kill()
    wait_for(lambda: brain.status()["server"]["holder"] is None, what="the hold to be released")
    brain.tick()


def test_a_brain_that_dies_mid_call_leaves_nothing_half_done(server, brain):
    before = brain.status()["tick"]
    code = ("import time; from dynabrain.bridge import BrainClient; "
            f"b = BrainClient('arm', connect={server.endpoint!r}, brain='short-lived'); print('ready', flush=True); "
            "b.call('tick', 60, n=50000)")
    with Process(["-c", code], ready="ready") as doomed:
        time.sleep(0.3)  # the long call (a second or more) runs in the server's worker
        doomed.kill()
    assert brain.tick() == before + 50000 + 1  # the call ran whole, and the server goes on


def test_inputs_by_subscription_apply_at_the_next_step_and_state_streams(brain):
    frames_seen: list = []
    events: list = []
    brain.subscribe_state(frames_seen.append)
    brain.subscribe_events(events.append)
    time.sleep(0.2)
    brain.set_inputs({"servo.target": [0.25, 0.0, 0.0]})
    time.sleep(0.2)
    assert brain.get("servo.target")[0] != 0.25  # held until a step boundary
    tick = brain.tick()
    assert brain.get("servo.target")[0] == 0.25
    wait_for(lambda: any(f.tick == tick for f in frames_seen), what="the state frame of the tick")
    frame = next(f for f in frames_seen if f.tick == tick)
    assert frame["core.body_pos"].shape == (6, 3)
    brain.set_inputs({"servo.nope": 1.0})  # a publication is not ordered with later calls: tick until it lands
    wait_for(lambda: brain.tick() and any(e["kind"] == "input_error" and "servo.nope" in e["detail"]["message"]
                                          for e in events), what="the input error event")
    brain.backtick()
    wait_for(lambda: any(e["kind"] == "rollback" for e in events), what="the rollback event")


def test_start_runs_the_loop_and_stop_ends_it(brain):
    t0 = brain.status()["tick"]
    brain.start(realtime=True, until=brain.status()["time"] + 10.0)
    time.sleep(0.3)
    status = brain.status()
    assert status["server"]["loop"]["running"]
    brain.tick()  # calls go on between the loop's ticks
    brain.stop()
    stopped = brain.status()["tick"]
    assert stopped > t0 + 1 and not brain.status()["server"]["loop"]["running"]
    time.sleep(0.1)
    assert brain.status()["tick"] == stopped  # the loop no longer steps
    with pytest.raises(WorldRefusedError, match="not after"):
        brain.start(until=0.0)


def test_thousands_of_fuzzed_payloads_leave_the_server_running(server, brain):
    rng = np.random.default_rng(7)
    session, _ = open_session(Settings(connect=[server.endpoint]))
    counts = {"ok": 0, "error": 0}
    kinds = set()
    calls = [*p.CALLS, "nope", "", "tick/extra", "TICK"]
    safe = [c for c in p.CALLS if c not in ("start", "fork", "tick", "backtick", "add_module", "acquire")]
    try:
        for i in range(3000):
            call = calls[int(rng.integers(len(calls)))]
            payload = fuzz_payload(rng, call if call in safe else None, i)
            replies = list(session.get(p.call_key("arm", call) if call else "dynabrain/arm/call", payload=payload,
                                       timeout=5.0))
            for r in replies:
                if r.ok is not None:
                    counts["ok"] += 1
                else:
                    body = json.loads(r.err.payload.to_bytes())
                    assert body["error"] in p.ERROR_KINDS and body["message"], body
                    kinds.add(body["error"])
                    counts["error"] += 1
        for i in range(1000):  # inputs by subscription: no reply, every one validated
            key = p.key("arm", "in", "set" if i % 2 else "motion")
            session.put(key, fuzz_payload(rng, None, i))
    finally:
        session.close()
    assert server.alive()
    assert counts["error"] > 2000 and {"bad_request", "unknown_call"} <= kinds, (counts, kinds)
    brain.stop()
    before = brain.status()["tick"]
    assert brain.tick(3) == before + 3


def fuzz_payload(rng: np.random.Generator, valid_call: str | None, i: int) -> bytes:
    """Random bytes, random JSON, or a command with broken arguments (oversized now and then)."""
    pool = [-1, 0, 1, 2**63, 1e308, float("nan"), 1.5, "1", "", None, [], {}, True, [1, "a"], {"a": {"b": []}},
            "x" * 300, "core.*", "servo.target", [0.1, 0.2, 0.3]]
    kind = i % 6
    if kind == 0:
        return rng.bytes(int(rng.integers(0, 300)))
    if kind == 1:
        return json.dumps(pool[int(rng.integers(len(pool)))]).encode()
    if kind == 5 and i % 300 == 5:
        return b'{"args": {"name": "' + b"x" * (p.MAX_COMMAND_BYTES + 10) + b'"}}'
    args: dict = {}
    model = p.CALLS.get(valid_call or "", None)
    fields = list(model.model_fields) if model is not None else ["n", "name", "objects", "view", "value"]
    for name in fields:
        if rng.random() < 0.7:
            args[name] = pool[int(rng.integers(len(pool)))]
    if rng.random() < 0.3:
        args["unexpected"] = 1
    envelope = {"v": int(rng.integers(0, 3)), "brain": pool[int(rng.integers(len(pool)))], "args": args}
    if kind == 4:
        envelope = {"args": args} if valid_call else envelope
    return json.dumps(envelope).encode()


def test_restarted_server_is_detected_and_a_frozen_one_times_out():
    first = ServerProcess(ARM, "--lease", "1s").start()
    endpoint = first.endpoint
    brain = BrainClient("arm", settings=Settings(connect=[endpoint], lease_ms=1000), timeout=0.5)
    second = None
    try:
        brain.tick(10)
        first.freeze()  # a frozen peer: no answer; it counts as gone when its 1 s lease runs out
        with pytest.raises((CallTimeoutError, NoWorldError)):
            brain.tick()
        wait_for(lambda: not brain.world_alive(timeout=0.3), what="the frozen world's token to go")
        with pytest.raises(NoWorldError, match="no world answered tick"):
            brain.tick()
        first.kill()
        second = ServerProcess(ARM, listen=endpoint).start()
        wait_for(lambda: brain.world_alive(timeout=0.3), timeout=15, what="the new server's token")
        with pytest.raises(WorldRestartedError, match="restarted"):
            brain.tick()
        brain.reattach()
        assert brain.tick() == 1  # a new world: nothing of the old run was half-applied
    finally:
        first.kill()
        brain.close()
        if second is not None:
            second.stop()


def test_the_documented_client_without_dynabrain_works(server):
    """PROTOCOL.md's raw-Zenoh client (what a client in another language does) against a served world."""
    with open(os.path.join(ROOT, "bridge", "PROTOCOL.md"), encoding="utf-8") as fh:
        code = fh.read().split("```python\n")[-1].split("```")[0]
    code = code.replace("tcp/127.0.0.1:7447", server.endpoint)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    tick, rest = run.stdout.split(" ", 1)
    assert int(tick) > 0 and "args.n: Input should be a valid integer" in rest


def test_two_brains_at_once_are_serialised(server):
    errors: list = []

    def run(name: str) -> None:
        try:
            with BrainClient("arm", connect=server.endpoint, brain=name) as b:
                view = b.view(["core.joint_q"])
                for _ in range(100):
                    b.tick(2, view=view)
        except Exception as exc:  # reported below
            errors.append(exc)

    with BrainClient("arm", connect=server.endpoint) as watcher:
        t0 = watcher.status()["tick"]
        threads = [threading.Thread(target=run, args=(f"b{i}",)) for i in range(3)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert not errors, errors
        assert watcher.status()["tick"] - t0 == 600
