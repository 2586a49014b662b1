"""A peer cannot leave a served world unable to tick (issue 17, point 8), for real: `dynabrain serve` in
another process, brains and raw Zenoh sessions on loopback.

- non-finite numbers are refused in every number field;
- a long ``tick`` lets ``status`` and ``stop`` through between its slices; ``stop`` ends it early and its
  caller is told how many ticks ran; other brains' edits still wait for it;
- a hold whose brain has no liveliness token lasts a short lease, renewed by the brain's calls.
"""

from __future__ import annotations

import json
import os
import threading
import time

import pytest

from dynabrain.bridge import BadRequestError, BrainClient, TickStoppedError, WorldBusyError
from dynabrain.bridge import protocol as p
from dynabrain.bridge.testing import ServerProcess
from dynabrain.bridge.zenoh_io import Settings, open_session

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, "bridge", "arm.yaml")
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


def wait_for(predicate, timeout: float = 5.0, what: str = "condition"):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


# -- values -----------------------------------------------------------------------------------------------------
def test_non_finite_numbers_are_refused_in_number_fields(raw, brain):
    for call, args in (("set", '{"name": "core.friction", "value": 1e999}'),
                       ("place", '{"body": "cube", "pos": [Infinity, 0, 0.1]}'),
                       ("start", '{"until": 1e300}'), ("acquire", '{"lease": NaN}')):
        ok, body = ask(raw, call, '{"v": 1, "brain": "raw", "args": ' + args + "}")
        assert not ok and body["error"] == "bad_request", (call, args, body)
    with pytest.raises(BadRequestError, match="lease"):
        brain.acquire(lease=float("inf"))  # the client checks as the server does: nothing sent
    assert brain.status()["server"]["holder"] is None


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
