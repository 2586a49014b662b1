"""The batch on a real local Ray: the same branches as the serial backend, bit for bit; a worker that
crashes fails its branch and is replaced; a cluster that cannot be reached is a clear error."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_batch import same_state
from test_fmu_isolation import crashy_folder

from dynabrain.orchestrator import Batch, load_world

ray = pytest.importorskip("ray")

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.usefixtures("fmu_cache")


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False,
             _node_ip_address="127.0.0.1")
    yield
    ray.shutdown()


def test_ray_branches_equal_the_serial_ones(local_ray):
    world = load_world(ROOT / "scenarios" / "humanoid_stand.yaml")
    try:
        world.tick(20)
        request = dict(branches=3, params={"core.friction": [0.5, 0.8, 1.1]},
                       record=["core.pelvis.pos", "zmp.zmp"])
        with Batch(world, backend="serial") as batch:
            serial = batch.run(30, **request)
        with Batch(world, backend="ray", workers=2) as batch:
            remote = batch.run(30, **request)
        assert remote.ok and remote.backend == "ray"
        for name in request["record"]:
            assert serial.signals[name].tobytes() == remote.signals[name].tobytes()
        assert [same_state(a, b) for a, b in zip(serial.states, remote.states, strict=True)] == [True] * 3
    finally:
        world.close()


def test_a_crashing_ray_worker_fails_its_branch_and_is_replaced(local_ray, tmp_path):
    src = crashy_folder(tmp_path)
    scenario = tmp_path / "crashy.yaml"
    scenario.write_text(f"name: crashy\nworld: {{step: 1ms, duration: 1s, core: null}}\n"
                        f"modules:\n  - {{name: c, fmu: {src.name}, params: {{how: 0}}}}\n")
    world = load_world(scenario)
    try:
        u = np.zeros((3, 10, *np.shape(world.get("c.u"))))
        u[0, 5:] = 1.0
        with Batch(world, backend="ray", workers=2) as batch:
            result = batch.run(10, branches=3, inputs={"c.u": u}, record=["c.y"])
            assert [s.ok for s in result.status] == [False, True, True]
            assert "branch 0 died" in result.status[0].reason
            assert batch._pool.replaced == 1
            assert batch.run(3, branches=2).ok
    finally:
        world.close()


def test_an_unreachable_cluster_names_its_address():
    code = ("from dynabrain.orchestrator import Batch, load_world\n"
            f"w = load_world({str(ROOT / 'scenarios' / 'two_cubes.yaml')!r})\n"
            "Batch(w, backend='ray', address='127.0.0.1:9').run(2, branches=1)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode != 0
    assert "cannot reach the Ray cluster at '127.0.0.1:9'" in done.stderr
