"""The MJWarp physics (issue 25, item 2: `modules.mujoco.warp_batch`) on warp's CPU device, against MuJoCo's
C: a small model's worlds stepped together on warp stay within `warp_batch.TOLERANCE` of C, run to run
they are bit equal, a world that diverges fails alone, a lockstep batch of the two cubes with
``physics="mjwarp"`` follows the batch on C within the same tolerance, per-branch friction steps on
warp (a value per world), and a branch whose parameters warp cannot hold per world (gravity) steps on
C. Skipped, with warp's reason, where warp is not installed or cannot start or compile.

Warp compiles its kernels on first use (cold, on two cores: 18 s for the small model and 13 s more for
the two cubes, the file 37 s; then read from warp's kernel cache, `warp_batch.cache_dir`: the file runs
in about 10 s); the module's fixture pays it once."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from dynabrain.modules.mujoco import warp_batch
from dynabrain.orchestrator import Batch, DynabrainError, load_world
from dynabrain.orchestrator.brain.lockstep import LockstepBackend

ROOT = Path(__file__).resolve().parents[1]
WORLDS, STEPS = 3, 200
MODEL = """<mujoco><option timestep="0.002"/>
<worldbody>
  <geom type="plane" size="2 2 .1"/>
  <body name="box" pos="0 0 .3"><freejoint/><geom type="box" size=".05 .05 .05" mass="1"/></body>
  <body name="upper" pos="0.5 0 1">
    <joint name="shoulder" type="hinge" axis="0 1 0" damping="0.01"/>
    <geom type="capsule" fromto="0 0 0 0 0 -.4" size=".02"/>
    <body pos="0 0 -.4">
      <joint name="elbow" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -.3" size=".02"/>
    </body>
  </body>
