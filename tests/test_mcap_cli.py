"""The log commands: replay's summary, plot, log recover after a SIGKILL, and every kind of bad
input (exit code 2, a message naming the file and the problem)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap.writer import Writer
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app
from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.logs.read import read_index
from dynabrain.orchestrator.logs.verify import verify

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"
runner = CliRunner()


def dyn(*args: str):
    result = runner.invoke(app, [str(a) for a in args])
    return result.exit_code, result.output


@pytest.fixture(scope="module")
def cubes_log(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("log") / "cubes.mcap"
    code, out = dyn("run", SCENARIOS / "two_cubes.yaml", "--log", path, "-q")
    assert code == 0, out
    return path


def test_replay_summarizes_a_run(cubes_log):
    code, out = dyn("replay", cubes_log)
    assert code == 0, out
    assert "scenario two_cubes" in out and "duration: 5.000 s simulated, ticks 0..2500" in out
    for line in ("/bus", "2501 messages  dynabrain.layout1.Bus (protobuf)", "foxglove.FrameTransforms",
                 "foxglove.SceneUpdate", "expect pass: aa rests flat on the floor", "run_end"):
        assert line in out, line


def test_plot_writes_a_png(cubes_log, tmp_path):
    png = tmp_path / "cubes.png"
    code, out = dyn("plot", cubes_log, "aa.pos[2]", "core.bb.pos", "bb.linvel", "-o", png)
    assert code == 0, out
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    default = dyn("plot", cubes_log, "aa.pos")
    assert default[0] == 0 and cubes_log.with_suffix(".png").exists()


@pytest.mark.parametrize(("args", "message"), [
    (("replay", "{tmp}/missing.mcap"), "missing.mcap: no such file"),
    (("replay", "{tmp}/notes.txt"), "notes.txt is not an MCAP file (it does not start with the MCAP magic"),
    (("replay", "{tmp}/empty.mcap"), "empty.mcap is not an MCAP file (it is empty)"),
    (("replay", "{tmp}/half.mcap"), "half.mcap is truncated or damaged"),
    (("plot", "{tmp}/half.mcap", "aa.pos"), "`dynabrain log recover"),
    (("replay", "{tmp}/other.mcap", "--verify"), "is not a dynabrain recording (written by 'other-tool"),
    (("plot", "{log}", "aa.poz"), "no signal 'aa.poz' in"),
    (("plot", "{log}", "aa.pos[5]"), "core.aa.pos has 3 component(s), so [5] does not exist"),
    (("plot", "{tmp}/other.mcap", "x"), "has no dynabrain bus channel"),
    (("log", "recover", "{tmp}/notes.txt"), "notes.txt is not an MCAP file"),
])
def test_bad_input_is_a_clear_error_with_exit_code_2(cubes_log, tmp_path, args, message):
    (tmp_path / "notes.txt").write_text("not a log\n")
    (tmp_path / "empty.mcap").write_bytes(b"")
    data = cubes_log.read_bytes()
    (tmp_path / "half.mcap").write_bytes(data[:len(data) // 2])
    with open(tmp_path / "other.mcap", "wb") as fh:
        writer = Writer(fh)
        writer.start(profile="", library="other-tool 1.0")
        writer.add_message(writer.register_channel("/x", "json", writer.register_schema("x", "jsonschema", b"{}")),
                           log_time=5, data=b"{}", publish_time=5)
        writer.finish()
    code, out = dyn(*(a.format(tmp=tmp_path, log=cubes_log) for a in args))
    assert code == 2, out
    assert message in " ".join(out.split()), out
    if "aa.poz" in args:
        assert "did you mean 'aa.pos'" in out


def test_a_foreign_mcap_still_has_a_summary(tmp_path):
    with open(tmp_path / "other.mcap", "wb") as fh:
        writer = Writer(fh)
        writer.start(library="other-tool 1.0")
        channel = writer.register_channel("/x", "json", writer.register_schema("x", "jsonschema", b"{}"))
        for t in (1_000_000_000, 3_500_000_000):
            writer.add_message(channel, log_time=t, data=b"{}", publish_time=t)
        writer.finish()
    code, out = dyn("replay", tmp_path / "other.mcap")
    assert code == 0, out
    assert "not a dynabrain recording" in out and "duration: 2.500 s" in out and "2 messages" in out


def test_a_recording_whose_scenario_no_longer_loads(tmp_path):
    (tmp_path / "box.xml").write_text('<mujoco><worldbody><body name="b" pos="0 0 1"><freejoint/>'
                                      '<geom type="box" size="0.1 0.1 0.1"/></body></worldbody></mujoco>')
    (tmp_path / "drop.yaml").write_text("name: drop\nworld: {step: 2ms, duration: 0.1s}\nscene: {model: box.xml}\n")
    code, out = dyn("run", tmp_path / "drop.yaml", "--log", tmp_path / "drop.mcap", "-q")
    assert code == 0, out
    assert dyn("replay", tmp_path / "drop.mcap", "--verify")[0] == 0
    (tmp_path / "box.xml").unlink()
    code, out = dyn("replay", tmp_path / "drop.mcap", "--verify")
    assert code == 2, out
    flat = " ".join(out.split())
    assert "the recorded scenario no longer loads" in flat and "model file 'box.xml' not found" in flat
    assert "drop.yaml (as recorded in" in flat


def _run_until_killed(path: Path, whole_group: bool, sig: int = signal.SIGKILL) -> None:
    """`dynabrain run --log` until the log holds 400 kB, then a signal (SIGKILL by default): to the
    simulation's process alone, or to it and its writer process together (as a terminal sends Ctrl-C
    to the whole foreground process group). The run is 10 simulated hours, so it is still running then
    even when a busy machine keeps the writer far behind it (600 s once ended first: the signal then
    found it exiting with status 0)."""
    proc = subprocess.Popen([sys.executable, "-m", "dynabrain.orchestrator.cli", "run",
                             str(SCENARIOS / "two_cubes.yaml"), "--log", str(path), "--duration", "36000s", "-q"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while (not path.exists() or path.stat().st_size < 400_000) and time.monotonic() < deadline:
            assert proc.poll() is None, proc.stderr.read().decode()
            time.sleep(0.05)
        if whole_group:
            os.killpg(proc.pid, sig)
        else:
            os.kill(proc.pid, sig)
    finally:
        proc.wait(timeout=30)
    expected = 130 if sig == signal.SIGINT else -sig  # Ctrl-C: the run stops cleanly, exit status 130
    assert proc.returncode == expected and path.stat().st_size >= 400_000
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:  # the writer process, if alive, finishes the file and ends
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    else:
        os.killpg(proc.pid, signal.SIGKILL)
        raise AssertionError("the log writer process did not end")


def _assert_the_run(path: Path) -> None:
    """What a log holds is the run from tick 0 on, and it re-simulates bit for bit."""
    for _ in StreamReader(open(path, "rb"), validate_crcs=True).records:  # noqa: SIM115
        pass
    with open(path, "rb") as fh:
        stats = make_reader(fh).get_summary().statistics
    index = read_index(path)
    ticks = sorted(t for _e, t, _p in index.keys["/bus"])
    assert ticks == list(range(len(ticks))) and len(ticks) > 1000
    assert stats.message_count == sum(index.counts.values()) and index.info.scenario_name == "two_cubes"
    result = verify(path)
    assert result.ok and result.last_tick == ticks[-1]


def test_a_killed_simulation_leaves_a_complete_log(tmp_path):
    """The writer process outlives the simulation's: it writes what it was handed and the summary."""
    path = tmp_path / "killed.mcap"
    _run_until_killed(path, whole_group=False)
    code, out = dyn("replay", path)
    assert code == 0, out
    _assert_the_run(path)


