"""The logger's hot path and its blocks of rows: every tick's row reaches the file as the world had it
across what makes the hot path step aside (a new block, the scene each simulated second, a make, a
module added, a rollback), and rows so large that a block holds only a few never leave the stepping
thread waiting for a block the writer cannot give back."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

from dynabrain.modules.basic import Counter
from dynabrain.orchestrator.logs import logger as mcap_logger
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.read import iter_bus, read_index
from dynabrain.orchestrator.scenario.model import load_scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"


def record(tmp_path: Path, **kw):
    sc = load_scenario(SCENARIOS / "two_cubes.yaml")
    world = sc.build()
    McapLogger(tmp_path / "run.mcap", **kw).attach(world, sc)
    return world, tmp_path / "run.mcap"


@pytest.mark.parametrize("writer", ["process", "thread"])
def test_every_row_is_the_worlds_across_what_interrupts_the_hot_path(tmp_path, writer):
    world, path = record(tmp_path, window=8, batch=16, scene_every=37, writer=writer)
    seen = {0: world.snapshot().bus.tobytes()}

    def tick(n: int) -> None:
        for _ in range(n):
            world.tick()
            seen[world.tick_count] = world.snapshot().bus.tobytes()

    tick(90)  # blocks fill and new ones start; a scene every 37 ticks
    world.make(["aa"])
    tick(5)
    world.add_module(Counter("counter"))  # a new layout (the bus grows)
    tick(40)
    world.backtick(3)  # within the window
    tick(10)
    world.close()
    rows = {r.tick: r.row.tobytes() for r in iter_bus(path, read_index(path)) if r.topic.startswith("/bus")}
    assert sorted(rows) == sorted(seen) and all(rows[t] == seen[t] for t in seen)


def test_rows_that_fill_a_block_each_never_wait_for_a_block_forever(tmp_path, monkeypatch):
    # a block holds a single row and there are two at most: the batch (256 rows) cannot wait in blocks,
    # so the logger hands rows over before the batch is full rather than wait for a block
    monkeypatch.setattr(mcap_logger, "BLOCK_BYTES", 8)
    monkeypatch.setattr(mcap_logger, "MAX_BLOCKS", 2)
    world, path = record(tmp_path, window=0)
    previous = signal.signal(signal.SIGALRM, lambda *_: pytest.fail("the logger waited for a block"))
    signal.alarm(60)
    try:
        world.tick(300)
        world.close()
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    ticks = [r.tick for r in iter_bus(path, read_index(path)) if r.topic == "/bus"]
    assert ticks == list(range(301))
