"""Strict protobuf readers decode every channel of a log (issue 29): the schemas are checked the way the
official ``mcap`` CLI's reader (Go's protodesc) checks them, every message of every channel is decoded
with protobuf's own descriptor pool and message classes, and turned into JSON with the fields' JSON names,
as ``mcap cat --json`` does. The log holds a layout change (``/bus/layout2``), a rollback beyond the
window (``/discarded/...``), imagined futures (``/imagined/...``, with poses and a second layout) and the
run's results; the bus schema of every shipped scenario is checked too. Where an ``mcap`` CLI is on PATH
(built from foxglove/mcap; none in CI), its ``cat --json`` reads the same log."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, json_format, message_factory
from google.protobuf.unknown_fields import UnknownFieldSet
from mcap.reader import make_reader

from dynabrain.modules.basic import Sine
from dynabrain.orchestrator.kernel.observers import WorldView
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.schema import BusCodec, FieldNumbers, Slot
from dynabrain.orchestrator.scenario.model import load_scenario

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "scenarios"


def check_strict(fds: descriptor_pb2.FileDescriptorSet, what: str) -> None:
    """What Go's protodesc refuses and protobuf's Python pool lets through: a ``SourceCodeInfo`` location
    whose span is not 3 or 4 numbers (the error ``proto: invalid span: []`` of ``mcap cat --json``)."""
    for fd in fds.file:
        for loc in fd.source_code_info.location:
            assert len(loc.span) in (3, 4), f"{what}: {fd.name}: a SourceCodeInfo location {list(loc.path)} " \
                                            f"has the span {list(loc.span)}: strict readers refuse it"


def message_class(data: bytes, name: str, what: str) -> type:
    """The message class of a schema, from a pool of its own (as a reader builds it from the file)."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(data)
    check_strict(fds, what)
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)  # the pool checks names, numbers, types, JSON names and dependencies
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def strict_read(path: Path) -> dict[str, list[dict]]:
    """Every message of every channel, decoded strictly and as JSON: topic -> messages."""
    out: dict[str, list[dict]] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        classes = {sid: message_class(s.data, s.name, f"schema {s.name}") for sid, s in summary.schemas.items()}
        assert {s.encoding for s in summary.schemas.values()} == {"protobuf"}
        for schema, channel, message in reader.iter_messages():
            decoded = classes[schema.id].FromString(message.data)
            assert not len(UnknownFieldSet(decoded)), f"{channel.topic}: fields its schema does not name"
            out.setdefault(channel.topic, []).append(json_format.MessageToDict(decoded))
    return out


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """Two cubes with a module arriving, a rollback beyond the window, imagined futures and the results."""
    path = tmp_path_factory.mktemp("strict") / "run.mcap"
    sc = load_scenario(SCENARIOS / "two_cubes.yaml")
    world = sc.build()
    logger = McapLogger(path, window=4).attach(world, sc)
    world.tick(20)
    world.add_module(Sine("wave", frequency=2.0))
    world.tick(20)
    world.backtick(15)
    world.tick(5)
    start = world.tick_count
    ahead = np.linspace(0, 1, 10)[:, None]
    world.imagine("push", start, {"aa.pos": world.get("aa.pos") + ahead * [0, 0, 0.1],
                                  "aa.quat": np.tile(world.get("aa.quat"), (10, 1))})
    world.imagine("push", start, {"guess": ahead[:, 0]})  # other signals: a layout of its own
    world.tick(5)
    logger.log_result(SimpleNamespace(ticks=world.tick_count, sim_time=world.time, wall_time=0.1, error=None,
                                      ok=True, ended=None, expectations=[]))
    truth = {"ticks": world.tick_count, "aa.pos": world.get("aa.pos").tolist()}
    world.close()
    return path, truth


def test_every_channel_decodes_with_a_strict_reader(session):
    path, truth = session
    got = strict_read(path)
    assert {"/bus", "/bus/layout2", "/tf", "/scene", "/events", "/discarded/bus/layout2", "/discarded/tf",
            "/imagined/push/0/bus", "/imagined/push/0/bus/layout2", "/imagined/push/0/tf",
            "/imagined/push/0/scene"} <= set(got)
    last = got["/bus/layout2"][-1]  # the JSON names are the signals' own names (what mcap cat --json prints)
    assert int(last["tick"]) == truth["ticks"] and last["core.aa.pos"] == truth["aa.pos"] and "wave.y" in last
    assert [len(m) for m in (got["/imagined/push/0/bus"], got["/imagined/push/0/bus/layout2"])] == [10, 10]
    kinds = [json.loads(m["message"])["kind"] for m in got["/events"]]
    assert {"layout", "rollback", "imagined", "run_end"} <= set(kinds)


