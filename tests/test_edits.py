"""Edits as typed records (`kernel.edits`): what the world tells is a record, each record crosses as
plain values and back, and applying the told records to a twin world makes the same world, bit for bit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dynabrain.modules.basic import Gain
from dynabrain.orchestrator import load_world
from dynabrain.orchestrator.kernel import edits
from dynabrain.orchestrator.kernel.observers import Observer


class Told(Observer):
    def __init__(self):
        self.events = []

    def on_event(self, view, event):
        self.events.append(event)


def _edit_everything(world) -> None:
    world.add_body(name="box1", shape="box", size=["50mm"] * 3, mass="50g", pos=[0.3, 0, "0.2m"], color="blue")
    world.set_material("box1", friction=0.4, restitution=0.2)
    world.place("box1", [0.3, 0.1, 0.2])
    world.make_joint("aa", "box1", "hold", kind="hinge", axis=[0, 1, 0])
    world.no_collision(["aa", "box1"])
    world.make(["aa", "box1", "floor"], others="absent")
    world.set("core.friction", 0.7)
    world.add_module(Gain("g", k=2.0, n=3, unit="m"), connect=[["core.aa.pos", "g.u"]])
    world.disconnect("g.u")
    world.connect("core.aa.pos", "g.u")
    world.remove_joint("hold")
    world.remove_module("g")
    world.remove_body("box1")


def test_what_the_world_tells_is_a_record_that_crosses_as_json_and_back():
    world = load_world("two_cubes")
    told = Told()
    world.observe(told)
    _edit_everything(world)
    kinds = [e.kind for e in told.events if e.edit is not None]
    assert {"body_added", "material", "place", "make_joint", "no_collision", "make", "param", "module_added",
            "connect", "disconnect", "remove_joint", "module_removed", "body_removed"} <= set(kinds)
    for event in told.events:
        if event.edit is None:
            continue
        assert event.edit.kind == event.kind and event.edit.detail() == event.detail
        again = edits.edit_of(event.kind, json.loads(json.dumps(event.detail)))  # as a log holds it
        assert type(again) is type(event.edit) and again.detail() == event.detail
    world.close()


def test_the_told_records_applied_to_a_twin_make_the_same_world():
    world, twin = load_world("two_cubes"), load_world("two_cubes")
    told = Told()
    world.observe(told)
    world.tick(5)
    twin.tick(5)
    _edit_everything(world)
    for event in told.events:
        if event.edit is not None:
            edits.edit_of(event.kind, json.loads(json.dumps(event.detail))).apply(twin)
    world.tick(20)
    twin.tick(20)
    assert world.signals == twin.signals
    assert np.array_equal(world.bus.view(np.int64), twin.bus.view(np.int64))
    world.close()
    twin.close()


def test_a_damaged_or_unknown_record_is_refused_naming_what_is_wrong():
    with pytest.raises(edits.EditFormatError, match="lacks src, dst"):
        edits.edit_of("connect", {})
    with pytest.raises(edits.EditFormatError, match="'explode' is no edit"):
        edits.edit_of("explode", {})
    with pytest.raises(edits.EditFormatError, match="its spec"):
        edits.edit_of("body_added", {"body": "x", "spec": {"name": "x", "shape": "box", "__reduce__": "os.system"}})
    assert edits.edit_of("make", {"objects": ["aa"]}) == edits.Make(("aa",), "frozen")  # an old log's make
