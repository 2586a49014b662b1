"""The ``threads`` batch backend (`mujoco.rollout` on threads) for worlds whose only module is the MuJoCo
core: every branch bit-identical to the ``serial`` backend (which test_batch checks against the branch
stepped alone), its final state the same; requests it cannot serve refused before anything runs; a
diverging branch failed as on every backend while the others go on.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

from dynabrain.orchestrator import Batch, DynabrainError, WiringError, load_world
from dynabrain.orchestrator.kernel.portable import decode

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"
TICKS = 40
RECORD = ("core.joint_q", "pelvis.pos", "core.body_quat", "l_knee.qd", "sensor.imu_gyro", "sensor.imu_acc",
          "sensor.l_sole", "core.body_linvel", "core.ctrl")
"""Joints (qpos rows), a free body's position (qpos), orientations (mj_kinematics), a velocity-stage and
two acceleration-stage sensors, the core's velocity sensors, an input."""


def bits(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, dtype=np.float64).tobytes()


def same_state(a: bytes, b: bytes) -> bool:
    """Two exported states hold the same values (as in test_batch)."""
    x, y = decode(a), decode(b)
    return (x.tick == y.tick and x.modules == y.modules and bits(x.bus) == bits(y.bus)
            and [pickle.dumps(s) for s in x.states] == [pickle.dumps(s) for s in y.states]
            and [pickle.dumps(p) for p in x.params] == [pickle.dumps(p) for p in y.params])


def fingerprint(world) -> tuple:
    snap = world.snapshot()
    return snap.tick, bits(snap.bus), pickle.dumps(snap.states)


@pytest.fixture(scope="module")
def humanoid(tmp_path_factory):
    """The humanoid model alone: a scenario with the MuJoCo core and no module."""
    path = tmp_path_factory.mktemp("threads") / "humanoid_core.yaml"
    path.write_text("name: humanoid_core\nworld: {step: 2ms, duration: 1s, core: mujoco}\n"
                    f"scene: {{model: {SCENARIOS / 'models' / 'humanoid.xml'}}}\n")
    world = load_world(path)
    world.tick(25)
    yield world
    world.close()


def on_both(world, ticks: int, *, reran: int = 0, **request):
    """The same request on ``serial`` (the reference) and on ``threads``, where ``reran`` branches are
    run again on the world (the others rolled out)."""
    out = []
    for backend in ("serial", "threads"):
        with Batch(world, backend=backend, workers=2) as batch:
            out.append(batch.run(ticks, **request))
            if backend == "threads":
                assert batch._pool.reran == reran
    return out


def assert_same(serial, threads, record) -> None:
    assert threads.backend == "threads"
    assert [str(s) for s in threads.status] == [str(s) for s in serial.status]
    assert [s.failed_tick for s in threads.status] == [s.failed_tick for s in serial.status]
    for name in record:
        assert threads.signals[name].shape == serial.signals[name].shape
        for b in range(len(serial.status)):
            assert bits(threads.signals[name][b]) == bits(serial.signals[name][b]), (name, b)
    for b, (x, y) in enumerate(zip(serial.states, threads.states, strict=True)):
        assert (x is None and y is None) or same_state(x, y), b


def test_each_branch_equals_the_serial_backend(humanoid):
    """Three branches, each with its own torque sequence and friction, one with a joint force too."""
    rng = np.random.default_rng(7)
    ctrl = rng.normal(0.0, 0.4, (3, TICKS, *np.shape(humanoid.get("core.ctrl"))))
    knee = np.zeros((3, TICKS))
    knee[2] = np.linspace(0.0, 0.5, TICKS)
    before = fingerprint(humanoid)
    serial, threads = on_both(humanoid, TICKS, branches=3, inputs={"core.ctrl": ctrl, "l_knee.force": knee},
                              params={"core.friction": [0.5, 0.9, 1.3]}, record=RECORD)
    assert threads.ok
    assert_same(serial, threads, RECORD)
    assert fingerprint(humanoid) == before  # nothing of the world changed
    assert bits(threads.signals["core.ctrl"]) == bits(ctrl)
    twin = humanoid.fork()  # a final state continues exactly like the branch would
    try:
        twin.import_state(threads.states[1])
        assert twin.tick_count == humanoid.tick_count + TICKS and twin.get("core.friction") == 0.9
        assert bits(twin.get("core.pelvis.pos")) == bits(threads.signals["pelvis.pos"][1, -1])
    finally:
        twin.close()


