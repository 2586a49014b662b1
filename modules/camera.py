"""A camera: RGB and depth images of the scene, rendered offscreen at the module's rate.

Targets: one camera of the model (``targets: [eye]``). Rate: the module's period (``period: 100ms``);
between two frames the outputs hold the last images. The renderer is chosen at run time (EGL, then
OSMesa, see `modules.offscreen`); where none works the module refuses to load and says why.

Outputs:

- ``rgb`` (height, width, 3), unit 1: colours in 0..1, row 0 at the top of the image;
- ``depth`` (height, width), m: distance along the camera's axis to the nearest surface (the far
  clipping distance where nothing is hit);
- ``frames``: images rendered so far.

Images are bus signals, so history keeps them with every tick: 64 x 48 pixels are 12288 floats
(96 KiB) per saved state. Keep images small, or the history short, or the rate low.

The camera has no state of its own (its outputs are on the bus, so a rollback restores them); a
fork opens its own GL context at its first frame.
"""

from __future__ import annotations

import copy
from typing import Any

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.module import Module, Param, Port, SetupContext

from .mujoco.access import MujocoLink, fail
from .mujoco.offscreen import BACKENDS, RendererUnavailableError, open_gl


class Camera(Module):
    """RGB-D images from a camera of the model (see the module docstring)."""

    PARAMS = (
        Param("width", 64, doc="image width in pixels"),
        Param("height", 48, doc="image height in pixels"),
        Param("backend", "auto", doc=f"offscreen OpenGL backend: auto, {', '.join(BACKENDS)}"),
    )
    DEFAULT_PERIOD = "100ms"

    def __init__(self, name: str, **kwargs: Any):
        super().__init__(name, **kwargs)
        w, h = self.params["width"], self.params["height"]
        if not (0 < w <= 4096 and 0 < h <= 4096):
            raise fail(name, "params", f"image size {w} x {h} is out of range (1..4096)")
        self._gl: Any = None
        self._mjr: Any = None

    def outputs(self) -> list[Port]:
        w, h = self.params["width"], self.params["height"]
        return [Port("rgb", (h, w, 3), "1", "colours, 0..1"), Port("depth", (h, w), "m", "depth along the view axis"),
                Port("frames", (), "1", "images rendered")]

    def setup(self, ctx: SetupContext) -> None:
        if len(self.targets) != 1:
            raise fail(self.name, "targets", f"a camera takes one camera of the model: targets: [name], "
                       f"got {list(self.targets)}")
        self._link = MujocoLink(self.name, ctx.core)
        self._link.lookup("camera", self.targets[0])
        m = self._link.model
        w, h = self.params["width"], self.params["height"]
        if w > m.vis.global_.offwidth or h > m.vis.global_.offheight:
            raise fail(self.name, "params", f"image {w} x {h} is larger than the model's offscreen buffer "
                       f"{m.vis.global_.offwidth} x {m.vis.global_.offheight} (<visual><global offwidth=...>)")
        try:
            self.backend, self._gl = open_gl(w, h, self.params["backend"])
        except RendererUnavailableError as exc:
            raise fail(self.name, "params.backend", str(exc)) from None
        self._link.changed()
        self._resolve()

    def _resolve(self) -> None:
        """Scene, camera and GL resources for the core's current model."""
        m = self._link.model
        if self._gl is None:
            self.backend, self._gl = open_gl(self.params["width"], self.params["height"], self.params["backend"])
        with self._gl.as_current():
            self._free_mjr()
            self._mjr = mujoco.MjrContext(m, mujoco.mjtFontScale.mjFONTSCALE_100)
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._mjr)
        self._mjr.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._scene = mujoco.MjvScene(m, maxgeom=max(1000, 2 * m.ngeom))
        self._option = mujoco.MjvOption()
        self._cam = mujoco.MjvCamera()
        self._cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._cam.fixedcamid = self._link.lookup("camera", self.targets[0])
        w, h = self.params["width"], self.params["height"]
        self._rect = mujoco.MjrRect(0, 0, w, h)
        self._rgb8 = np.empty((h, w, 3), dtype=np.uint8)
        self._zbuf = np.empty((h, w), dtype=np.float32)
        extent = m.stat.extent
        near, far = np.float32(m.vis.map.znear * extent), np.float32(m.vis.map.zfar * extent)
        c = -(far + near) / (far - near)
        d = -(np.float32(2) * far * near) / (far - near)
        self._c, self._d = np.float32(-0.5) * c - np.float32(0.5), np.float32(-0.5) * d  # reversed-Z projection

    def start(self, t_ns: int) -> None:
        self.out["frames"][...] = 0
        self._render()

    def step(self, t_ns: int, dt_ns: int) -> None:
        self._render()

    def _render(self) -> None:
        if self._mjr is None or self._link.changed():
            self._resolve()
        link = self._link
        mujoco.mjv_updateScene(link.model, link.data, self._option, None, self._cam,
                               mujoco.mjtCatBit.mjCAT_ALL, self._scene)
        with self._gl.as_current():  # current only while rendering: the world may step in another thread
            mujoco.mjr_render(self._rect, self._scene, self._mjr)
            mujoco.mjr_readPixels(self._rgb8, self._zbuf, self._rect, self._mjr)
        self.out["rgb"][...] = self._rgb8[::-1] / 255.0
        self.out["depth"][...] = self._d / (self._zbuf[::-1].astype(np.float64) + self._c)
        self.out["frames"][...] += 1

    def _free_mjr(self) -> None:
        if self._mjr is not None:
            self._mjr.free()
            self._mjr = None

    def close(self) -> None:
        if self._gl is not None:
            try:
                with self._gl.as_current():
                    self._free_mjr()
            finally:
                self._gl.free()
                self._gl = None

    def fork(self, memo: dict) -> Camera:
        """A fork's camera: same configuration, the copied core, its own GL context (opened lazily)."""
        twin = copy.copy(self)
        memo[id(self)] = twin
        twin.bind_ports(None)
        twin._link = copy.deepcopy(self._link, memo)
        twin._gl, twin._mjr = None, None
        return twin
