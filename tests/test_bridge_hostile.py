"""A peer cannot leave a served world unable to tick (issue 17, point 8), for real: `dynabrain serve` in
another process, brains and raw Zenoh sessions on loopback.

- values beyond the scenario's limits (a gravity of 1e308, NaN, a huge input) are refused with the reason,
  by ``set``, ``in/set``, ``place`` and ``batch`` alike, and the world ticks on; a parameter change with
  which the next tick diverges is refused too;
- a long ``tick`` lets ``status`` and ``stop`` through between its slices; ``stop`` ends it early and its
  caller is told how many ticks ran; other brains' edits still wait for it;
- a hold whose brain has no liveliness token lasts a short lease, renewed by the brain's calls.
"""

from __future__ import annotations

import json
import os
import re
import threading
import time

import numpy as np
import pytest

from dynabrain.bridge import BadRequestError, BrainClient, TickStoppedError, WorldBusyError, WorldRefusedError
from dynabrain.bridge import protocol as p
from dynabrain.bridge.testing import ServerProcess, wait_for
from dynabrain.bridge.zenoh_io import Settings, open_session

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, "bridge", "arm.yaml")
GRAVITY = [0.0, 0.0, -9.81]
LIVELY = 5.0
"""Seconds within which a call that must not wait for a long tick answers (the tick would take 10 s or more)."""


@pytest.fixture(scope="module")
def server():
    with ServerProcess(ARM, "--lease", "1s", "--tokenless-lease", "1s") as srv:
        yield srv
    assert "Traceback" not in srv.output, srv.output


@pytest.fixture()
def brain(server):
    with BrainClient("arm", connect=server.endpoint, timeout=20) as b:
        yield b


@pytest.fixture()
def raw(server):
    """A Zenoh session that speaks the protocol by hand and declares no liveliness token."""
    session, _ = open_session(Settings(connect=[server.endpoint]))
    yield session
    session.close()


def ask(session, call: str, payload: bytes | str, timeout: float = 10.0) -> tuple[bool, dict]:
    """(ok, body) of one call made by hand."""
    replies = list(session.get(p.call_key("arm", call), payload=payload, timeout=timeout))
    assert replies, f"no reply to {call}"
    reply = replies[0]
    if reply.ok is not None:
        return True, json.loads(reply.ok.payload.to_bytes())
    return False, json.loads(reply.err.payload.to_bytes())




# -- values -----------------------------------------------------------------------------------------------------
def test_a_gravity_of_1e308_is_refused_and_the_world_ticks_on(brain):
    tick = brain.status()["tick"]
    with pytest.raises(WorldRefusedError, match=r"core\.gravity = \[1e\+308, .*refused: .*at most 1000") as err:
        brain.set("core.gravity", [1e308, 1e308, 1e308])
    assert err.value.kind == "refused"
    for bad, why in (([float("nan"), 0.0, -9.81], "finite"), ([0.0, 0.0, -5000.0], "at least -1000")):
        with pytest.raises(WorldRefusedError, match=why):
            brain.set("core.gravity", bad)  # NaN goes as null: the server sees NaN
    with pytest.raises(WorldRefusedError, match="at most 1, got 2"):
        brain.set("core.restitution", 2.0)
    with pytest.raises(WorldRefusedError, match=r"servo\.target = \[1e\+300, 0\.0, 0\.0\] refused: .*within ±1e\+15"):
        brain.set("servo.target", [1e300, 0, 0])
    with pytest.raises(WorldRefusedError, match="finite number"):
        brain.set("servo.target", [float("nan"), 0, 0])
    with pytest.raises(WorldRefusedError, match=r"place 'cube' refused: .*1e\+300"):
        brain.place("cube", [1e300, 0.0, 0.1])
    assert np.array_equal(brain.get("core.gravity"), GRAVITY)
    assert brain.tick(20) == tick + 20 and np.isfinite(brain.get("cube.pos")).all()