def test_ctrl_c_stops_a_logged_run_with_a_complete_log(tmp_path):
    """Ctrl-C reaches the writer process too (the whole process group); it leaves the stop to the
    simulation, which closes the log."""
    path = tmp_path / "stopped.mcap"
    _run_until_killed(path, whole_group=True, sig=signal.SIGINT)
    code, out = dyn("replay", path)
    assert code == 0, out
    _assert_the_run(path)


def test_a_run_killed_with_its_writer_is_recovered(tmp_path):
    path = tmp_path / "killed.mcap"
    _run_until_killed(path, whole_group=True)
    code, out = dyn("replay", path)
    assert code == 2 and "truncated" in out
    code, out = dyn("log", "recover", path)
    assert code == 0, out
    recovered = tmp_path / "killed.recovered.mcap"
    assert f"wrote {recovered}" in " ".join(out.split())
    _assert_the_run(recovered)


def test_the_scenario_log_setting_and_a_world_without_a_core(tmp_path):
    (tmp_path / "signals.yaml").write_text(
        "name: signals\nworld: {step: 1ms, duration: 0.2s, core: null, seed: 7}\n"
        "modules:\n  - {name: noise, python: dynabrain.modules.basic:Noise, params: {n: 2}}\n"
        "  - {name: wave, python: dynabrain.modules.basic:Sine, params: {frequency: 5Hz}}\n"
        "events:\n  - {at: 0.1s, set: {wave.amplitude: 3.0}}\n"
        "log: {mcap: runs/signals.mcap, decimate: 5}\n")
    code, out = dyn("run", tmp_path / "signals.yaml", "-q")
    assert code == 0, out
    path = tmp_path / "runs" / "signals.mcap"  # relative to the scenario's folder
    index = read_index(path)
    assert {c.topic for c in index.channels.values()} == {"/events", "/bus"}  # no core: no poses, no scene
    assert index.info.seed == 7 and index.info.settings["decimate"] == 5
    assert [e["source"] for e in index.events if e["kind"] == "param"] == ["scenario"]
    assert verify(path).ok
    code, out = dyn("plot", path, "wave.y", "noise.y[1]")
    assert code == 0 and (tmp_path / "runs" / "signals.png").exists()