def test_starts_per_branch_without_states(humanoid):
    later = humanoid.fork()
    try:
        later.tick(15)
        starts = [humanoid.export_state(), later.export_state(), humanoid.export_state()]
    finally:
        later.close()
    serial, threads = on_both(humanoid, 20, starts=starts, record=RECORD, keep_states=False)
    assert threads.states == [None, None, None]
    assert_same(serial, threads, RECORD)


def test_edited_structures_wrenches_and_substeps():
    """Starts on four structures (a frozen object fused into the world, a weld, a collision filter),
    wrench inputs on a free body, substeps that differ per branch."""
    world = load_world(SCENARIOS / "two_cubes.yaml")
    try:
        world.tick(100)
        starts = [world.export_state()]
        world.make(["aa"])
        world.tick(5)
        starts.append(world.export_state())
        world.make(["aa", "bb"])
        world.make_joint("aa", "bb")
        world.tick(5)
        starts.append(world.export_state())
        world.no_collision(["aa", "bb"])
        world.set("bb.wrench", [0.0, 0.0, 0.2, 0.0, 0.01, 0.0])  # held on the bus, not driven
        world.tick(3)
        starts.append(world.export_state())
        wrench = np.zeros((4, 60, 6))
        wrench[:, :, 0] = np.linspace(-0.4, 0.4, 4)[:, None]
        record = ("core.body_pos", "core.body_quat", "core.body_linvel", "core.body_angvel", "bb.wrench")
        serial, threads = on_both(world, 60, starts=starts, inputs={"aa.wrench": wrench},
                                  params={"core.substeps": [1, 3, 2, 1], "core.restitution": 0.4}, record=record)
        assert threads.ok
        assert_same(serial, threads, record)
    finally:
        world.close()


def test_a_diverging_branch_fails_as_on_every_backend_and_the_others_go_on(humanoid):
    gravity = [[0, 0, -9.81], [0, 0, -1e12], [0, 0, -9.81]]
    serial, threads = on_both(humanoid, TICKS, reran=1, branches=3, params={"core.gravity": gravity}, record=RECORD)
    assert [s.ok for s in threads.status] == [True, False, True]
    assert "core" in threads.status[1].reason and threads.status[1].failed_tick == humanoid.tick_count
    assert_same(serial, threads, RECORD)  # the failure, its partial signals and rolled-back state included
    assert bits(threads.signals["pelvis.pos"][0]) == bits(threads.signals["pelvis.pos"][2])


def test_a_warning_that_stops_rollout_runs_the_branch_again(humanoid):
    """A NaN control: MuJoCo warns and zeroes it, the core goes on, `mujoco.rollout` stops at the
    warning. That branch is run again on the world and returned as on every backend."""
    ctrl = np.zeros((3, TICKS, *np.shape(humanoid.get("core.ctrl"))))
    ctrl[1, 10, 3] = np.nan
    serial, threads = on_both(humanoid, TICKS, reran=1, branches=3, inputs={"core.ctrl": ctrl}, record=RECORD)
    assert threads.ok
    assert_same(serial, threads, RECORD)


def test_requests_it_cannot_serve_are_refused_before_anything_runs(humanoid):
    full = load_world(SCENARIOS / "humanoid_stand.yaml")
    try:
        with Batch(full, backend="threads") as batch, pytest.raises(
                DynabrainError, match=r"only module is the MuJoCo core.*also has .*servo.*'processes'"):
            batch.run(5, branches=2)
    finally:
        full.close()
    cubes = load_world(SCENARIOS / "two_cubes.yaml")
    try:
        before = fingerprint(cubes)
        with Batch(cubes, backend="threads") as batch:
            with pytest.raises(WiringError, match=r"cannot drive 'aa\.velocity'.*core\.ctrl.*core\.<body>\.wrench"):
                batch.run(5, branches=2, inputs={"aa.velocity": np.zeros((5, 6))})
            cubes.set("aa.velocity", [0.0, 0.0, 1.0, np.nan, np.nan, np.nan])
            with pytest.raises(DynabrainError, match=r"holds a value in core\.body_velocity"):
                batch.run(5, branches=2)
        cubes.set("aa.velocity", [np.nan] * 6)
        twin = cubes.fork()
        try:
            twin.at(twin.time_ns + 2 * twin.dt_ns, "push", lambda w: w.set("core.friction", 0.1))
            with Batch(twin, backend="threads") as batch, pytest.raises(DynabrainError, match=r"scenario events"):
                batch.run(5, branches=2)
            with Batch(twin, backend="threads") as batch:
                assert batch.run(2, branches=1).ok  # the event is after these ticks
        finally:
            twin.close()
        cubes.set("aa.velocity", [np.nan] * 6)
        assert fingerprint(cubes)[:2] == before[:2]
    finally:
        cubes.close()