def test_non_finite_numbers_are_refused_in_any_field(raw, brain):
    for call, args, kind, why in (
            ("set", '{"name": "core.friction", "value": 1e999}', "bad_request", "finite number"),
            ("set", '{"name": "core.gravity", "value": [NaN, 0, -9.81]}', "refused", "finite"),
            ("set", '{"name": "cube.velocity", "value": [Infinity, 0, 0, 0, 0, 0]}', "refused", "finite"),
            ("place", '{"body": "cube", "pos": [Infinity, 0, 0.1]}', "bad_request", "finite number"),
            ("start", '{"until": 1e300}', "bad_request", "less than or equal to"),
            ("acquire", '{"lease": NaN}', "bad_request", "finite number"),
            ("batch", '{"ticks": 5, "branches": 2, "params": {"core.friction": [0.5, NaN]}}', "refused", "finite"),
            ("batch", '{"ticks": 5, "branches": 2, "params": {"core.gravity": [[0, 0, -9.81], [0, 0, 1e308]]}}',
             "refused", r"within \[-1000, 1000\]"),
            ("batch", '{"ticks": 2, "branches": 1, "inputs": {"servo.target": [[1e300, 0, 0], [0, 0, 0]]}}',
             "refused", r"within ±1e\+15"),
            ("batch", '{"ticks": 2, "branches": 1, "inputs": {"servo.target": [[NaN, 0, 0], [0, 0, 0]]}}',
             "refused", "not all finite")):
        ok, body = ask(raw, call, '{"v": 1, "brain": "raw", "args": ' + args + "}")
        assert not ok and body["error"] == kind, (call, args, body)
        assert re.search(why, body["message"]), (call, args, body["message"])
    with pytest.raises(BadRequestError, match="lease"):
        brain.acquire(lease=float("inf"))  # the client checks as the server does: nothing sent
    assert brain.status()["server"]["holder"] is None
    assert np.array_equal(brain.get("core.gravity"), GRAVITY)


def test_inputs_get_the_same_checks(brain):
    events: list = []
    brain.subscribe_events(events.append)
    time.sleep(0.2)
    brain.set_inputs({"core.gravity": [1e308, 1e308, 1e308], "servo.target": [0.1, 0.0, 0.0]})
    wait_for(lambda: brain.tick() and any(e["kind"] == "input_error" and "core.gravity" in e["detail"]["message"]
                                          for e in events), what="the input error event")
    message = next(e["detail"]["message"] for e in events if e["kind"] == "input_error")
    assert "at most 1000" in message, message
    assert np.array_equal(brain.get("core.gravity"), GRAVITY) and brain.get("servo.target")[0] == 0.1
    brain.set("servo.target", [0.0, 0.0, 0.0])


def test_nan_is_taken_where_it_means_unset(brain):
    """A body's velocity input starts NaN ("leave the motion alone"): a brain writes NaN back to let go."""
    brain.set("cube.velocity", [0.2, 0.0, 0.0, float("nan"), float("nan"), float("nan")])
    brain.tick(5)
    assert brain.get("cube.linvel")[0] == pytest.approx(0.2, abs=0.02)
    brain.set("cube.velocity", [float("nan")] * 6)
    assert np.isnan(brain.get("cube.velocity")).all()
    with pytest.raises(BadRequestError, match="infinite value"):
        brain.set("cube.velocity", [float("inf")] + [0.0] * 5)  # JSON has no infinity: the client refuses it
    brain.tick(5)


def test_a_parameter_change_that_makes_the_next_tick_diverge_is_refused(brain):
    brain.set("servo.target", [1.0, 1.0, 1.0])
    brain.set("servo.kp", 1e14)  # harmless while the force saturates at max_force
    try:
        tick = brain.tick()
        with pytest.raises(WorldRefusedError, match=r"servo\.max_force = 100000000000000\.0 refused: with it the next "
                                                    r"tick fails \(module 'core'.*became NaN, infinite or larger"):
            brain.set("servo.max_force", 1e14)
        assert brain.get("servo.max_force") == 40.0
        assert brain.tick(10) == tick + 10  # the world was not touched
    finally:
        brain.set("servo.kp", 60.0)
        brain.set("servo.target", [0.0, 0.0, 0.0])