def test_bus_schemas_hold_no_source_info_and_the_units_are_in_the_channel_metadata(session):
    path, _truth = session
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    for schema in summary.schemas.values():
        fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
        assert not any(fd.HasField("source_code_info") for fd in fds.file), schema.name
    meta = next(c.metadata for c in summary.channels.values() if c.topic == "/bus")
    units = json.loads(meta["units"])
    assert units["core.aa.pos"] == "m" and units["core.aa.angvel"] == "rad/s"


def test_the_checker_refuses_a_location_without_a_span():
    """The rule the check applies is the one the old schemas broke (a comment with no span)."""
    fd = descriptor_pb2.FileDescriptorProto(name="x.proto", package="x", syntax="proto3")
    fd.message_type.add(name="Bus").field.add(name="a", number=1, type=1, label=1)
    fd.source_code_info.location.add(path=[4, 0, 2, 0]).leading_comments = " a: unit m"
    with pytest.raises(AssertionError, match=r"has the span \[\]: strict readers refuse it"):
        message_class(descriptor_pb2.FileDescriptorSet(file=[fd]).SerializeToString(), "x.Bus", "x")


@pytest.mark.parametrize("scenario", sorted(p.stem for p in SCENARIOS.glob("*.yaml")))
def test_every_shipped_scenarios_bus_schema_is_strict(scenario):
    """Each shipped scenario's bus: its schema builds in a strict pool, and a row encoded by the codec
    decodes through it to the same values under the signals' names."""
    world = load_scenario(SCENARIOS / f"{scenario}.yaml").build()
    try:
        view = WorldView(world)
        bus = view.bus().copy()
        codec = BusCodec.from_view(view.signal_slots(), bus.size, FieldNumbers(), 1)
    finally:
        world.close()
    cls = message_class(codec.descriptor(), codec.schema_name, scenario)
    decoded = cls.FromString(codec.encode(bus[None, :], [7], [0], 2_000_000)[0].tobytes())
    as_json = json_format.MessageToDict(decoded, always_print_fields_with_no_presence=True)
    assert int(as_json.pop("tick")) == 7 and set(as_json) - {"epoch", "time"} == set(codec.numbers)
    for f in codec.fields:
        want = bus[f.offset:f.offset + f.size]
        value = np.array(as_json[f.name], dtype=float).reshape(-1)
        assert np.array_equal(value, want, equal_nan=True), f"{scenario}: {f.name}"


def test_field_names_are_protobuf_identifiers():
    slots = [Slot("core.bé.pos", 0, (3,), "m"), Slot("m.2x", 3, (), ""), Slot("m-x.y", 4, (), "")]
    codec = BusCodec(slots, FieldNumbers(), 5)
    cls = message_class(codec.descriptor(), codec.schema_name, "odd names")
    names = [f.name for f in cls.DESCRIPTOR.fields]
    assert names[3:] == ["core__b___pos", "m__2x", "m_x__y"] and all(n.isascii() for n in names)
    assert not math.isnan(cls.FromString(codec.encode(np.ones((1, 5)), [1], [0], 1)[0].tobytes()).m__2x)


def _mcap_cli() -> str | None:
    found = shutil.which("mcap")
    if found is None:
        return None
    probe = subprocess.run([found, "cat", "--help"], capture_output=True, text=True, timeout=30)
    return found if "--json" in probe.stdout + probe.stderr else None


@pytest.mark.skipif(_mcap_cli() is None, reason="no mcap CLI on PATH (foxglove/mcap's Go or Rust CLI, built "
                                                "from its source; CI installs none): the strict check above stands in")
def test_the_mcap_cli_decodes_every_channel(session):
    path, _truth = session
    done = subprocess.run([_mcap_cli(), "cat", "--json", str(path)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    topics = {json.loads(line)["topic"] for line in done.stdout.splitlines()}
    assert {"/bus", "/bus/layout2", "/discarded/bus/layout2", "/imagined/push/0/bus", "/imagined/push/0/bus/layout2",
            "/events", "/tf", "/scene"} <= topics
