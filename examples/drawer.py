"""The drawer found by stereo vision (the paper's Fig. 21): see the knob, reach it, pull the drawer open.

The scene (`scenarios/drawer.yaml`): a cabinet with a drawer on a slider and a red knob, an arm of four
servoed hinges with a fork for a hand, a head on a mast. The brain:

1. gives the head its eyes: a stereo camera module (`modules.stereo`) added to the running world;
2. extracts the knob's colour region in both eyes (red: the largest such blob in each image), checks
   that both lie on the same rows (the pair is rectified), and triangulates the regions' centroids from
   their disparity; the dense depth from disparity over the region gives the knob's visible face;
3. plans the reach with inverse kinematics (`modules.ik`, mink): the fork over the knob, pointing down,
   then lowered over the knob's stem behind its disc, then drawn back along the slider's axis, each
   pose solved from the one before;
4. plays the poses as one motion program of the servo and watches the drawer open; at the end it looks
   again and triangulates where the knob has gone.

    .venv/bin/python examples/drawer.py                        # prints what it saw, planned and did
    .venv/bin/python examples/drawer.py --save runs/drawer.png # the eyes' images and the colour regions
    .venv/bin/python examples/drawer.py --no-vision            # no renderer here: the knob where the
                                                               # scene's drawing puts it, IK and the pull

The knob's true position (``core.knob.pos``) is read only to report the triangulation's error.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dynabrain.modules.ik import IkResult, InverseKinematics, Target
from dynabrain.modules.stereo import Region, StereoCamera, largest_region, to_world, triangulate
from dynabrain.orchestrator import World, load_world

SCENARIO = Path(__file__).resolve().parents[1] / "scenarios" / "drawer.yaml"
EYES = {"targets": ["head"], "width": 160, "height": 120, "baseline": 0.1, "num_disparities": 48}
"""The head's stereo camera: 160 x 120 eyes 10 cm apart (the knob is about 40 cm from the robot)."""
EYES_PERIOD = "500ms"
KNOB_DRAWN = np.array([0.38, 0.0, 0.38])
"""Where the scene's drawing puts the knob (models/drawer.xml); used only with --no-vision."""
BEHIND_M = 0.03
"""The fork goes down this far behind the knob's centre: between its disc (7.5 mm thick) and the drawer."""
ABOVE_M = 0.08
"""The fork's tip first comes this far above the knob's centre, clear of the disc (30 mm radius)."""
BELOW_M = 0.01
"""Lowered, the tip is this far below the knob's centre: the fingers straddle the stem, behind the disc."""
PULL_M = 0.2
PULL_STEPS = 4
DOWN = {"axis": [0, 0, 1], "direction": [0, 0, -1]}
"""The fingers point down (the tip site's z along them), whatever the arm's heading."""
DURATIONS_S = {"over": 1.0, "lower": 0.6, "pull": 0.5}
SETTLE_S = 0.6


@dataclass(frozen=True)
class Sighting:
    """The knob as the eyes see it: the regions, their disparity (px), the triangulated centre and the
    visible face (median of the region's points from the dense depth), both in the world frame (m)."""

    left: Region
    right: Region
    disparity_px: float
    row_offset_px: float
    position: np.ndarray
    face: np.ndarray


@dataclass(frozen=True)
class Outcome:
    """What the brain did: what it saw before and after, the poses it solved, how far the drawer came."""

    sighting: Sighting | None
    knob_true: np.ndarray
    poses: list[IkResult]
    opened_m: float
    seen_after: Sighting | None

    @property
    def reached(self) -> bool:
        return bool(self.poses) and all(p.reached for p in self.poses)

    @property
    def triangulation_error_m(self) -> float:
        return float("nan") if self.sighting is None else float(np.linalg.norm(self.sighting.position
                                                                                - self.knob_true))


