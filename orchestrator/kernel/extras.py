"""The optional parts of dynabrain and the extra that installs each (``pip install 'dynabrain[fmu]'``).

The base install runs scenarios with MuJoCo, writes and reads logs, and serves and drives worlds over
Zenoh. Everything else is imported where it is used, so that a part that is missing fails only when it
is asked for, and then by name: `hint` turns the `ModuleNotFoundError` of a missing package into the
extra to install. The CLI, `make_module` and the class-path resolver say it that way.
"""

from __future__ import annotations

from .errors import DynabrainError

EXTRAS: dict[str, tuple[str, str]] = {
    # imported package: (the extra that installs it, what it is for)
    "fmpy": ("fmu", "FMUs (FMI 1.0, 2.0 and 3.0), SSP import and export"),
    "exudyn": ("exudyn", "the Exudyn physics core"),
    "cv2": ("vision", "stereo depth (OpenCV)"),
    "scipy": ("mesh", "mesh bodies' convex hulls"),
    "gymnasium": ("learn", "the Gymnasium environment"),
    "cma": ("learn", "CMA-ES: learning policies, calibrating the simulator"),
    "mink": ("ik", "inverse kinematics (mink)"),
    "rosbags": ("ros2", "ROS 2 messages (serve --ros2, --ros2-schemas logs)"),
    "ray": ("ray", "batches of futures on a Ray cluster"),
    "rerun": ("view", "the Rerun viewer (dynabrain view, --view)"),
    "matplotlib": ("view", "plots of logs (dynabrain plot)"),
    "warp": ("warp", "MJWarp physics for lockstep batches"),
    "mujoco_warp": ("warp", "MJWarp physics for lockstep batches"),
}


class MissingExtraError(DynabrainError, ModuleNotFoundError):
    """A part of dynabrain that is not installed: names the package and the extra that installs it."""


def hint(exc: BaseException) -> MissingExtraError | None:
    """The error to raise instead of ``exc`` when it is a missing optional package, else None."""
    name = getattr(exc, "name", None)
    top = name.partition(".")[0] if isinstance(name, str) else ""
    if not isinstance(exc, ModuleNotFoundError) or top not in EXTRAS:
        return None
    extra, what = EXTRAS[top]
    err = MissingExtraError(f"{what} needs the package {top!r}, which is not installed: "
                            f"pip install 'dynabrain[{extra}]' (or 'dynabrain[all]')")
    err.name = name
    return err
