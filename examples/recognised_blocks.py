"""The recognised blocks (the paper's Fig. 23): blocks seen by a stereo camera become bodies of the brain's world.

The scene (`scenarios/recognised_blocks.yaml`): three coloured blocks on a table under a head. The
brain:

1. gives the head its eyes: a stereo camera module (`modules.stereo`) added to the running world;
2. finds each block's top face in both eyes: the pixels of the block's colour (hue and saturation)
   that are lit as a face turned up is (the directional light and the headlight come from above: a
   block's sides are darker), the largest such region in each image;
3. from the stereo pair: the regions' centroids lie on the same row (the pair is rectified) and their
   column difference is the disparity, so the top face's depth is ``f * baseline / disparity``; the
   camera looks straight down, so every point of the top face is at that depth, and the face's pixels
   back-projected at it give the face in the world. Its smallest enclosing rectangle (OpenCV's
   ``minAreaRect``) gives the block's centre, length, width and heading; its height is how far the top
   is above the table (the brain's own model knows where its table is);
4. adds a box of that size, pose and colour to its own world while it runs (`World.add_body`: the
   paper's model acquisition) and simulates it: the blocks settle on the brain's table where they
   were seen.

The brain's world is its own, not the scene's: a floor and the table, built from primitives
(`brain_world`). The true blocks (``core.<colour>.pos``, the model's sizes) are read only to report the
estimates' errors.

    .venv/bin/python examples/recognised_blocks.py                          # what it saw and added
    .venv/bin/python examples/recognised_blocks.py --save runs/blocks.png   # the pair, regions marked

It needs an offscreen renderer (EGL or OSMesa); where none works it says why and stops.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.modules.mujoco.offscreen import RendererUnavailableError
from dynabrain.modules.stereo import Region, StereoCamera, largest_region, to_world, triangulate
from dynabrain.orchestrator import BodySpec, JointSpec, SceneSpec, World, load_world

SCENARIO = Path(__file__).resolve().parents[1] / "scenarios" / "recognised_blocks.yaml"
EYES = {"targets": ["head"], "width": 320, "height": 240, "baseline": 0.1, "num_disparities": 64}
"""The head's stereo camera: 320 x 240 eyes 10 cm apart, 0.7 m above the table (disparities of about
45 px)."""
EYES_PERIOD = "100ms"
TABLE_TOP_M = 0.4
"""Where the table's top is, in the brain's own model of the room (`brain_world`)."""
HUES = {"red": (170, 10), "green": (45, 75), "blue": (105, 130)}
"""The blocks' colours: OpenCV hue ranges (0..180; red wraps round 0)."""
MIN_SATURATION, MIN_VALUE, TOP_FACE = 120, 60, 0.8
"""A block's pixel is saturated (above 120 of 255) and not dark (above 60); its top face is the part as
bright as 0.8 of its brightest pixel (the sides face away from the light)."""
MIN_PIXELS = 30
DENSITY_KG_M3 = 600.0
"""The brain does not weigh what it sees: a block's mass is its volume times this (wood)."""
SQUARE_PX = 2.0
"""A face whose length and width differ by less than this (in pixels) is square: its heading is known
modulo 90 degrees, and is given within +-45."""


@dataclass(frozen=True)
class Block:
    """A block as the brain models it: ``size`` (length >= width, height; m), ``pos`` (its centre, m,
    world frame), ``yaw`` (rad, within +-90 degrees: a box turned by 180 degrees is the same box)."""

    colour: str
    size: tuple[float, float, float]
    pos: tuple[float, float, float]
    yaw: float

    @property
    def quat(self) -> tuple[float, float, float, float]:
        return (math.cos(self.yaw / 2), 0.0, 0.0, math.sin(self.yaw / 2))

    def spec(self) -> BodySpec:
        """The body `World.add_body` takes: a box of this size, pose and colour, 1 mm above where it was
        seen (it settles), of the mass its volume gives."""
        x, y, z = self.pos
        mass = DENSITY_KG_M3 * math.prod(self.size)
        return BodySpec(name=self.colour, shape="box", size=self.size, pos=(x, y, z + 0.001), quat=self.quat,
                        mass=mass, color=self.colour)


