"""``dynabrain replay LOG --publish`` for real: a recording of the arm world (with a backtick, so some ticks
are discarded) replayed over Zenoh on loopback, by the CLI in another process and in-process, to a real
subscriber; the frames carry the recorded bus rows bit for bit, the events of the run follow, and the
pacing follows the speed factor."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from dynabrain.bridge import BrainClient, WorldRefusedError, publish_recording
from dynabrain.bridge.replay import LISTEN_ENV, load_recording
from dynabrain.bridge.testing import Process
from dynabrain.bridge.zenoh_io import Settings, free_port
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.logs.logger import McapLogger
from dynabrain.orchestrator.logs.read import iter_bus, read_index
from dynabrain.orchestrator.logs.schema import TOPIC_BUS
from dynabrain.orchestrator.scenario.model import load_scenario

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, "bridge", "arm.yaml")
STREAM = ("core.body_pos", "core.body_quat", "core.joint_q", "core.joint_qd")


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """300 ticks of the arm moving, with a backtick of 60 and a parameter change after it."""
    path = tmp_path_factory.mktemp("replay") / "arm.mcap"
    sc = load_scenario(ARM)
    world = sc.build()
    McapLogger(path).attach(world, sc)
    world.set("servo.target", [0.4, 0.7, -1.0])
    world.tick(150)
    world.set("core.friction", 0.6)  # discarded by the backtick: not part of the run
    world.tick(10)
    world.backtick(70)
    world.set("core.friction", 0.5)
    world.tick(210)
    world.close()
    return path


def recorded_rows(path, names=STREAM) -> dict[int, np.ndarray]:
    """The run's stream values per tick, read back with the project's reader."""
    index = read_index(path)
    final = index.final(TOPIC_BUS)
    out = {}
    for codec, _e, tick, row, pos, _t in iter_bus(path, index):
        if pos in final:
            out[tick] = np.concatenate([row[codec.by_name[n].offset:codec.by_name[n].offset + codec.by_name[n].size]
                                        for n in names])
    return out


class Collector:
    def __init__(self):
        self.frames, self.arrived, self.events = [], [], []
        self.lock = threading.Lock()

    def on_frame(self, frame) -> None:
        with self.lock:
            self.frames.append(frame)
            self.arrived.append(time.perf_counter())

    def on_event(self, event) -> None:
        with self.lock:
            self.events.append(event)


def check_frames(got: Collector, path) -> None:
    rows = recorded_rows(path)
    assert [f.tick for f in got.frames] == sorted(rows), "every tick of the run, once, in order"
    assert len(rows) == 301  # ticks 0..300: the discarded ticks are not replayed
    for frame in got.frames:
        assert np.array_equal(frame.values, rows[frame.tick]), f"tick {frame.tick} differs from the recording"
        assert frame.time_ns == frame.tick * 2_000_000
    assert np.array_equal(got.frames[-1]["core.joint_q"], rows[300][-6:-3])
    kinds = [(e["kind"], e["tick"], e["detail"].get("value")) for e in got.events]
    assert ("param", 90, 0.5) in kinds and ("rollback", 90, None) in kinds
    assert ("param", 150, 0.6) not in kinds, "an event of the discarded future is not part of the run"
    assert "layout" not in {e["kind"] for e in got.events}


def test_the_cli_replays_a_recording_to_a_subscriber_bit_for_bit(recording):
    replay = Process(["-m", "dynabrain.orchestrator.cli", "replay", str(recording), "--publish", "--speed", "2"],
                     ready="replaying world", env={LISTEN_ENV: "tcp/127.0.0.1:0"})
    got = Collector()
    with replay:
        endpoint = replay.ready_line.split(" on ")[1].split()[0]
        with BrainClient("arm", connect=endpoint) as brain:
            status = brain.status()
            assert status["replay"]["file"] == "arm.mcap" and [s["name"] for s in status["stream"]["signals"]] \
                == list(STREAM)
            with pytest.raises(WorldRefusedError, match=r"replay of arm\.mcap: it answers status only"):
                brain.tick(1)
            brain.subscribe_events(got.on_event)
            brain.subscribe_state(got.on_frame)  # the replay starts once a subscriber is there
            code, out = replay.wait(30)
            time.sleep(0.2)  # the last samples in flight
    assert code == 0, out
    assert "replayed 301 frames" in out, out
    check_frames(got, recording)
    # pacing: 300 ticks of 2 ms at speed 2 take at least 0.3 s, and arrivals never run ahead of half the
    # simulated time (the slope of arrival against simulated time). Only lower bounds: a busy machine
    # may publish late, never early, and a test asserts no wall time from above.
    span = got.arrived[-1] - got.arrived[0]
    assert span > 0.3 * 0.8, span
    slope = np.polyfit([f.time_ns / 1e9 for f in got.frames], got.arrived, 1)[0]
    assert slope > 0.5 * 0.7, slope


def test_in_process_replay_follows_the_speed_and_a_chosen_stream(recording):
    port = free_port()
    result = {}
    ready = threading.Event()

    def run() -> None:
        result["r"] = publish_recording(recording, speed=6.0, settings=Settings(listen=[f"tcp/127.0.0.1:{port}"]),
                                        name="arm-replay", signals=["cube.pos", "servo.f*"], wait_s=20,
                                        log=lambda line: ready.set())

    thread = threading.Thread(target=run)
    thread.start()
    got = Collector()
    try:
        assert ready.wait(20)
        with BrainClient("arm-replay", connect=f"tcp/127.0.0.1:{port}") as brain:
            names = [s["name"] for s in brain.status()["stream"]["signals"]]
            assert names == ["core.cube.pos", "servo.force"]
            brain.subscribe_state(got.on_frame)
            thread.join(30)
            time.sleep(0.2)
    finally:
        thread.join(30)
    r = result["r"]
    assert r.frames == 301 and len(got.frames) == 301 and r.first_tick == 0 and r.last_tick == 300
    rows = recorded_rows(recording, ["core.cube.pos", "servo.force"])
    assert all(np.array_equal(f.values, rows[f.tick]) for f in got.frames)
    assert got.frames[0]["cube.pos"][2] == pytest.approx(0.03, abs=1e-3)
    assert r.wall_s >= 0.6 / 6 * 0.95  # 0.6 s simulated at speed 6: never faster


def test_bad_input_is_a_clear_error(recording, tmp_path):
    with pytest.raises(DynabrainError, match=r"no signal 'cube.poz' in the recording \(did you mean 'core.cube.pos'"):
        load_recording(recording, ["cube.poz"])
    with pytest.raises(DynabrainError, match="positive factor"):
        publish_recording(recording, speed=0.0, settings=Settings(listen=["tcp/127.0.0.1:0"]))
    (tmp_path / "notes.txt").write_text("not a log\n")
    for bad, message in ((tmp_path / "missing.mcap", "missing.mcap: no such file"),
                         (tmp_path / "notes.txt", "notes.txt is not an MCAP file")):
        proc = subprocess.run([sys.executable, "-m", "dynabrain.orchestrator.cli", "replay", str(bad), "--publish"],
                              capture_output=True, text=True, timeout=60, cwd=tmp_path)
        assert proc.returncode == 2, proc.stdout + proc.stderr
        assert message in " ".join((proc.stdout + proc.stderr).split())
