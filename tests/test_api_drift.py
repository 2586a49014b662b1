"""One definition of the brain's API (issue 27, item 3): the bridge's table of calls (`protocol.TABLE`) is
checked against `World` and `BrainClient`, so that a call added to one and not the others fails here.

- every public member of `World` is either a call of the table or listed below with the reason it does not
  cross the bridge;
- every call of the table that the world answers is a `World` member of the same name (or listed as the
  bridge's own), and a `BrainClient` method of that name takes the call's fields (as keywords, or through
  ``**fields`` where the call takes a free set), plus only the client's own ``timeout``;
- a keyword the World method takes is a field of the call (nothing of the world is silently unreachable)."""

from __future__ import annotations

import inspect

from dynabrain.bridge import protocol as p
from dynabrain.bridge.client import BrainClient
from dynabrain.orchestrator import World

NOT_OVER_THE_BRIDGE = {
    # read-only views of the structure: `status` carries them
    "connections": "status", "modules": "status", "signals": "status", "schedule_order": "status",
    "core": "status", "history": "status", "running": "status", "tick_count": "status", "time": "status",
    "time_ns": "status", "scheduled_ticks": "status",
    # in-process only: objects, callables or threads that cannot cross a network
    "at": "takes a Python callable", "observe": "takes a Python observer (remote: subscribe_events)",
    "unobserve": "takes a Python observer", "lock": "a lock of this process", "wait": "waits on this process's thread",
    "run": "per-tick inputs in one call: a remote brain ticks with set_inputs, or runs futures with batch",
    "imagine": "keeps a future in this process's log",
    # states cross as snapshots the server keeps (snapshot, restore, batch starts), not as bytes
    "export_state": "snapshot", "import_state": "restore", "check_state": "restore",
    # name resolution a client does through get and the errors of set
    "settable": "set", "signal_shape": "get", "material_target": "set_material", "ticks_of": "tick",
    # strong coupling: a loop is declared by the scenario (`iterate:`); the bridge cannot declare one yet
    "iterate": "the scenario's iterate:", "loops": "status", "loop_report": "status",
    # the kernel's read-only views for tools in this process (arrays, structures, callables)
    "bus": "get", "structure": "status", "compiled": "in-process", "observers": "subscribe_events",
    "parts": "in-process", "error": "the failed call's error", "module_factory": "in-process", "rebuild": "in-process",
}
BRIDGE_ONLY = {"acquire", "release", "view", "read", "drop_view", "drop_snapshot", "batch", "motion", "robot_enable",
               "robot_stop", "robot_status"}
"""Calls of the table that are the bridge's own (leases, views, robots, the server's batch), not World's."""
FREE_FIELDS = {"add_body": "fields", "set_material": "coefficients", "add_module": "fields"}
"""Calls whose client method takes the fields as ``**kwargs`` (a body's or a module's spec)."""
WIRE_ONLY = {"motion": {"sent_ns", "seq"}}
"""Fields the client fills in itself."""


def _public(cls: type) -> set[str]:
    return {n for n in vars(cls) if not n.startswith("_")}


def test_every_world_member_crosses_the_bridge_or_says_why_not():
    world = _public(World)
    unlisted = world - set(p.TABLE) - set(NOT_OVER_THE_BRIDGE)
    assert not unlisted, f"World members neither in the bridge's table nor in NOT_OVER_THE_BRIDGE: {sorted(unlisted)}"
    stale = set(NOT_OVER_THE_BRIDGE) - world
    assert not stale, f"NOT_OVER_THE_BRIDGE names what World no longer has: {sorted(stale)}"
    for name in set(p.TABLE) - BRIDGE_ONLY:
        assert name in world, f"the bridge's call {name!r} has no World member of that name"


def test_every_call_has_a_client_method_that_takes_its_fields():
    for name, call in p.TABLE.items():
        method = getattr(BrainClient, name, None)
        assert method is not None, f"BrainClient has no method for the call {name!r}"
        params = inspect.signature(method).parameters
        takes = {q for q in params if q != "self"} - {"timeout"}
        fields = set(call.model.model_fields) - WIRE_ONLY.get(name, set()) if call.model else set()
        if name in FREE_FIELDS:
            assert params[FREE_FIELDS[name]].kind is inspect.Parameter.VAR_KEYWORD, name
            continue
        if name == "add_module":
            continue
        assert takes == fields, f"BrainClient.{name} takes {sorted(takes)}; the call's fields are {sorted(fields)}"


def test_a_world_keyword_is_a_field_of_its_call():
    for name, call in p.TABLE.items():
        if name in BRIDGE_ONLY or call.model is None or not callable(getattr(World, name, None)):
            continue
        world_kw = {q.name for q in inspect.signature(getattr(World, name)).parameters.values()
                    if q.name != "self" and q.kind in (q.KEYWORD_ONLY, q.POSITIONAL_OR_KEYWORD)}
        fields = set(call.model.model_fields)
        alias = {"add_body": {"spec"}, "add_module": {"module", "period", "connect"}, "restore": {"state", "snapshot"}}
        missing = world_kw - fields - alias.get(name, set())
        assert not missing, f"World.{name} takes {sorted(missing)}, which the bridge's call {name!r} cannot carry"
