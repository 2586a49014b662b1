"""The log's chunk compression (zstd, the default; lz4; none): each file reads back with the mcap
package and with dynabrain's readers, and `replay --verify` replays it bit for bit. Writes of several
buffers at once (`McapWriter._write`) land in the file in order."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.read import iter_bus, read_index
from dynabrain.orchestrator.logs.schema import BusCodec, FieldNumbers, Slot
from dynabrain.orchestrator.logs.verify import verify
from dynabrain.orchestrator.logs.write import McapWriter
from dynabrain.orchestrator.scenario.model import load_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_each_compression_reads_back_and_verifies(tmp_path, compression):
    sc = load_scenario(SCENARIOS / "two_cubes.yaml")
    world = sc.build()
    path = tmp_path / "run.mcap"
    McapLogger(path, compression=compression, chunk_bytes=40_000).attach(world, sc)
    seen = {0: world.snapshot().bus}
    for _ in range(300):
        world.tick()
        seen[world.tick_count] = world.snapshot().bus
    world.close()

    with open(path, "rb") as fh:  # the mcap package: every chunk says its compression, every message decodes
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert {c.compression for c in summary.chunk_indexes} == {"" if compression == "none" else compression}
        assert len(summary.chunk_indexes) > 1
        assert sum(1 for _ in reader.iter_messages(topics=["/bus"])) == 301
    rows = {r.tick: r.row for r in iter_bus(path, read_index(path))}
    assert sorted(rows) == sorted(seen)
    for tick, bus in seen.items():
        assert rows[tick].tobytes() == np.asarray(bus, dtype=np.float64).tobytes()
    result = verify(path)
    assert result.ok, result.divergence


def test_an_unknown_compression_is_refused(tmp_path):
    with pytest.raises(DynabrainError, match="compression"):
        McapLogger(tmp_path / "run.mcap", compression="gzip")
    with pytest.raises(DynabrainError, match="compression"):
        McapWriter(tmp_path / "run.mcap", compression="brotli")


def test_writes_of_many_buffers_land_in_order(tmp_path, monkeypatch):
    from dynabrain.orchestrator.logs import write

    monkeypatch.setattr(write, "IOV_MAX", 3)  # more buffers than one system call takes
    writer = McapWriter(tmp_path / "w.mcap")
    start = writer.bytes_written
    parts = [bytes([k]) * (k + 1) for k in range(10)]
    writer._write(*parts, b"")
    writer.close()
    data = (tmp_path / "w.mcap").read_bytes()
    assert data[start:] == b"".join(parts)
    assert writer.bytes_written == len(data)


def test_bus_messages_written_into_used_memory_are_the_fresh_ones():
    """`BusCodec.encode` into a caller's memory (a chunk buffer, holding older bytes) writes the whole
    message: the same bytes as into the codec's own buffer."""
    slots = [Slot("a", 0, (), "m"), Slot("b", 1, (3,), "m"), Slot("c", 4, (2, 2), "rad"), Slot("d", 8, (), "")]
    codec = BusCodec(slots, FieldNumbers(), 9)
    rows = np.random.default_rng(1).normal(size=(5, 9))
    ticks, epochs = np.arange(5), np.array([0, 0, 1, 1, 2])
    fresh = codec.encode(rows, ticks, epochs, 2_000_000).copy()
    used = np.full((5, codec.length + 13), 0xAB, dtype=np.uint8)
    out = codec.encode(rows, ticks, epochs, 2_000_000, out=used[:, 7:7 + codec.length])
    assert np.array_equal(out, fresh)
    back, t, e = codec.decode(fresh)
    assert back.tobytes() == rows.tobytes() and list(t) == list(ticks) and list(e) == list(epochs)


@pytest.mark.parametrize("compression, at", [("zstd", -1), ("zstd", -200), ("lz4", -200), ("none", -200)])
def test_a_damaged_chunk_is_found_with_each_compression(tmp_path, compression, at):
    """zstd chunks carry the frame's checksum of their content (their MCAP CRC is 0), the others a CRC:
    a flipped bit in a chunk's data (``at``: from its end; -1 is the zstd checksum itself) loses that
    chunk, which `log recover` reports, and keeps the others."""
    from dynabrain.orchestrator.logs.recover import recover
    from dynabrain.orchestrator.logs.scan import TruncatedLogError, scan

    sc = load_scenario(SCENARIOS / "two_cubes.yaml")
    world = sc.build()
    path = tmp_path / "run.mcap"
    McapLogger(path, compression=compression, chunk_bytes=40_000).attach(world, sc)
    world.tick(600)
    world.close()
    with open(path, "rb") as fh:
        chunks = make_reader(fh).get_summary().chunk_indexes
    assert {c.compression for c in chunks} == {"" if compression == "none" else compression}
    assert len(chunks) >= 4
    data = bytearray(path.read_bytes())
    crcs = {int.from_bytes(data[c.chunk_start_offset + 33:c.chunk_start_offset + 37], "little") for c in chunks}
    assert (crcs == {0}) == (compression == "zstd")
    second = chunks[1]
    data[second.chunk_start_offset + second.chunk_length + at] ^= 0x01
    (tmp_path / "bad.mcap").write_bytes(data)
    with pytest.raises(TruncatedLogError):
        list(scan(tmp_path / "bad.mcap"))
    out, report = recover(tmp_path / "bad.mcap")
    assert len(report.damaged) == 1
    kept = {r.tick for r in iter_bus(out, read_index(out))}
    assert 0 in kept and 600 in kept and len(kept) < 601