def test_plot_names_rows_and_columns_and_groups_event_labels(tmp_path):
    from dynabrain.orchestrator.logs.logger import McapLogger
    from dynabrain.orchestrator.logs.plot import event_groups, resolve
    from dynabrain.orchestrator.scenario.model import load_scenario

    sc = load_scenario(SCENARIOS / "humanoid_stand.yaml")
    world = sc.build()
    McapLogger(tmp_path / "h.mcap").attach(world, sc)
    world.tick(20)
    world.close()
    index = read_index(tmp_path / "h.mcap")
    cop = resolve(index, "zmp.cop")  # (2, 3): a row per foot (the ports that view them), a column per axis
    assert cop.labels == ("[l_foot, x]", "[l_foot, y]", "[l_foot, z]", "[r_foot, x]", "[r_foot, y]", "[r_foot, z]")
    assert [resolve(index, s).component for s in ("zmp.cop[r_foot, z]", "zmp.cop[1, 2]", "zmp.cop[5]")] == [5, 5, 5]
    assert resolve(index, "core.torso.quat").labels == ("[w]", "[x]", "[y]", "[z]")
    with pytest.raises(DynabrainError, match=r"\[heel\] is no index of dimension 0 of zmp.cop \(0..1 or l_foot"):
        resolve(index, "zmp.cop[heel, x]")
    code, out = dyn("plot", tmp_path / "h.mcap", "zmp.cop", "zmp.cop[l_foot, y]")
    assert code == 0, out
    many = [(0.001 * k, "set") for k in range(30)] + [(0.5, "param"), (0.5, "set"), (2.0, "rollback")]
    assert event_groups(many, gap=0.05) == [(0.0, "set x30"), (0.5, "param, set"), (2.0, "rollback")]
