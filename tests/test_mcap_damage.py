"""Damaged logs lose at most the chunks the damage touches: logs are chunked by size and by simulated
time, every chunk declares its own channels, and `log recover` resynchronises on the next valid chunk
after a damaged record. Bytes are flipped in several places and files cut at several points; the ticks
kept are counted against the chunks that held them (read with the mcap package). `replay --verify` of a
log with no ticks fails with a clear message."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader, breakup_chunk
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.read import read_index
from dynabrain.orchestrator.logs.recover import recover
from dynabrain.orchestrator.logs.scan import LogError
from dynabrain.orchestrator.logs.verify import verify
from dynabrain.orchestrator.scenario.model import load_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"
DT = 2_000_000
TICKS = 4000


def run(path: Path, ticks: int = TICKS, **kw) -> Path:
    """two_cubes, as `dynabrain run` logs it (no window), much faster than real time."""
    sc = load_scenario(SCENARIOS / "two_cubes.yaml")
    world = sc.build()
    McapLogger(path, window=0, **kw).attach(world, sc)
    world.tick(ticks)
    world.close()
    return path


def chunks(path: Path) -> list[tuple[int, int, set[int]]]:
    """Each chunk's (offset, end of its message indexes, the /bus ticks it holds), in file order."""
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    bus = {c.id for c in summary.channels.values() if c.topic == "/bus"}
    places = sorted((c.chunk_start_offset, c.chunk_start_offset + c.chunk_length + c.message_index_length)
                    for c in summary.chunk_indexes)
    with open(path, "rb") as fh:
        found = [rec for rec in StreamReader(fh, emit_chunks=True).records if type(rec).__name__ == "Chunk"]
    ticks = [{m.publish_time // DT for m in breakup_chunk(c) if getattr(m, "channel_id", None) in bus} for c in found]
    return [(a, b, t) for (a, b), t in zip(places, ticks, strict=True)]


def kept_ticks(path: Path) -> list[int]:
    """The /bus ticks of a (recovered) file, read with the mcap package, checking every CRC."""
    with open(path, "rb") as fh:
        for _ in StreamReader(fh, validate_crcs=True).records:
            pass
    with open(path, "rb") as fh:
        return sorted(m.publish_time // DT for _s, _c, m in make_reader(fh).iter_messages(topics=["/bus"]))


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> tuple[Path, bytes, list]:
    path = run(tmp_path_factory.mktemp("damage") / "run.mcap")
    return path, path.read_bytes(), chunks(path)


def test_chunks_span_at_most_a_simulated_second(log):
    path, _data, table = log
    with open(path, "rb") as fh:
        indexes = make_reader(fh).get_summary().chunk_indexes
    assert len(indexes) >= TICKS * DT / 1e9  # 8 s simulated: at least 8 chunks
    assert all(c.message_end_time - c.message_start_time < 1_000_000_000 for c in indexes)
    # a tick's bus, poses and scene share a chunk: chunks follow each other in time
    assert all(a.message_end_time < b.message_start_time for a, b in itertools.pairwise(indexes))
    assert sorted(t for _a, _b, ticks in table for t in ticks) == list(range(TICKS + 1))


def test_chunks_hold_at_most_chunk_bytes(tmp_path):
    path = run(tmp_path / "small.mcap", ticks=600, chunk_bytes=32_000)
    with open(path, "rb") as fh:
        indexes = make_reader(fh).get_summary().chunk_indexes
    assert len(indexes) >= 8 and max(c.uncompressed_size for c in indexes) < 32_000 + 4_000


def test_recover_keeps_every_intact_chunk_around_several_damaged_ones(log, tmp_path):
    _path, data, table = log
    bad = bytearray(data)
    (a1, _b1, _t1), (a3, _b3, _t3), (a5, _b5, _t5), (_a6, b6, _t6) = table[1], table[3], table[5], table[6]
    bad[a1 + 200] ^= 0xFF                  # inside chunk 1's compressed data: its CRC fails
    bad[a3] = 0x16                         # chunk 3's opcode: an unknown record
    bad[a5 + 8] = 0x7F                     # chunk 5's length: runs past the end of the file
    mi = table[6][0] + int.from_bytes(data[table[6][0] + 1:table[6][0] + 9], "little") + 9
    bad[mi + 8] = 0x7F                     # the first message index after chunk 6: harmless, but out of step
    assert mi < b6
    (tmp_path / "bad.mcap").write_bytes(bad)
    out, report = recover(tmp_path / "bad.mcap")
    lost = table[1][2] | table[3][2] | table[5][2]
    expected = sorted(set(range(TICKS + 1)) - lost)
    assert kept_ticks(Path(out)) == expected
    assert report.run_ticks == len(expected) > TICKS - 3 * 520
    assert not report.complete and len(report.damaged) == 4 and report.dropped == 0
    assert "damaged" in report.problem and "3 more damaged regions" in report.problem
    index = read_index(out)
    assert index.report.complete and index.info.scenario_name == "two_cubes"


@pytest.mark.parametrize("where", ["inside chunk 2", "after chunk 4", "at the end of chunk 6", "in the summary"])
def test_a_file_cut_short_keeps_every_chunk_before_the_cut(log, tmp_path, where):
    _path, data, table = log
    cut = {"inside chunk 2": table[2][0] + 5000, "after chunk 4": table[4][1] - 3,
           "at the end of chunk 6": table[6][1], "in the summary": len(data) - 40}[where]
    (tmp_path / "cut.mcap").write_bytes(data[:cut])
    out, report = recover(tmp_path / "cut.mcap")
    expected = sorted(t for _a, end, ticks in table if end <= cut for t in ticks)
    if where == "after chunk 4":  # the chunk is whole; only its last message index is cut
        expected = sorted(t for _a, end, ticks in table[:5] for t in ticks)
    assert kept_ticks(Path(out)) == expected and report.run_ticks == len(expected)
    assert not report.complete and (report.lost_bytes > 0) == (where != "at the end of chunk 6")


def test_verify_refuses_a_log_with_no_ticks(log, tmp_path):
    _path, data, table = log
    (tmp_path / "early.mcap").write_bytes(data[:table[0][0] + 100])  # killed before its first chunk
    out, report = recover(tmp_path / "early.mcap")
    assert report.run_ticks == 0 and report.ticks is None
    with pytest.raises(LogError, match="holds no ticks"):
        verify(out)
    result = CliRunner().invoke(app, ["replay", out, "--verify"])
    assert result.exit_code == 2 and "holds no ticks" in " ".join(result.output.split())