def red(rgb: np.ndarray) -> np.ndarray:
    """The knob's colour: clearly red (the cabinet's wood is orange-brown, its red over green 1.3)."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return (r > 0.3) & (r > 2.5 * g) & (r > 2.5 * b)


def look(world: World, eyes: str = "eyes", min_pixels: int = 6) -> Sighting | None:
    """Find the knob in the eyes' last images and triangulate it; None when it is not seen in both, or
    the two regions are not on the same rows (not one object)."""
    g = world.get
    left, right = largest_region(red(g(f"{eyes}.left.rgb"))), largest_region(red(g(f"{eyes}.right.rgb")))
    if left is None or right is None or min(left.pixels, right.pixels) < min_pixels:
        return None
    rows = float(left.centroid[1] - right.centroid[1])
    disparity = float(left.centroid[0] - right.centroid[0])
    if abs(rows) > 1.0 or disparity <= 0:
        return None
    focal, center, baseline = float(g(f"{eyes}.focal")), g(f"{eyes}.center"), world.modules[eyes].baseline
    pos, rot = g(f"{eyes}.left.pos"), g(f"{eyes}.rot")
    centre = to_world(triangulate(left.centroid[0], left.centroid[1], disparity, focal, center, baseline), pos, rot)
    v, u = np.nonzero(left.mask)
    points = to_world(triangulate(u + 0.5, v + 0.5, g(f"{eyes}.disparity")[v, u], focal, center, baseline), pos, rot)
    points = points[np.all(np.isfinite(points), axis=1)]
    face = np.median(points, axis=0) if len(points) else np.full(3, np.nan)
    return Sighting(left, right, disparity, rows, centre, face)


def plan(ik: InverseKinematics, knob: np.ndarray, pull_m: float = PULL_M) -> list[IkResult]:
    """The poses that hook the knob and draw it back ``pull_m`` along -x (the slider's axis), each solved
    from the one before."""
    tip = np.asarray(knob, dtype=float) + np.array([BEHIND_M, 0.0, 0.0])
    waypoints = [tip + np.array([0.0, 0.0, ABOVE_M]), tip - np.array([0.0, 0.0, BELOW_M])]
    waypoints += [tip - np.array([pull_m * (i + 1) / PULL_STEPS, 0.0, BELOW_M]) for i in range(PULL_STEPS)]
    poses: list[IkResult] = []
    for point in waypoints:
        start = None if not poses else poses[-1].q
        poses.append(ik.solve(Target("tip", pos=point, **DOWN), start=start))
    return poses


def program(poses: list[IkResult]) -> list[dict]:
    """The servo's motion program: over the knob, lowered, then the pull in steps."""
    durations = [DURATIONS_S["over"], DURATIONS_S["lower"]] + [DURATIONS_S["pull"]] * (len(poses) - 2)
    return [p.step(d) for p, d in zip(poses, durations, strict=True)]


def ticks(world: World, seconds: float) -> int:
    return round(seconds / (world.dt_ns * 1e-9))


def run(world: World, *, vision: bool = True, pull_m: float = PULL_M, save: Path | None = None) -> Outcome:
    """The whole task on a world built from the scenario (see the module docstring); ``save``: a PNG of
    what the eyes saw first."""
    sighting = None
    if vision:
        world.add_module(StereoCamera("eyes", **EYES), period=EYES_PERIOD)
    world.tick(ticks(world, 0.2))  # the arm settles; the eyes have taken their first pair
    knob_true = np.array(world.get("core.knob.pos"))
    if vision:
        sighting = look(world)
        if save is not None:
            save_view(world, save)
        if sighting is None:
            return Outcome(None, knob_true, [], float(world.get("core.drawer_slide.q")), None)
        knob = sighting.position
    else:
        knob = KNOB_DRAWN
    ik = InverseKinematics.for_servo(world, "servo")
    poses = plan(ik, knob, pull_m)
    if not all(p.reached for p in poses):
        return Outcome(sighting, knob_true, poses, float(world.get("core.drawer_slide.q")), None)
    steps = program(poses)
    world.set("servo.sequence", steps)
    world.tick(ticks(world, sum(float(s["duration"][:-1]) for s in steps) + SETTLE_S))
    seen_after = look(world) if vision else None
    return Outcome(sighting, knob_true, poses, float(world.get("core.drawer_slide.q")), seen_after)


def save_view(world: World, path: Path) -> None:
    """The eyes' images side by side, the colour regions below them (the paper's Fig. 21, upper right)."""
    left, right = world.get("eyes.left.rgb"), world.get("eyes.right.rgb")
    masks = [np.repeat(red(img)[..., None], 3, axis=2).astype(float) for img in (left, right)]
    picture = np.vstack([np.hstack([left, right]), np.hstack(masks)])
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor((picture * 255).astype(np.uint8), cv2.COLOR_RGB2BGR))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-vision", action="store_true", help="no eyes: the knob where the drawing puts it")
    parser.add_argument("--save", type=Path, help="a PNG of the eyes' first images and the colour regions")
    args = parser.parse_args()
    world = load_world(SCENARIO)
    try:
        out = run(world, vision=not args.no_vision, save=args.save)
    finally:
        world.close()
    s = out.sighting
    if s is not None:
        print(f"knob seen: {s.left.pixels} / {s.right.pixels} red pixels, disparity {s.disparity_px:.2f} px, "
              f"rows {s.row_offset_px:+.2f} px")
        print(f"  triangulated at {np.round(s.position, 4)} m, true {np.round(out.knob_true, 4)} m: "
              f"{out.triangulation_error_m * 1000:.1f} mm off; visible face at {np.round(s.face, 4)} m")
    elif not args.no_vision:
        print("the knob was not seen in both eyes")
    for i, p in enumerate(out.poses):
        print(f"pose {i}: {p.message}")
    print(f"the drawer is open {out.opened_m * 1000:.0f} mm (asked {PULL_M * 1000:.0f} mm)")
    if out.seen_after is not None:
        moved = out.sighting.position - out.seen_after.position if out.sighting is not None else None
        print(f"seen again at {np.round(out.seen_after.position, 4)} m"
              + (f": the knob came {moved[0] * 1000:.0f} mm towards the robot" if moved is not None else ""))


if __name__ == "__main__":
    main()
