"""A stereo camera: two eyes a baseline apart, their images, and depth from the disparity between them.

Targets: one camera of the model, the head (``targets: [head]``). The two eyes sit either side of it,
``baseline / 2`` along the camera's x axis (its right), each looking the way the camera looks: the left
eye at ``-baseline / 2``, the right one at ``+baseline / 2``. Both render offscreen (see `modules.camera`:
EGL, then OSMesa; where none works the module refuses to load and says why) at the module's rate.

Rectification: MuJoCo renders both eyes through the same pinhole with exactly parallel axes, the right
eye shifted along the image rows. The pair is therefore already rectified (epipolar lines are the
image rows, at the same height in both images): the rectifying transform is the identity, and
``rectified`` holds the pair as the matcher takes it (grey, 0..1). A real head would be calibrated
and rectified here (OpenCV's ``stereoRectify``); a simulated one needs neither.

Disparity: OpenCV's semi-global block matcher (``cv2.StereoSGBM``, the field's standard; the package is
``opencv-python-headless``, wheels without GUI or GL libraries), run on the rectified pair, with
sub-pixel precision (1/16 px). A pixel of the left image at column ``u`` matched in
the right image at ``u - d`` has disparity ``d``; its depth along the axis is ``Z = f * baseline / d``,
with ``f`` the focal length in pixels. Pixels without a reliable match (no texture, occluded in the other
eye, the left band of ``num_disparities`` columns the right eye does not see) are 0 in ``disparity``
and ``depth`` (no disparity, no depth: the convention of depth images, REP 118), so every output
stays a finite number.

Outputs (h x w images, row 0 at the top; the camera frame is OpenCV's: x right, y down, z forward):

- ``left.rgb``, ``right.rgb`` (h, w, 3), unit 1: each eye's colours, 0..1;
- ``left.depth``, ``right.depth`` (h, w), m: each eye's rendered depth along its axis (ground truth);
- ``rectified`` (2, h, w), unit 1: the rectified pair, grey (left, then right);
- ``disparity`` (h, w), px: left-image disparity, 0 where unmatched;
- ``depth`` (h, w), m: depth from disparity, in the left eye's frame, 0 where unmatched;
- ``left.pos``, ``right.pos`` (3,), m: where the eyes are, in the world frame, when the images were taken;
- ``rot`` (3, 3), unit 1: the eyes' orientation (columns: camera x, y, z in the world frame);
- ``focal`` (), px and ``center`` (2,), px: the pinhole (focal length; principal point u, v, with
  pixel (row i, column j) centred at (j + 0.5, i + 0.5));
- ``frames``: image pairs taken so far.

`triangulate` turns pixels and their disparities into points, `to_world` into the world frame.

Images are bus signals, kept by history at every tick: a 160 x 120 pair is about 0.25 M floats (2 MiB)
per saved state. Keep them small, the history short (``world: {history: 20}``), or the rate low.
The module has no state of its own; a fork opens its own GL context at its first frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.module import Param, Port, SetupContext

from .camera import Camera
from .mujoco.access import fail

MAX_BASELINE_M = 10.0


class StereoError(DynabrainError):
    """A stereo call given something it cannot use; the message names the call and the field."""


def check_baseline(baseline: Any, where: str) -> float:
    """The baseline in metres, or a `StereoError` naming ``where`` (the call or module and field)."""
    if isinstance(baseline, bool) or not isinstance(baseline, (int, float)) or not math.isfinite(baseline):
        raise StereoError(f"{where}: expected a distance in metres, got {baseline!r}")
    if baseline <= 0:
        raise StereoError(f"{where}: a baseline of {baseline!r} m puts the eyes on top of each other (or swaps "
                          "them), and depth cannot come from disparity; give the distance between the eyes, "
                          "above 0 (60mm, 0.1)")
    if baseline > MAX_BASELINE_M:
        raise StereoError(f"{where}: a baseline of {baseline!r} m is beyond {MAX_BASELINE_M:g} m")
    return float(baseline)


def match(left: np.ndarray, right: np.ndarray, num_disparities: int = 64, block_size: int = 5) -> np.ndarray:
    """Disparity (px, float64, 0 where unmatched) of a rectified pair of grey uint8 images, by OpenCV's
    semi-global block matcher (see the module docstring)."""
    raw = _matcher(num_disparities, block_size).compute(left, right)
    return np.where(raw > 0, raw / 16.0, 0.0)  # OpenCV marks "no match" below the least disparity (0)


def _matcher(num_disparities: int, block_size: int) -> Any:
    channels = 1
    return cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=num_disparities, blockSize=block_size,
        P1=8 * channels * block_size ** 2, P2=32 * channels * block_size ** 2,
        disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=50, speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)


def triangulate(u: Any, v: Any, disparity: Any, focal: float, center: Any, baseline: float) -> np.ndarray:
    """Points (..., 3) in the left eye's frame (x right, y down, z forward; m) of pixel coordinates ``u``
    (column, px) and ``v`` (row, px) of the left image with their ``disparity`` (px); NaN where the
    disparity is not above 0. ``focal`` (px), ``center`` (u, v px) and ``baseline`` (m) describe the pair."""
    b = check_baseline(baseline, "triangulate [baseline]")
    if not (isinstance(focal, (int, float, np.floating)) and math.isfinite(focal) and focal > 0):
        raise StereoError(f"triangulate [focal]: expected a focal length above 0 px, got {focal!r}")
    c = np.asarray(center, dtype=np.float64)
    if c.shape != (2,):
        raise StereoError(f"triangulate [center]: expected (u, v) in px, got shape {c.shape}")
    u, v, d = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (u, v, disparity)))
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(d > 0, focal * b / d, np.nan)
    return np.stack([(u - c[0]) * z / focal, (v - c[1]) * z / focal, z], axis=-1)


@dataclass(frozen=True)
class Region:
    """A colour region in one eye: its pixels and centroid (u, v in px, pixel centres at +0.5)."""

    mask: np.ndarray
    centroid: np.ndarray
    pixels: int


def largest_region(mask: np.ndarray) -> Region | None:
    """The largest connected region of a mask (8-connected, OpenCV), or None when there is none."""
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if count < 2:
        return None
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return Region(labels == best, centroids[best] + 0.5, int(stats[best, cv2.CC_STAT_AREA]))


def to_world(points: np.ndarray, pos: Any, rot: Any) -> np.ndarray:
    """Points (..., 3) in an eye's frame to the world frame, given the eye's ``pos`` and ``rot`` outputs."""
    return np.asarray(points) @ np.asarray(rot).T + np.asarray(pos)


class StereoCamera(Camera):
    """Two eyes a baseline apart on a camera of the model, and depth from their disparity (see the
    module docstring)."""

    PARAMS = (
        *Camera.PARAMS,
        Param("baseline", 0.1, unit="m", dimension="length", doc="distance between the eyes (above 0)"),
        Param("num_disparities", 64, unit="px", doc="disparities searched, 0 .. this (a multiple of 16)"),
        Param("block_size", 5, unit="px", doc="matched block size (odd, 1 .. 11)"),
    )

    def __init__(self, name: str, **kwargs: Any):
        super().__init__(name, **kwargs)
        p = self.params
        self.baseline = check_baseline(p["baseline"], f"module {name!r} [params.baseline]")
        nd, bs = p["num_disparities"], p["block_size"]
        if not (16 <= nd <= 256 and nd % 16 == 0):
            raise fail(name, "params.num_disparities", f"{nd} is not a multiple of 16 within 16..256")
        if nd >= p["width"]:
            raise fail(name, "params.num_disparities", f"{nd} disparities leave nothing of a {p['width']} px wide "
                       "image to match (the left band of that width is unseen by the right eye)")
        if not (1 <= bs <= 11 and bs % 2 == 1):
            raise fail(name, "params.block_size", f"{bs} is not odd within 1..11")

    def outputs(self) -> list[Port]:
        w, h = self.params["width"], self.params["height"]
        return [Port("left.rgb", (h, w, 3), "1", "left eye's colours, 0..1"),
                Port("left.depth", (h, w), "m", "left eye's rendered depth along its axis"),
                Port("right.rgb", (h, w, 3), "1", "right eye's colours, 0..1"),
                Port("right.depth", (h, w), "m", "right eye's rendered depth along its axis"),
                Port("rectified", (2, h, w), "1", "the rectified pair, grey, left then right"),
                Port("disparity", (h, w), "px", "left-image disparity, 0 where unmatched"),
                Port("depth", (h, w), "m", "depth from disparity in the left eye's frame, 0 where unmatched"),
                Port("left.pos", (3,), "m", "left eye's position, world frame"),
                Port("right.pos", (3,), "m", "right eye's position, world frame"),
                Port("rot", (3, 3), "1", "the eyes' axes x right, y down, z forward (columns), world frame"),
                Port("focal", (), "px", "focal length"),
                Port("center", (2,), "px", "principal point (u, v)"),
                Port("frames", (), "1", "image pairs taken")]

    def setup(self, ctx: SetupContext) -> None:
        super().setup(ctx)
        m = self._link.model
        cam = self._link.lookup("camera", self.targets[0])
        if float(np.max(m.cam_sensorsize[cam])) > 0:
            raise fail(self.name, "targets", f"camera {self.targets[0]!r} has a sensor size (intrinsics); "
                       "the stereo camera takes a camera with a vertical field of view (fovy) only")
        if int(m.cam_projection[cam]) != int(mujoco.mjtProjection.mjPROJ_PERSPECTIVE):
            raise fail(self.name, "targets", f"camera {self.targets[0]!r} is orthographic; stereo needs a pinhole")

    def _resolve(self) -> None:
        super()._resolve()
        m = self._link.model
        h, w = self.params["height"], self.params["width"]
        fovy = math.radians(float(m.cam_fovy[self._cam.fixedcamid]))
        self._focal = (h / 2.0) / math.tan(fovy / 2.0)
        self._center = np.array([w / 2.0, h / 2.0])
        self._sgbm = _matcher(self.params["num_disparities"], self.params["block_size"])
        self._grey = [np.empty((h, w), dtype=np.uint8), np.empty((h, w), dtype=np.uint8)]

    def _render(self) -> None:
        if self._mjr is None or self._link.changed():
            self._resolve()
        link, out = self._link, self.out
        cid = self._cam.fixedcamid
        mujoco.mjv_updateScene(link.model, link.data, self._option, None, self._cam,
                               mujoco.mjtCatBit.mjCAT_ALL, self._scene)
        center = np.array(link.data.cam_xpos[cid])
        axes = np.array(link.data.cam_xmat[cid]).reshape(3, 3)  # columns: right, up, backward
        right = axes[:, 0]
        half = 0.5 * self.baseline
        for side, offset, grey in (("left", -half, self._grey[0]), ("right", half, self._grey[1])):
            eye = center + offset * right
            for gl_cam in self._scene.camera:  # both GL cameras at this eye: mjr_render draws their average
                gl_cam.pos[:] = eye
                gl_cam.frustum_center = 0.0
            with self._gl.as_current():
                mujoco.mjr_render(self._rect, self._scene, self._mjr)
                mujoco.mjr_readPixels(self._rgb8, self._zbuf, self._rect, self._mjr)
            rgb8 = self._rgb8[::-1]
            out[f"{side}.rgb"][...] = rgb8 / 255.0
            out[f"{side}.depth"][...] = self._d / (self._zbuf[::-1].astype(np.float64) + self._c)
            cv2.cvtColor(np.ascontiguousarray(rgb8), cv2.COLOR_RGB2GRAY, dst=grey)
            out[f"{side}.pos"][...] = eye
        out["rectified"][0] = self._grey[0] / 255.0
        out["rectified"][1] = self._grey[1] / 255.0
        raw = self._sgbm.compute(self._grey[0], self._grey[1])
        matched = raw > 0
        disparity = np.where(matched, raw / 16.0, 0.0)
        out["disparity"][...] = disparity
        out["depth"][...] = np.divide(self._focal * self.baseline, disparity, out=np.zeros_like(disparity),
                                      where=matched)
        out["rot"][...] = axes * np.array([1.0, -1.0, -1.0])  # x right, y down, z forward
        out["focal"][...] = self._focal
        out["center"][...] = self._center
        out["frames"][...] += 1
