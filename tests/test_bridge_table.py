"""The bridge's one table of calls (`protocol.TABLE`): the server and the world service answer exactly
its calls (checked once per class), `PROTOCOL.md` lists them as the table says, and a client checks
each command against it before sending (a real Zenoh session on loopback sees nothing of a refused one)."""

from __future__ import annotations

import json
import os
import threading

import pytest

from dynabrain.bridge import BadRequestError, BrainClient
from dynabrain.bridge import protocol as p
from dynabrain.bridge.calls import WorldService
from dynabrain.bridge.schema import DOC_PATH, render_doc
from dynabrain.bridge.server import BridgeServer
from dynabrain.bridge.zenoh_io import JSON, Settings, open_session, payload_bytes
from dynabrain.orchestrator.scenario import load_world

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, "bridge", "arm.yaml")


def test_every_call_has_one_handler_on_its_side_of_the_table():
    world_side = {name for name, call in p.TABLE.items() if not call.server}
    server_side = set(p.TABLE) - world_side
    world = load_world(ARM)
    try:
        assert set(WorldService(world, instance=1)._handlers) == world_side
        assert set(BridgeServer(world)._handlers) == server_side  # not opened: no session
    finally:
        world.close()
    assert {name: call.model for name, call in p.TABLE.items()} == p.CALLS
    assert {"status", "get", "read", "view", "drop_view", "robot_status"} == p.READ_ONLY
    assert {"add_module", "add_body", "remove_body", "fork", "close", "batch"} == p.SLOW


class _Extra(WorldService):
    def do_teleport(self, a: p.NoArgs) -> None:
        """A handler the table does not know."""


class _Missing(WorldService):
    do_make = None  # the table's `make` has no handler here


class _Twice(WorldService):
    def do_acquire(self, a: p.AcquireArgs) -> None:
        """A server call answered by the world too."""


@pytest.mark.parametrize(("cls", "message"), [
    (_Extra, "do_<call> for what is no world call: teleport"),
    (_Missing, "no do_<call> for make"),
    (_Twice, "do_<call> for what is no world call: acquire"),
])
def test_a_service_that_does_not_match_the_table_is_refused(cls, message):
    world = load_world(ARM)
    try:
        with pytest.raises(TypeError, match=message):
            cls(world, instance=1)
    finally:
        world.close()


def test_the_protocol_document_lists_the_calls_of_the_table():
    with open(DOC_PATH, encoding="utf-8") as fh:
        text = fh.read()
    assert text == render_doc(text), "the table of calls in bridge/PROTOCOL.md is stale: " \
                                     "run python -m dynabrain.bridge.schema"
    for name in p.TABLE:
        assert f"| `{name}` |" in text


def test_the_client_refuses_a_bad_command_before_sending_it():
    """A queryable of our own stands where a world would be and records every command that arrives."""
    session, endpoints = open_session(Settings(listen=["tcp/127.0.0.1:0"]))
    arrived: list[tuple[str, dict]] = []
    lock = threading.Lock()

    def on_query(query) -> None:
        with lock:
            arrived.append((str(query.key_expr).rsplit("/", 1)[-1], json.loads(payload_bytes(query.payload))))
        query.reply(query.key_expr, p.encode({"tick": 7, "instance": 5, "result": None}), encoding=JSON)

    queryable = session.declare_queryable(p.key("probe", "call", "*"), on_query, complete=True)
    alive = session.liveliness().declare_token(p.key("probe", "alive"))
    try:
        with BrainClient("probe", connect=endpoints[0], timeout=5) as brain:
            with pytest.raises(BadRequestError, match=r"unknown call 'tikc' \(did you mean 'tick'\?\).*nothing sent"):
                brain.call("tikc")
            with pytest.raises(BadRequestError, match=r"args\.n: Input should be a valid integer"):
                brain.call("tick", n="3")
            with pytest.raises(BadRequestError, match="Extra inputs are not permitted"):
                brain.call("make", objects=["cube"], colour="red")
            with pytest.raises(BadRequestError, match=r"args\.pos: List should have at least 3 items"):
                brain.place("cube", [0.0, 1.0])
            assert arrived == []
            assert brain.tick(3) == 7
            brain.set("servo.target", [0.1, 0.2, 0.3])
        with lock:
            assert [(call, body["args"]) for call, body in arrived] == [
                ("tick", {"n": 3}), ("set", {"name": "servo.target", "value": [0.1, 0.2, 0.3]})]
    finally:
        alive.undeclare()
        queryable.undeclare()
        session.close()
