"""Batches of imagined futures: portable state, the Batch API on every backend, bad input and faults.

The claim a batch makes: each branch's result is bit-identical to the same inputs stepped alone on the
world in-process. Every backend is checked against that reference, computed here by hand.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import pytest
from test_fmu_isolation import crashy_folder

from dynabrain.modules.basic import Counter
from dynabrain.orchestrator import Batch, DynabrainError, WiringError, load_world
from dynabrain.orchestrator.kernel.portable import StateFormatError, decode

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"
HUMANOID = SCENARIOS / "humanoid_stand.yaml"
TICKS = 40
RECORD = ("core.pelvis.pos", "zmp.zmp", "servo.tau")

pytestmark = pytest.mark.usefixtures("fmu_cache")


def bits(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, dtype=np.float64).tobytes()


def states_of(world) -> tuple:
    """Everything a snapshot holds that two worlds can share: tick, bus, module states, parameters."""
    snap = world.snapshot()
    return (snap.tick, bits(snap.bus), tuple(pickle.dumps(s) for s in snap.states),
            tuple(pickle.dumps(p) for p in snap.params))


def same_state(a: bytes, b: bytes) -> bool:
    """Two exported states hold the same values (their pickles may share objects differently)."""
    x, y = decode(a), decode(b)
    return (x.tick == y.tick and x.modules == y.modules and bits(x.bus) == bits(y.bus)
            and [pickle.dumps(s) for s in x.states] == [pickle.dumps(s) for s in y.states]
            and [pickle.dumps(p) for p in x.params] == [pickle.dumps(p) for p in y.params])


@pytest.fixture(scope="module")
def humanoid():
    world = load_world(HUMANOID)
    world.tick(25)
    yield world
    world.close()


def targets(world, branches: int) -> np.ndarray:
    """Per-branch, per-tick offsets to the servo's program: each branch leans the first joints by its
    own angle, growing over the ticks."""
    out = np.zeros((branches, TICKS, *np.shape(world.get("servo.q_ref"))))
    for b in range(branches):
        out[b, :, :2] = 0.05 * (b - 1) * np.linspace(0, 1, TICKS)[:, None]
    return out


def reference(world, start: bytes, inputs: dict, params: dict) -> tuple[dict[str, np.ndarray], bytes]:
    """The branch stepped alone, in this process, by the World API: its signals and final state."""
    twin = world.fork()
    try:
        twin.import_state(start)
        for name, value in params.items():
            twin.set(name, value)
        out = {name: [] for name in RECORD}
        for k in range(TICKS):
            for name, values in inputs.items():
                twin.set(name, values[k])
            twin.tick()
            for name in RECORD:
                out[name].append(np.asarray(twin.get(name), dtype=np.float64))
        return {name: np.stack(rows) for name, rows in out.items()}, twin.export_state()
    finally:
        twin.close()


# -- portable state ---------------------------------------------------------------------------------------
def test_export_import_is_bit_exact_in_another_world(humanoid):
    data = humanoid.export_state()
    humanoid.tick(30)
    expected = states_of(humanoid)
    humanoid.backtick(30)
    other = load_world(HUMANOID)
    try:
        other.tick(3)  # somewhere else entirely
        other.import_state(data)
        assert other.tick_count == humanoid.tick_count
        other.tick(30)
        assert states_of(other) == expected
        other.backtick(10)  # history restarts at the imported state and works
        other.tick(10)
        assert states_of(other) == expected
    finally:
        other.close()


def test_import_brings_modules_added_at_run_time(tmp_path):
    world = load_world(SCENARIOS / "two_cubes.yaml")
    other = load_world(SCENARIOS / "two_cubes.yaml")
    try:
        world.tick(10)
        world.add_module(Counter("count"))
        world.set("core.friction", 0.4)
        world.tick(5)
        other.import_state(world.export_state())
        assert "count" in other.modules and other.get("core.friction") == 0.4
        world.tick(20)
        other.tick(20)
        assert bits(world.snapshot().bus) == bits(other.snapshot().bus)
        assert world.get("count.count") == other.get("count.count") > 0
    finally:
        world.close()
        other.close()


def test_import_refuses_another_world_and_damaged_bytes(humanoid):
    data = humanoid.export_state()
    cubes = load_world(SCENARIOS / "two_cubes.yaml")
    try:
        before = states_of(cubes)
        with pytest.raises(StateFormatError, match=r"module 'core' differs.*other ports"):
            cubes.import_state(data)
        with pytest.raises(StateFormatError, match="not a dynabrain world state"):
            cubes.import_state(b"hello")
        with pytest.raises(StateFormatError, match="damaged"):
            cubes.import_state(data[:-50])
        assert states_of(cubes) == before  # the world is as it was
    finally:
        cubes.close()


def test_import_never_runs_code_from_the_bytes(humanoid, tmp_path):
    data = humanoid.export_state()
    head_end = 20 + int.from_bytes(data[16:20], "little")  # magic, length, header: the payload follows
    marker = tmp_path / "ran"
    evil = pickle.dumps(Evil(str(marker)), protocol=5)
    with pytest.raises(StateFormatError, match="which is not a state type"):
        humanoid.import_state(data[:head_end] + evil)
    assert not marker.exists()


class Evil:
    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return (open, (self.path, "w"))


# -- the batch, every backend -------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", ["serial", "processes"])
def test_each_branch_equals_the_same_inputs_stepped_alone(humanoid, backend):
    start = humanoid.export_state()
    inputs = {"servo.q_ref": targets(humanoid, 3)}
    frictions = [0.6, 0.9, 1.2]
    before = states_of(humanoid)
    with Batch(humanoid, backend=backend, workers=2) as batch:
        result = batch.run(TICKS, branches=3, inputs=inputs, params={"core.friction": frictions}, record=RECORD)
    assert result.ok and result.backend == backend
    assert states_of(humanoid) == before  # nothing of the world changed
    for b in range(3):
        ref, final = reference(humanoid, start, {"servo.q_ref": inputs["servo.q_ref"][b]},
                               {"core.friction": frictions[b]})
        assert same_state(result.states[b], final), (backend, b)
        for name in RECORD:
            assert result.signals[name].shape == (3, TICKS, *ref[name].shape[1:])
            assert bits(result.signals[name][b]) == bits(ref[name]), (backend, b, name)
    # each branch's final state continues exactly like the branch would
    twin = humanoid.fork()
    try:
        twin.import_state(result.states[2])
        assert bits(twin.get("core.pelvis.pos")) == bits(result.signals["core.pelvis.pos"][2, -1])
    finally:
        twin.close()


def test_bad_requests_are_refused_before_anything_runs(humanoid):
    tick0 = humanoid.tick_count
    with Batch(humanoid, backend="serial") as batch:
        for branches in (0, -1, 2.5):
            with pytest.raises(DynabrainError, match="branch count"):
                batch.run(10, branches=branches)
        with pytest.raises(WiringError, match=r"shape \(3, 23\)"):
            batch.run(10, branches=2, inputs={"servo.q_ref": np.zeros((3, 23))})
        with pytest.raises(DynabrainError, match=r"no signal or parameter named 'servo\.targt'"):
            batch.run(10, branches=2, inputs={"servo.targt": np.zeros((10, 23))})
        with pytest.raises(DynabrainError, match=r"nothing\.here"):
            batch.run(10, branches=2, record=["nothing.here"])
        with pytest.raises(DynabrainError, match=r"2 values of core\.friction for 3 branches"):
            batch.run(10, branches=3, params={"core.friction": [0.5, 0.6]})
        cubes = load_world(SCENARIOS / "two_cubes.yaml")
        try:
            with pytest.raises(DynabrainError, match=r"starts\[0\].*module 'core' differs"):
                batch.run(10, starts=[cubes.export_state()])
        finally:
            cubes.close()
        with pytest.raises(DynabrainError, match="ticks must be a positive integer"):
            batch.run(0, branches=2)
    assert humanoid.tick_count == tick0
    with pytest.raises(DynabrainError, match="unknown"):
        Batch(humanoid, backend="gpu")


def test_a_failing_branch_is_marked_and_the_others_go_on(humanoid):
    """A diverging branch (an absurd gravity) fails with its reason; the others are returned."""
    with Batch(humanoid, backend="serial") as batch:
        result = batch.run(TICKS, branches=3, params={"core.gravity": [[0, 0, -9.81], [0, 0, -1e12], [0, 0, -9.81]]},
                           record=["core.pelvis.pos"])
    assert [s.ok for s in result.status] == [True, False, True]
    assert "core" in result.status[1].reason and result.failed == [1]
    assert np.isfinite(result.signals["core.pelvis.pos"][0]).all()
    assert bits(result.signals["core.pelvis.pos"][0]) == bits(result.signals["core.pelvis.pos"][2])


@pytest.mark.parametrize("crash", [1, 0])
def test_a_worker_that_segfaults_is_reported_and_replaced(tmp_path, crash):
    """An FMU that crashes its process (in-process, not isolated) kills the worker running branch
    ``crash``; the other branches are still returned (one handed to the same worker behind it runs on
    its replacement) and the pool has a fresh worker for the next run."""
    src = crashy_folder(tmp_path)
    scenario = tmp_path / "crashy.yaml"
    scenario.write_text(f"name: crashy\nworld: {{step: 1ms, duration: 1s, core: null}}\n"
                        f"modules:\n  - {{name: c, fmu: {src.name}, params: {{how: 0}}}}\n")
    world = load_world(scenario)
    try:
        u = np.zeros((3, 20, 1)) if np.shape(world.get("c.u")) == (1,) else np.zeros((3, 20))
        u[crash, 10:] = 1.0  # that branch crashes at its 11th tick
        with Batch(world, backend="processes", workers=2) as batch:
            result = batch.run(20, inputs={"c.u": u}, branches=3, record=["c.y"])
            assert [s.ok for s in result.status] == [i != crash for i in range(3)]
            reason = result.status[crash].reason
            assert f"branch {crash} died" in reason and "SIGSEGV" in reason
            assert batch._pool.replaced == 1
            again = batch.run(5, branches=2, record=["c.y"])
            assert again.ok
    finally:
        world.close()


def test_processes_need_a_world_that_can_be_rebuilt(humanoid):
    from dynabrain.orchestrator import World

    bare = World("bare")
    try:
        with pytest.raises(DynabrainError, match="load_world"):
            Batch(bare, backend="processes")
        # auto falls back on the in-process backend: lockstep where there are cores to step on, else serial
        assert Batch(bare).backend == ("lockstep" if (os.cpu_count() or 1) > 1 else "serial")
        with pytest.raises(DynabrainError, match=r"physics='mjwarp' chooses how the lockstep backend"):
            Batch(bare, backend="serial", physics="mjwarp")
    finally:
        bare.close()


def test_a_serial_batch_brings_modules_added_to_the_world(tmp_path):
    """The serial backend's private copy makes, like the world, a module the start state has and the
    copy lacks; a parameter's name is not a signal to record."""
    world = load_world(SCENARIOS / "two_cubes.yaml")
    try:
        with Batch(world, backend="serial") as batch:
            batch.run(2, branches=1)  # the private copy exists before the module is added
            world.add_module(Counter("count"))
            result = batch.run(5, branches=2, record=["count.count"])
            assert result.ok and result.signals["count.count"][:, -1].tolist() == [5.0, 5.0]
            with pytest.raises(DynabrainError, match="no signal"):
                batch.run(5, branches=2, record=["core.friction"])
    finally:
        world.close()


def test_a_body_own_friction_is_a_parameter_a_batch_can_sweep():
    world = load_world(SCENARIOS / "two_cubes.yaml")
    try:
        world.tick(100)
        world.set("core.aa.velocity", [1.0, 0, 0, np.nan, np.nan, np.nan])
        world.tick(1)
        world.set("core.aa.velocity", [np.nan] * 6)
        with Batch(world, backend="serial") as batch:
            result = batch.run(200, branches=3, params={"core.aa.friction": [0.1, 0.5, None]}, record=["aa.pos"])
            assert result.ok
            slid = result.signals["aa.pos"][:, -1, 0]
            assert slid[0] > slid[1]  # less friction, further
            with pytest.raises(DynabrainError, match="finite number >= 0"):
                batch.run(5, branches=2, params={"core.aa.friction": [0.1, -1.0]})
    finally:
        world.close()
