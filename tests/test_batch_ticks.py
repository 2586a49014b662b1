"""A batch a controller (and a planner) can live with: branches of different lengths in one batch, on
every backend, each bit for bit the branch stepped alone; a batch submitted now and taken later; one
input sequence broadcast to several ports; a dead worker's branch marked lost, not failed."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest
from test_batch import same_state

from dynabrain.orchestrator import Batch, DynabrainError, WiringError, load_world

ROOT = Path(__file__).resolve().parent
SLIDER = ROOT / "scenarios" / "slider.yaml"
CUBES = ROOT.parent / "scenarios" / "two_cubes.yaml"
LENGTHS = [30, 7, 55, 1]
RECORD = ["core.s.q", "core.s.qd"]


@pytest.fixture(scope="module")
def slider():
    world = load_world(SLIDER)
    world.tick(5)
    yield world
    world.close()


@pytest.fixture(scope="module")
def processes(slider):
    """Two worker processes for the slider, shared by this file's tests (one kills a worker: the pool
    replaces it)."""
    with Batch(slider, backend="processes", workers=2) as batch:
        yield batch


def batch_of(slider, processes, backend: str) -> Batch:
    return processes if backend == "processes" else Batch(slider, backend=backend, workers=2)


def forces(b: int, ticks: int) -> np.ndarray:
    return np.linspace(-3.0 + 2.0 * b, 6.0 - b, ticks)


def alone(world, start: bytes, ticks: int, force: np.ndarray) -> tuple[dict[str, np.ndarray], bytes]:
    """The branch stepped alone on a copy of the world, by the World API."""
    twin = world.fork()
    try:
        twin.import_state(start)
        recorded = twin.run(ticks, inputs={"core.s.force": force}, record=RECORD)
        return recorded, twin.export_state()
    finally:
        twin.close()


def check_ragged(world, batch: Batch) -> None:
    first = world.export_state()
    world.tick(3)
    second = world.export_state()
    world.backtick(3)
    starts = [first, second, first, second]
    inputs = [forces(b, t) for b, t in enumerate(LENGTHS)]
    result = batch.run(LENGTHS, starts=starts, inputs={"core.s.force": inputs}, record=RECORD)
    backend = batch.backend
    assert result.ok and result.ticks == max(LENGTHS) and result.branch_ticks == LENGTHS
    for b, ticks in enumerate(LENGTHS):
        ref, final = alone(world, starts[b], ticks, inputs[b])
        assert same_state(result.states[b], final), (backend, b)
        for name in RECORD:
            assert result.signals[name].shape == (len(LENGTHS), max(LENGTHS))
            assert result.branch(name, b).tobytes() == ref[name].tobytes(), (backend, b, name)
            assert np.isnan(result.signals[name][b, ticks:]).all()  # past its end


@pytest.mark.parametrize("backend", ["serial", "processes", "threads"])
def test_branches_of_different_lengths_each_equal_the_branch_alone(slider, processes, backend):
    batch = batch_of(slider, processes, backend)
    check_ragged(slider, batch)
    if backend == "threads":
        assert batch._pool.reran == 0  # every branch rolled out by mujoco.rollout, none stepped again
    if batch is not processes:
        batch.close()


def test_branches_of_different_lengths_on_ray(slider):
    ray = pytest.importorskip("ray")
    mine = not ray.is_initialized()
    if mine:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False,
                 _node_ip_address="127.0.0.1")
    try:
        with Batch(slider, backend="ray", workers=2) as batch:
            check_ragged(slider, batch)
    finally:
        if mine:
            ray.shutdown()


def test_tick_counts_and_inputs_that_do_not_fit_are_refused(slider):
    with Batch(slider, backend="serial") as batch:
        with pytest.raises(DynabrainError, match="3 tick counts for 2 branches"):
            batch.run([5, 6, 7], branches=2)
        with pytest.raises(DynabrainError, match="one per branch"):
            batch.run([5, 0])
        with pytest.raises(WiringError, match="branch 1 have shape"):
            batch.run([5, 6], inputs={"core.s.force": [np.zeros(5), np.zeros(4)]})
        with pytest.raises(WiringError, match=r"up to 6 ticks"):
            batch.run([5, 6], inputs={"core.s.force": np.zeros(5)})
        wide = batch.run([2, 4], inputs={"core.s.force": np.ones((2, 4))}, record=["core.s.force"])
        assert wide.branch("core.s.force", 0).tolist() == [1.0, 1.0]  # a branch takes the rows it runs


@pytest.mark.parametrize("backend", ["serial", "processes"])
def test_a_submitted_batch_runs_while_the_world_goes_on(slider, processes, backend):
    start = slider.export_state()
    inputs = {"core.s.force": [forces(b, t) for b, t in enumerate(LENGTHS)]}
    batch = batch_of(slider, processes, backend)
    future = batch.submit(LENGTHS, inputs=inputs, record=RECORD)  # from the world now
    slider.tick(20)  # the controller goes on; the batch read the world when it was submitted
    later = batch.run(LENGTHS, starts=[start] * 4, inputs=inputs, record=RECORD)  # after the submitted one
    result = future.result(timeout=60)
    if batch is not processes:
        batch.close()
    slider.import_state(start)
    for b, ticks in enumerate(LENGTHS):
        ref, final = alone(slider, start, ticks, inputs["core.s.force"][b])
        assert same_state(result.states[b], final), b
        for name in RECORD:
            assert result.branch(name, b).tobytes() == ref[name].tobytes()
            assert later.branch(name, b).tobytes() == ref[name].tobytes()


def test_a_submitted_batch_fails_as_run_would(slider):
    with Batch(slider, backend="serial") as batch:
        bad = batch.submit(5, branches=1, inputs={"core.s.force": np.full(5, 1e300)}, record=RECORD)
        assert not bad.result(timeout=60).ok  # a failed branch is a value in the future too
        with pytest.raises(DynabrainError, match="no signal"):
            batch.submit(5, branches=1, record=["core.nothing"])  # a bad request: at once, not in the future


def test_one_sequence_broadcast_to_several_ports():
    world = load_world(CUBES)
    try:
        push = np.zeros((10, 6))
        push[:, 2] = 3.0
        with Batch(world, backend="serial") as batch:
            both = batch.run(10, branches=1, inputs={("core.aa.wrench", "core.bb.wrench"): push},
                             record=["core.aa.wrench", "core.bb.wrench", "aa.pos", "bb.pos"])
            apart = batch.run(10, branches=1, inputs={"core.aa.wrench": push, "core.bb.wrench": push},
                              record=["core.aa.wrench", "core.bb.wrench", "aa.pos", "bb.pos"])
            with pytest.raises(WiringError, match="given twice"):
                batch.run(10, branches=1, inputs={("core.aa.wrench", "core.bb.wrench"): push, "core.aa.wrench": push})
        for name in both.signals:
            assert both.signals[name].tobytes() == apart.signals[name].tobytes()
        assert (both.signals["core.bb.wrench"][0, :, 2] == 3.0).all()
    finally:
        world.close()


def test_a_dead_worker_s_branch_is_lost_not_failed(processes):
    """A worker killed between two batches: the branch handed to it first is marked lost (its worker
    died; the branch may well be fine), with the cause; the pool replaces the worker."""
    batch = processes
    assert batch.run(5, branches=2).ok
    replaced = batch._pool.replaced
    victim = batch._pool._workers[0].proc
    os.kill(victim.pid, signal.SIGKILL)
    victim.wait()
    result = batch.run(5, branches=4, record=RECORD)
    lost = [s for s in result.status if s.lost]
    assert len(lost) == 1 and not lost[0].ok and "SIGKILL" in lost[0].reason
    assert all(s.ok for s in result.status if not s.lost)
    assert batch.run(5, branches=4).ok and batch._pool.replaced == replaced + 1


def test_the_threads_backend_refuses_an_animated_robot_and_runs_a_core_with_joint_targets():
    """A robot a selection left out follows its joint targets between MuJoCo steps: mujoco.rollout
    cannot, so the threads backend says so; the same core with every robot selected has the
    ``joint_target`` input too (no effect there) and rolls out."""
    from dynabrain.modules.mujoco.core import MujocoCore
    from dynabrain.orchestrator import World
    from dynabrain.orchestrator.kernel.core import SceneSpec

    model = ROOT.parent / "scenarios" / "models" / "earthquake.xml"
    world = World("w", core=MujocoCore("core", SceneSpec(model=str(model))))
    try:
        assert "core.joint_target" in world.signals
        with Batch(world, backend="threads", workers=1) as batch:
            assert batch.run(3, branches=2, record=["core.joint_q"]).ok
            world.make(["floor"])  # the robot is animated
            with pytest.raises(DynabrainError, match="animated"):
                batch.run(3, branches=2, record=["core.joint_q"])
    finally:
        world.close()