@dataclass(frozen=True)
class Sighting:
    """One block seen in both eyes: the regions, their disparity and row offset (px), and the block."""

    left: Region
    right: Region
    disparity_px: float
    row_offset_px: float
    block: Block


def top_face(rgb: np.ndarray, colour: str) -> np.ndarray:
    """The pixels of a block's top face of this colour (see `MIN_SATURATION`)."""
    hsv = cv2.cvtColor(np.round(rgb * 255).astype(np.uint8), cv2.COLOR_RGB2HSV)
    hue, sat, val = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    lo, hi = HUES[colour]
    in_hue = (hue >= lo) | (hue <= hi) if lo > hi else (hue >= lo) & (hue <= hi)
    mask = in_hue & (sat > MIN_SATURATION) & (val > MIN_VALUE)
    if mask.any():
        mask &= val >= TOP_FACE * val[mask].max()
    return mask


def estimate(colour: str, left: Region, disparity_px: float, world: World, eyes: str) -> Block:
    """The block whose top face is ``left`` (in the left eye) at this disparity (see the module
    docstring, step 3)."""
    g = world.get
    focal, center, baseline = float(g(f"{eyes}.focal")), g(f"{eyes}.center"), world.modules[eyes].baseline
    pos, rot = g(f"{eyes}.left.pos"), g(f"{eyes}.rot")
    v, u = np.nonzero(left.mask)
    face = to_world(triangulate(u + 0.5, v + 0.5, np.full(len(u), disparity_px), focal, center, baseline), pos, rot)
    (cx, cy), (a, b), angle = cv2.minAreaRect(face[:, :2].astype(np.float32))
    depth = focal * baseline / disparity_px
    pixel = depth / focal  # one pixel's footprint on the face (m)
    a, b = a + 0.5 * pixel, b + 0.5 * pixel  # pixel centres span half a pixel less than the face
    yaw = math.radians(angle)
    if a < b:
        a, b, yaw = b, a, yaw + math.pi / 2
    period = math.pi / 2 if a - b < SQUARE_PX * pixel else math.pi
    yaw = (yaw + period / 2) % period - period / 2
    top = float(np.mean(face[:, 2]))
    height = top - TABLE_TOP_M
    return Block(colour, (float(a), float(b), float(height)), (float(cx), float(cy), TABLE_TOP_M + height / 2), yaw)


def see(world: World, eyes: str = "eyes") -> list[Sighting]:
    """Every block of a known colour seen in both eyes, on the same rows (one object), estimated."""
    g = world.get
    seen = []
    for colour in HUES:
        left, right = (largest_region(top_face(g(f"{eyes}.{eye}.rgb"), colour)) for eye in ("left", "right"))
        if left is None or right is None or min(left.pixels, right.pixels) < MIN_PIXELS:
            continue
        rows = float(left.centroid[1] - right.centroid[1])
        disparity = float(left.centroid[0] - right.centroid[0])
        if abs(rows) > 1.0 or disparity <= 0:
            continue
        seen.append(Sighting(left, right, disparity, rows, estimate(colour, left, disparity, world, eyes)))
    return seen


def brain_world() -> World:
    """The brain's own world before it looks: a floor and its table (top at `TABLE_TOP_M`)."""
    table = BodySpec(name="table", shape="box", size=(1.0, 0.8, 0.04), pos=(0.0, 0.0, TABLE_TOP_M - 0.02),
                     joint=JointSpec(kind="fixed"), color="brown")
    floor = BodySpec(name="floor", shape="plane", size=(), color="grey")
    core = MujocoCore("core", SceneSpec(bodies=(floor, table)), friction=0.8)
    return World("brain", step="2ms", history=50, core=core)


