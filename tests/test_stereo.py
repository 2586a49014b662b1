"""The stereo camera (modules/stereo.py): two eyes a baseline apart whose pair is rectified as rendered
(a point lies on the same row in both), depth from OpenCV's disparity that agrees with the rendered
depth, the drawer's knob triangulated by the humanoid's head to within a few millimetres and the drawer
pulled open by the humanoid that saw it (examples/drawer.py). A baseline of zero is refused, naming the
module or call and the field. The matcher and the triangulation are checked on synthetic images everywhere; rendering is
skipped, with the reason, where no offscreen renderer (EGL or OSMesa) works."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.modules.mujoco.offscreen import RendererUnavailableError, open_gl
from dynabrain.modules.stereo import StereoCamera, StereoError, match, to_world, triangulate
from dynabrain.orchestrator import load_world
from dynabrain.orchestrator.kernel.checks import check_module
from dynabrain.orchestrator.kernel.core import SceneSpec
from dynabrain.orchestrator.kernel.errors import DynabrainError, ScenarioError

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
import drawer  # noqa: E402


def _renderer() -> str | None:
    try:
        _backend, gl = open_gl(8, 8)
        gl.free()
        return None
    except RendererUnavailableError as exc:
        return str(exc)


needs_renderer = pytest.mark.skipif(_renderer() is not None, reason=f"{_renderer()}")


# -- without a renderer ---------------------------------------------------------------------------------
def test_the_matcher_finds_a_known_shift_of_a_random_texture():
    rng = np.random.default_rng(3)
    texture = (rng.random((60, 140)) * 255).astype(np.uint8)
    shift = 9
    left, right = texture[:, shift:shift + 120].copy(), texture[:, :120].copy()  # right sees it 9 px to the left
    d = match(np.ascontiguousarray(right), np.ascontiguousarray(left), num_disparities=32, block_size=5)
    inner = d[8:-8, 40:-8]
    assert np.median(inner) == pytest.approx(shift, abs=1 / 16)
    assert np.mean(np.abs(inner - shift) < 0.5) > 0.95
    assert np.all(d[:, :30] == 0)  # the band the other eye does not see: unmatched, 0


def test_triangulation_inverts_the_pinhole():
    focal, center, baseline = 150.0, np.array([80.0, 60.0]), 0.1
    points = np.array([[0.05, -0.02, 0.6], [-0.2, 0.1, 1.3], [0.0, 0.0, 0.4]])
    u = center[0] + focal * points[:, 0] / points[:, 2]
    v = center[1] + focal * points[:, 1] / points[:, 2]
    d = focal * baseline / points[:, 2]
    assert np.allclose(triangulate(u, v, d, focal, center, baseline), points)
    assert np.all(np.isnan(triangulate(10.0, 10.0, 0.0, focal, center, baseline)))  # unmatched: no point
    rot, pos = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float), np.array([1.0, 2.0, 3.0])
    assert np.allclose(to_world([0, 0, 2.0], pos, rot), [3.0, 2.0, 3.0])  # forward is the third column


def test_a_baseline_of_zero_is_refused_naming_the_call_and_the_field(tmp_path):
    with pytest.raises(StereoError, match=r"triangulate \[baseline\]: a baseline of 0"):
        triangulate(1.0, 1.0, 2.0, 150.0, [80, 60], 0.0)
    with pytest.raises(StereoError, match=r"module 'eyes' \[params.baseline\]: a baseline of 0.0 m"):
        StereoCamera("eyes", targets=["head"], baseline=0)
    with pytest.raises(StereoError, match=r"\[params.baseline\]: a baseline of -0.05 m"):
        StereoCamera("eyes", targets=["head"], baseline="-50mm")
    with pytest.raises(DynabrainError, match=r"\[params.num_disparities\]"):
        StereoCamera("eyes", targets=["head"], num_disparities=20)
    scenario = tmp_path / "zero.yaml"
    scenario.write_text(
        "name: zero\nworld: {step: 2ms, duration: 0.1s, core: mujoco}\n"
        f"scene: {{model: {ROOT / 'scenarios' / 'models' / 'drawer.xml'}}}\n"
        "modules:\n"
        "  - {name: eyes, python: dynabrain.modules.stereo:StereoCamera, targets: [eye],\n"
        "     params: {baseline: 0mm}}\n")
    with pytest.raises(ScenarioError) as err:
        load_world(scenario)
    assert "zero.yaml:6" in str(err.value) and "module 'eyes' [params.baseline]" in str(err.value)


# -- rendered ---------------------------------------------------------------------------------------------
@pytest.fixture()
def seen():
    """The kid in its crouch, its head turned to the cabinet and looking down at it (its pose at 0.5 s)."""
    world = load_world(drawer.SCENARIO)
    world.add_module(StereoCamera("eyes", **drawer.EYES), period=drawer.EYES_PERIOD)
    world.tick(255)
    yield world
    world.close()


@needs_renderer
def test_the_pair_is_rectified_and_depth_from_disparity_agrees_with_the_rendered_depth(seen):
    g = seen.get
    baseline = drawer.EYES["baseline"]
    assert np.linalg.norm(g("eyes.right.pos") - g("eyes.left.pos")) == pytest.approx(baseline, abs=1e-6)
    rot = g("eyes.rot")
    assert np.allclose(rot.T @ rot, np.eye(3), atol=1e-6)
    assert np.dot(g("eyes.right.pos") - g("eyes.left.pos"), rot[:, 0]) == pytest.approx(baseline, abs=1e-6)
    assert np.array_equal(g("eyes.rectified")[0], np.round(g("eyes.rectified")[0] * 255) / 255)
    sighting = drawer.look(seen)
    assert sighting is not None
    assert abs(sighting.row_offset_px) < 0.25  # rectified: the knob on the same rows in both eyes
    depth, rendered = g("eyes.depth"), g("eyes.left.depth")
    matched = depth > 0
    assert matched.mean() > 0.4
    error = np.abs(depth - rendered)[matched & (rendered < 2.0)]
    assert np.median(error) < 0.03  # the scene's wood and floor are textured; edges and shadows miss
    # on the knob: one pixel of disparity is 6 mm of depth at 0.3 m; the matcher's 5 px blocks reach past
    # the knob's edge to the drawer behind it, so the knob's inside (the region less its rim) is compared
    inside = cv2.erode(sighting.left.mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & matched
    assert inside.sum() > 20 and np.median(np.abs(depth - rendered)[inside]) < 0.015


@needs_renderer
def test_the_humanoid_finds_the_knob_within_a_few_millimetres_and_pulls_the_drawer_open():
    world = load_world(drawer.SCENARIO)
    try:
        out = drawer.run(world)
    finally:
        world.close()
    assert out.sighting is not None
    assert abs(out.sighting.row_offset_px) < 0.25  # the same rows in both eyes
    assert out.sighting_error_m < 3e-3, out.sighting.position  # 1.2 mm at 0.3 m, 52 px of disparity
    assert out.reached and out.gripped and out.grip_gap_m < 3e-3 and out.opened_m >= 0.15
    b = out.balance
    assert not b.left_polygon and b.min_margin_m > 0.01 and b.feet_slip_m < 1e-3 and b.min_pelvis_z_m > 0.27


@needs_renderer
def test_a_fork_sees_the_same_and_the_module_passes_check_module(seen):
    fork = seen.fork()
    try:
        fork.tick(100)
        seen.tick(100)
        for port in ("left.rgb", "right.rgb", "disparity", "depth"):
            assert np.array_equal(fork.get(f"eyes.{port}"), seen.get(f"eyes.{port}"))
    finally:
        fork.close()
    core = MujocoCore("core", SceneSpec(model=str(ROOT / "scenarios" / "models" / "drawer.xml")))
    eyes = StereoCamera("eyes", targets=["eye"], width=48, height=36, num_disparities=16)
    check_module(eyes, core=core, period="10ms", ticks=6).assert_ok()