</worldbody>
<actuator><motor joint="shoulder" gear="1"/></actuator>
</mujoco>"""
"""A box that falls onto the floor (contacts, the solver) and a double pendulum driven by a motor."""

pytestmark = pytest.mark.skipif(warp_batch.unavailable() is not None,
                                reason=f"MJWarp cannot run here: {warp_batch.unavailable()}")


def starts(model: mujoco.MjModel) -> list[mujoco.MjData]:
    """One data per world, each from its own start (drop height, pendulum swing)."""
    datas = []
    for k in range(WORLDS):
        d = mujoco.MjData(model)
        d.qpos[2] += 0.05 * k
        d.qvel[6] = 0.5 * k
        mujoco.mj_forward(model, d)
        datas.append(d)
    return datas


def control(step: int, world: int) -> float:
    return 0.2 * np.sin(0.05 * step + world)


def on_warp(worlds: warp_batch.WarpWorlds, model: mujoco.MjModel) -> list[mujoco.MjData]:
    datas = starts(model)
    for step in range(STEPS):
        for k, d in enumerate(datas):
            d.ctrl[0] = control(step, k)
        worlds.put(datas)
        worlds.step()
        worlds.take(datas)
    return datas


@pytest.fixture(scope="module")
def small():
    """The small model and its warp worlds, stepped once (warp compiles its kernels here)."""
    model = mujoco.MjModel.from_xml_string(MODEL)
    try:
        worlds = warp_batch.WarpWorlds(model, WORLDS)
        worlds.put(starts(model))
        worlds.step()
    except Exception as exc:  # warp starts but cannot compile or run its kernels here
        pytest.skip(f"MJWarp cannot compile or step on the CPU device here: {exc}")
    return model, worlds


def test_warp_follows_mujoco_c_within_the_tolerance(small):
    model, worlds = small
    warp = on_warp(worlds, model)
    c = starts(model)
    for step in range(STEPS):
        for k, d in enumerate(c):
            d.ctrl[0] = control(step, k)
            mujoco.mj_step(model, d)
    for k, (w, d) in enumerate(zip(warp, c, strict=True)):
        assert np.abs(w.qpos - d.qpos).max() <= warp_batch.TOLERANCE["qpos_m"], k
        assert np.abs(w.qvel - d.qvel).max() <= warp_batch.TOLERANCE["qvel_m_s"], k
        assert w.time == d.time, k
    assert 0.04 < warp[0].qpos[2] < 0.06  # the box came to rest on the floor (half its size up)


def test_warp_is_deterministic_run_to_run_on_the_cpu(small):
    model, worlds = small
    first, second = on_warp(worlds, model), on_warp(worlds, model)
    for a, b in zip(first, second, strict=True):
        assert a.qpos.tobytes() == b.qpos.tobytes() and a.qvel.tobytes() == b.qvel.tobytes()


def test_a_lockstep_batch_on_mjwarp_follows_the_batch_on_c(small, monkeypatch):
    """The two cubes (contacts between boxes and with the floor), three branches from two starts."""
    world = load_world(ROOT / "scenarios" / "two_cubes.yaml")
    try:
        first = world.export_state()
        world.tick(40)
        second = world.export_state()
        branch_starts = [first, second, first]
        record = ("core.aa.pos", "core.bb.pos")
        with Batch(world, backend="lockstep") as batch:
            on_c = batch.run(200, starts=branch_starts, record=record)
        before = warp_batch.STEPPED["warp"]
        with Batch(world, backend="lockstep", physics="mjwarp") as batch:
            on_warp_ = batch.run(200, starts=branch_starts, record=record)
        assert warp_batch.STEPPED["warp"] - before == 3 * 200  # every branch's every tick on warp
        assert not any("failed" in note for note in on_warp_.notes), on_warp_.notes
        for b in range(3):
            assert on_warp_.status[b].ok, on_warp_.status[b]
            for name in record:
                gap = np.abs(on_warp_.branch(name, b) - on_c.branch(name, b)).max()
                assert 0 < gap <= warp_batch.TOLERANCE["qpos_m"], (b, name, gap)
    finally:
        world.close()


def test_a_world_that_diverges_fails_alone(small):
    """A world thrown at an absurd speed is not finite after the step; its neighbours step as without it."""
    model, worlds = small
    datas = starts(model)
    datas[1].qvel[7] = 1e30
    worlds.put(datas)
    for _ in range(5):
        worlds.step()
    assert worlds.take(datas).tolist() == [True, False, True]
    alone = starts(model)
    worlds.put(alone)
    for _ in range(5):
        worlds.step()
    worlds.take(alone)
    assert datas[0].qpos.tobytes() == alone[0].qpos.tobytes()
    assert datas[2].qpos.tobytes() == alone[2].qpos.tobytes()


def on_both(world, monkeypatch, ticks: int, **request) -> tuple:
    """The same lockstep batch on C and on warp: (result on C, result on warp, world-ticks on warp, on C)."""
    with Batch(world, backend="lockstep") as batch:
        on_c = batch.run(ticks, **request)
    monkeypatch.setenv("DYNABRAIN_LOCKSTEP_PHYSICS", "mjwarp")
    before = dict(warp_batch.STEPPED)
    with Batch(world, backend="lockstep") as batch:
        on_warp_ = batch.run(ticks, **request)
    monkeypatch.delenv("DYNABRAIN_LOCKSTEP_PHYSICS")
    return (on_c, on_warp_, warp_batch.STEPPED["warp"] - before.get("warp", 0),
            warp_batch.STEPPED["c"] - before.get("c", 0))


def test_per_branch_friction_steps_on_warp_each_world_its_own(small, monkeypatch):
    """A parameter that writes model fields warp holds per world (friction: geom_friction): every branch on
    warp, each with its own value, within the tolerance of C (400 ticks: the cubes land and slide)."""
    world = load_world(ROOT / "scenarios" / "two_cubes.yaml")
    try:
        on_c, on_warp_, warp, c = on_both(world, monkeypatch, 400, branches=3,
                                          params={"core.friction": [0.8, 0.8, 0.3]}, record=("core.aa.pos",))
        assert (warp, c) == (1200, 0)
        ends = [on_c.branch("core.aa.pos", b)[-1] for b in range(3)]
        assert np.abs(ends[2] - ends[0]).max() > 1e-3  # the low friction changed where the cube ends
        for b in range(3):
            gap = np.abs(on_warp_.branch("core.aa.pos", b) - on_c.branch("core.aa.pos", b)).max()
            assert 0 < gap <= warp_batch.TOLERANCE["qpos_m"], (b, gap)
    finally:
        world.close()


def test_a_branch_whose_parameters_warp_cannot_hold_per_world_steps_on_c(small, monkeypatch):
    """Gravity is one of the model's options, which warp shares among its worlds: the branch with its own
    gravity steps on C, bit for bit as on the C batch; the others on warp."""
    world = load_world(ROOT / "scenarios" / "two_cubes.yaml")
    try:
        gravity = [(0.0, 0.0, -9.81), (0.0, 0.0, -9.81), (0.0, 0.0, -3.0)]
        on_c, on_warp_, warp, c = on_both(world, monkeypatch, 100, branches=3, params={"core.gravity": gravity},
                                          record=("core.aa.pos",))
        assert (warp, c) == (200, 100)
        gaps = [np.abs(on_warp_.branch("core.aa.pos", b) - on_c.branch("core.aa.pos", b)).max() for b in range(3)]
        assert 0 < gaps[0] <= warp_batch.TOLERANCE["qpos_m"] and 0 < gaps[1] <= warp_batch.TOLERANCE["qpos_m"]
        assert gaps[2] == 0, gaps
    finally:
        world.close()


def test_an_unknown_physics_is_refused_by_name():
    world = load_world(ROOT / "scenarios" / "two_cubes.yaml")
    try:
        with pytest.raises(DynabrainError, match=r"no physics 'bullet'.*mjwarp"):
            LockstepBackend(world, physics="bullet")
    finally:
        world.close()


def test_mjwarp_where_warp_cannot_run_is_refused_with_the_reason(monkeypatch):
    """The backend asks the physics whether it can run here (a fake answer: warp is installed here)."""
    world = load_world(ROOT / "scenarios" / "two_cubes.yaml")
    monkeypatch.setattr(warp_batch, "unavailable", lambda: "warp-lang is not installed")
    try:
        with pytest.raises(DynabrainError, match=r"physics 'mjwarp' cannot run here: warp-lang is not installed"):
            LockstepBackend(world, physics="mjwarp")
    finally:
        world.close()
