"""Issue 24, item 5: a log given to ``replay --verify`` is trusted no further than it shows.

- verify states the dynabrain and MuJoCo versions that wrote the log, and refuses another major or
  minor version unless ``--allow-version-mismatch``;
- a recovered log whose middle chunk was lost reports the gap and verifies the ticks on both sides of it;
- a log with nothing of a run in it says what is missing.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.meta import versions
from dynabrain.orchestrator.logs.recover import recover
from dynabrain.orchestrator.logs.scan import Channel, LogError, Message, Metadata, Schema, scan
from dynabrain.orchestrator.logs.schema import BusCodec
from dynabrain.orchestrator.logs.verify import verify
from dynabrain.orchestrator.logs.write import McapWriter
from dynabrain.orchestrator.scenario.model import load_scenario

ROOT = Path(__file__).resolve().parents[1]
DT = 2_000_000
TICKS = 600
runner = CliRunner()


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    """two_cubes, 600 ticks, in chunks of about 32 kB (a dozen or so)."""
    path = tmp_path_factory.mktemp("logs") / "run.mcap"
    sc = load_scenario(ROOT / "scenarios" / "two_cubes.yaml")
    world = sc.build()
    McapLogger(path, window=0, chunk_bytes=32_000).attach(world, sc)
    world.tick(TICKS)
    world.close()
    return path


def with_versions(src: Path, dst: Path, bump_tick: int | None = None, **changed: str) -> Path:
    """A copy of the log whose recorded versions say ``changed`` (``dynabrain="0.9.0"``), and whose
    ``core.bb.pos`` x at ``bump_tick`` is 1e-9 more."""
    writer = McapWriter(dst, library="dynabrain", chunk_bytes=32_000)
    codecs: dict[int, BusCodec] = {}
    for rec in scan(src):
        if isinstance(rec, Metadata):
            values = dict(rec.values)
            if rec.name == "dynabrain":
                values["versions"] = json.dumps({**json.loads(values["versions"]), **changed})
            writer.add_metadata(rec.name, values)
        elif isinstance(rec, Schema):
            writer.add_schema(rec.name, rec.encoding, rec.data, schema_id=rec.id)
        elif isinstance(rec, Channel):
            writer.add_channel(rec.topic, rec.encoding, rec.schema_id, rec.metadata, channel_id=rec.id)
            if "layout" in rec.metadata:
                codecs[rec.id] = BusCodec.from_metadata(rec.metadata)
        elif isinstance(rec, Message):
            data, codec = rec.data, codecs.get(rec.channel_id)
            if codec is not None and bump_tick is not None and rec.publish_time == bump_tick * DT:
                rows, ticks, epochs = codec.decode(np.frombuffer(data, dtype=np.uint8))
                rows[0, codec.by_name["core.bb.pos"].offset] += 1e-9
                data = codec.encode(rows, ticks, epochs, DT)[0].tobytes()
            writer.add_message(rec.channel_id, rec.log_time, data, rec.sequence, rec.publish_time)
    writer.finish()
    return dst


def other_minor(version: str) -> str:
    major, minor, *_ = version.split(".")
    return f"{major}.{int(minor) + 1}.0"


@pytest.mark.parametrize("package", ["dynabrain", "mujoco"])
def test_a_log_of_another_minor_version_is_refused_unless_asked(log, tmp_path, package):
    here = versions()[package]
    other = with_versions(log, tmp_path / "other.mcap", **{package: other_minor(here)})
    with pytest.raises(LogError, match=rf"{package} {other_minor(here)} wrote it, {here} is installed.*"
                                       r"--allow-version-mismatch"):
        verify(other)
    refused = runner.invoke(app, ["replay", str(other), "--verify"])
    assert refused.exit_code == 2 and "--allow-version-mismatch" in " ".join(refused.output.split())
    result = verify(other, allow_version_mismatch=True)
    assert result.ok and f"{package} {other_minor(here)} (here {here})" in result.versions
    assert "despite the version mismatch" in result.versions
    done = runner.invoke(app, ["replay", str(other), "--verify", "--allow-version-mismatch"])
    assert done.exit_code == 0 and "verify: identical" in done.output, done.output
    assert f"{package} {other_minor(here)} (here {here})" in " ".join(done.output.split())


def test_verify_states_the_recorded_versions(log):
    done = runner.invoke(app, ["replay", str(log), "--verify"])
    assert done.exit_code == 0, done.output
    text = " ".join(done.output.split())
    assert f"recorded with dynabrain {versions()['dynabrain']}, mujoco {versions()['mujoco']}" in text


def middle_chunk(path: Path) -> int:
    """The offset of the log's middle chunk."""
    with open(path, "rb") as fh:
        offsets = sorted(i.chunk_start_offset for i in make_reader(fh).get_summary().chunk_indexes)
    assert len(offsets) >= 5
    return offsets[len(offsets) // 2]


def damaged_and_recovered(src: Path, tmp_path: Path) -> tuple[str, set[int]]:
    """``src`` with its middle chunk damaged, recovered; and the ticks lost (one run of them)."""
    data = bytearray(src.read_bytes())
    data[middle_chunk(src) + 200] ^= 0xFF  # inside the chunk's compressed data: its CRC fails
    (tmp_path / "bad.mcap").write_bytes(data)
    out, report = recover(tmp_path / "bad.mcap")
    with open(out, "rb") as fh:
        kept = {m.publish_time // DT for _s, _c, m in make_reader(fh).iter_messages(topics=["/bus"])}
    lost = set(range(TICKS + 1)) - kept
    assert not report.complete and report.run_ticks == len(kept) and lost == set(range(min(lost), max(lost) + 1))
    assert min(lost) > 0 and max(lost) < TICKS
    return out, lost


def test_a_recovered_gap_is_reported_and_both_sides_are_verified(log, tmp_path):
    out, lost = damaged_and_recovered(log, tmp_path)
    result = verify(out)
    assert result.ok, result.divergence
    assert result.gaps == ((min(lost), max(lost)),)
    assert result.rows == TICKS + 1 - len(lost) and result.last_tick == TICKS  # compared before and after the gap
    done = runner.invoke(app, ["replay", out, "--verify"])
    assert done.exit_code == 0, done.output
    assert f"gap: the recording lacks ticks {min(lost)}..{max(lost)}" in " ".join(done.output.split())


def test_a_recovered_gap_hides_no_divergence_after_it(log, tmp_path):
    """The ticks after a gap are compared: a value changed there is found."""
    _out, lost = damaged_and_recovered(log, tmp_path)
    later = max(lost) + 20
    changed = with_versions(log, tmp_path / "changed.mcap", bump_tick=later)
    out, lost_too = damaged_and_recovered(changed, tmp_path)
    assert later not in lost_too
    result = verify(out)
    assert not result.ok and result.divergence.tick == later and result.gaps


@pytest.mark.parametrize("cut", [20, 60])
def test_an_empty_recovered_log_says_what_is_missing(log, tmp_path, cut):
    (tmp_path / "cut.mcap").write_bytes(log.read_bytes()[:cut])
    out, _report = recover(tmp_path / "cut.mcap")
    with pytest.raises(LogError) as caught:
        verify(out)
    message = str(caught.value)
    assert "`dynabrain` metadata record" in message and "is not a dynabrain recording" not in message


def test_a_log_that_is_a_fifo_is_refused_unopened(tmp_path):
    os.mkfifo(tmp_path / "run.mcap")  # opening it would wait for a writer forever
    done = runner.invoke(app, ["replay", str(tmp_path / "run.mcap"), "--verify"])
    assert done.exit_code == 2 and "not a regular file" in done.output, done.output