@dataclass(frozen=True)
class Outcome:
    """What the brain saw, what it added, and where the added blocks rest after ``settled_s`` of its
    simulation (``rest``: colour -> position, m)."""

    sightings: list[Sighting]
    rest: dict[str, np.ndarray]
    settled_s: float


def acquire(scene: World, brain: World, *, settle_s: float = 1.0) -> Outcome:
    """Look at the scene and add what is seen to the running brain world, then simulate it."""
    scene.add_module(StereoCamera("eyes", **EYES), period=EYES_PERIOD)
    scene.tick(ticks(scene, 0.2))  # the eyes have taken a pair
    sightings = see(scene)
    brain.tick(ticks(brain, 0.1))  # the brain's world is running
    for s in sightings:
        brain.add_body(s.block.spec())
    brain.tick(ticks(brain, settle_s))
    return Outcome(sightings, {s.block.colour: brain.get(f"core.{s.block.colour}.pos") for s in sightings}, settle_s)


def truth(scene: World, colour: str) -> Block:
    """The scene's block of that colour, as the scene's model has it (for reporting errors only)."""
    q = scene.get(f"core.{colour}.quat")
    yaw = 2 * math.atan2(float(q[3]), float(q[0]))
    a, b, h = (2 * scene.core.mj.model.geom(colour).size).tolist()
    if a < b:
        a, b, yaw = b, a, yaw + math.pi / 2
    period = math.pi / 2 if abs(a - b) < 1e-9 else math.pi
    yaw = (yaw + period / 2) % period - period / 2
    return Block(colour, (a, b, h), tuple(scene.get(f"core.{colour}.pos").tolist()), yaw)


def ticks(world: World, seconds: float) -> int:
    return round(seconds / (world.dt_ns * 1e-9))


def save_view(scene: World, sightings: list[Sighting], path: Path) -> None:
    """The eyes' images side by side, each top face found outlined in white (the paper's Fig. 23, left)."""
    images = []
    for side in ("left", "right"):
        image = np.ascontiguousarray(np.round(scene.get(f"eyes.{side}.rgb") * 255).astype(np.uint8))
        for s in sightings:
            mask = getattr(s, side).mask.astype(np.uint8)
            contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            cv2.drawContours(image, contours, -1, (255, 255, 255), 1)
        images.append(image)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(np.hstack(images), cv2.COLOR_RGB2BGR))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--save", type=Path, help="a PNG of the eyes' images with the top faces found")
    args = parser.parse_args()
    scene, brain = load_world(SCENARIO), brain_world()
    try:
        try:
            out = acquire(scene, brain)
        except RendererUnavailableError as exc:
            sys.exit(f"no offscreen renderer here, the eyes cannot see: {exc}")
        if args.save is not None:
            save_view(scene, out.sightings, args.save)
        print(f"seen {len(out.sightings)} blocks; added to the brain's world and simulated {out.settled_s:g} s:")
        for s in out.sightings:
            b, t = s.block, truth(scene, s.block.colour)
            err = np.subtract(b.pos, t.pos) * 1000
            print(f"  {b.colour:>5}: {s.left.pixels} / {s.right.pixels} px, disparity {s.disparity_px:.2f} px "
                  f"(rows {s.row_offset_px:+.2f})")
            size, true_size = np.round(np.multiply(b.size, 1000), 1), np.round(np.multiply(t.size, 1000), 1)
            print(f"         size {size} mm (true {true_size}), centre off by {np.round(err, 1)} mm, "
                  f"heading {math.degrees(b.yaw):.1f} deg (true {math.degrees(t.yaw):.1f})")
            print(f"         rests in the brain's world at {np.round(out.rest[b.colour], 4)} m")
    finally:
        scene.close()
        brain.close()


if __name__ == "__main__":
    main()