# -- long ticks -------------------------------------------------------------------------------------------------
def test_a_long_tick_lets_status_and_stop_through_and_says_it_was_stopped(server, brain):
    outcome: dict = {}

    def long_tick() -> None:
        with BrainClient("arm", connect=server.endpoint, brain="ticker") as ticker:
            try:
                ticker.tick(1_000_000, timeout=120)  # at least 10 s of ticks
                outcome["done"] = ticker.last_tick
            except Exception as exc:  # checked below
                outcome["error"] = exc

    start = brain.status()["tick"]
    thread = threading.Thread(target=long_tick)
    thread.start()
    try:
        running = wait_for(lambda: brain.call("status", LIVELY)["server"]["running"], timeout=30,
                           what="the long tick to start")
        assert running["brain"] == "ticker" and running["ticks_asked"] == 1_000_000
        time.sleep(0.3)
        status = brain.call("status", LIVELY)  # answered between two slices, within the timeout
        assert 0 < status["server"]["running"]["ticks_done"] < 1_000_000
        assert status["tick"] > start
        assert brain.call("get", LIVELY, name="core.joint_q") is not None

        queued: dict = {}
        other = threading.Thread(target=lambda: queued.setdefault("tick", brain.tick(timeout=60)))
        other.start()  # an edit from another brain waits for the long tick: never interleaved with it
        time.sleep(0.2)
        assert "tick" not in queued

        with BrainClient("arm", connect=server.endpoint, brain="stopper") as stopper:
            reply = stopper.call("stop", LIVELY)
        assert reply["stopped"]["brain"] == "ticker" and 0 < reply["stopped"]["ticks_done"] < 1_000_000
        thread.join(timeout=LIVELY)
        assert not thread.is_alive(), "the stopped tick did not answer"
        other.join(timeout=LIVELY)
    finally:
        thread.join(timeout=120)
    err = outcome.get("error")
    assert isinstance(err, TickStoppedError), outcome
    assert err.kind == "stopped" and "tick stopped by brain 'stopper'" in str(err)
    assert err.ticks_asked == 1_000_000 and reply["stopped"]["ticks_done"] <= err.ticks_done < 1_000_000
    assert err.tick == start + err.ticks_done  # the ticks done stay
    assert queued["tick"] == err.tick + 1  # the other brain's tick ran after it
    assert brain.status()["server"]["running"] is None
    assert brain.stop()["stopped"] is None  # nothing runs now


# -- holds ------------------------------------------------------------------------------------------------------
def test_a_tokenless_hold_lasts_a_short_lease_renewed_by_its_calls(raw, brain):
    def command(**args) -> str:
        return json.dumps({"v": 1, "brain": "tokenless", "args": args})

    ok, body = ask(raw, "acquire", command(lease=3600))
    assert ok and body["result"]["holder"] == "tokenless" and body["result"]["lease"] == 1.0
    assert "no liveliness token" in body["result"]["note"]
    end = time.monotonic() + 2.5  # more than twice the lease: kept by calls
    while time.monotonic() < end:
        ok, body = ask(raw, "tick", command())
        assert ok, body
        with pytest.raises(WorldBusyError, match="tokenless"):
            brain.tick()
        time.sleep(0.25)
    # the brain goes silent (dead, or a frozen process): the hold ends after its short lease
    wait_for(lambda: brain.status()["server"]["holder"] is None, timeout=LIVELY, what="the tokenless hold to end")
    brain.tick()


def test_a_brain_with_a_token_gets_the_lease_it_asks_for(brain):
    wait_for(lambda: brain.brain in brain.status()["server"]["brains"], what="the brain's token")
    try:
        assert brain.acquire(lease=3600) == {"holder": brain.brain, "lease": 3600.0}
    finally:
        brain.release()
