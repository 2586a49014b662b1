"""The camera renders real images offscreen: the colour of what it looks at, the metric depth of a wall
at a known distance, images that follow the scene, a fork that renders the same. Skipped, with the
reason, where no offscreen renderer (EGL or OSMesa) works."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dynabrain.modules.camera import Camera
from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.modules.mujoco.offscreen import RendererUnavailableError, open_gl
from dynabrain.orchestrator.kernel.checks import check_module
from dynabrain.orchestrator.kernel.core import SceneSpec
from dynabrain.orchestrator.kernel.world import World

MODELS = Path(__file__).resolve().parent.parent / "scenarios" / "models"
ROOM = """<mujoco>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1" directional="true"/>
    <geom name="wall" type="box" size="0.05 2 2" pos="1.55 0 1" rgba="0.9 0.1 0.1 1"/>
    <camera name="cam" pos="0 0 1" xyaxes="0 -1 0 0 0 1" fovy="60"/>
    <body name="ball" pos="0 3 1"><freejoint/><geom type="sphere" size="0.15" rgba="0.1 0.1 0.9 1"/></body>
  </worldbody>
</mujoco>"""


def _renderer() -> str | None:
    try:
        _backend, gl = open_gl(8, 8)
        gl.free()
        return None
    except RendererUnavailableError as exc:
        return str(exc)


pytestmark = pytest.mark.skipif(_renderer() is not None, reason=f"{_renderer()}")


@pytest.fixture()
def room(tmp_path) -> World:
    path = tmp_path / "room.xml"
    path.write_text(ROOM)
    core = MujocoCore("core", SceneSpec(model=str(path)), gravity=[0, 0, 0])
    world = World("room", step="2ms", history=20, core=core)
    world.add_module(Camera("cam", targets=["cam"], width=41, height=31), period="10ms")  # odd: a pixel on the axis
    yield world
    world.close()


def test_colour_and_metric_depth_of_a_wall(room):
    room.tick(5)
    rgb, depth = room.get("cam.rgb"), room.get("cam.depth")
    assert rgb.shape == (31, 41, 3) and depth.shape == (31, 41)
    red, green, blue = rgb[15, 20]
    assert red > 0.5 and green < 0.3 and blue < 0.3
    assert depth[15, 20] == pytest.approx(1.5, abs=1e-4)  # the wall's face, on the optical axis
    assert np.allclose(depth, 1.5, atol=1e-4)  # a flat wall facing the camera: same depth along the axis
    assert room.get("cam.frames") == 2  # at start, then every 10 ms


def test_images_follow_the_scene_and_a_fork_renders_the_same(room):
    room.tick(5)
    before = room.get("cam.rgb")
    room.place("ball", [0.8, 0.0, 1.0])  # into the middle of the view
    room.tick(5)
    after, depth = room.get("cam.rgb"), room.get("cam.depth")
    assert after[15, 20, 2] > 0.5 and not np.array_equal(before, after)
    assert depth[15, 20] == pytest.approx(0.65, abs=2e-3)  # the ball's front, 0.8 - 0.15 m away, drawn as facets
    fork = room.fork()
    fork.tick(5)
    room.tick(5)
    assert np.array_equal(fork.get("cam.rgb"), room.get("cam.rgb"))
    assert np.array_equal(fork.get("cam.depth"), room.get("cam.depth"))
    fork.close()


def test_the_humanoid_sees_from_its_head_and_the_camera_passes_check_module():
    core = MujocoCore("core", SceneSpec(model=str(MODELS / "humanoid.xml")))
    report = check_module(Camera("eye", targets=["eye"], width=16, height=12), core=core, period="10ms", ticks=10)
    report.assert_ok()


def test_the_camera_renders_while_the_world_runs_in_its_thread(room):
    room.start(until=0.2)
    assert room.wait(30)
    room.stop()
    assert room.get("cam.frames") == 21 and room.get("cam.depth")[15, 20] == pytest.approx(1.5, abs=1e-4)
