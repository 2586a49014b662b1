"""The checks and conversions of `BrainClient`'s arguments before anything is sent, and of a robot's
status after a program was sent (`robot_check`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .errors import BadRequestError, RobotLostError, RobotStoppedError
from .replies import Snapshot


def snapshot_id(snapshot: Snapshot | int) -> int:
    return snapshot.id if isinstance(snapshot, Snapshot) else integer(snapshot, "a snapshot id")


def integer(value: Any, what: str) -> Any:
    """An integer as JSON writes it (numpy's integers too); anything else goes on for the table's check to
    refuse, naming the field."""
    return int(value) if isinstance(value, (int, np.integer)) and not isinstance(value, bool) else value


def finite_list(values: Any, name: str) -> list[Any]:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise BadRequestError("bad_request", f"inputs[{name!r}]: not an array of numbers ({exc}); nothing sent",
                              "batch") from None
    if not np.isfinite(arr).all():
        raise BadRequestError("bad_request", f"inputs[{name!r}]: NaN or infinite values; nothing sent", "batch")
    return arr.tolist()


def has_infinity(value: Any) -> bool:
    if isinstance(value, float):
        return value in (float("inf"), float("-inf"))
    if isinstance(value, (list, tuple)):
        return any(has_infinity(v) for v in value)
    if isinstance(value, dict):
        return any(has_infinity(v) for v in value.values())
    return False


def robot_check(robot: str, status: dict[str, Any]) -> None:
    """Raise when the robot's status says its program will not be played to its end."""
    if not status.get("alive"):
        tick = status.get("lost_tick")
        raise RobotLostError(robot, tick, f"robot {robot!r}: link lost at tick {tick} (its liveliness token went "
                                          "away); the program may not have been carried out")
    program = status.get("program")
    if program is None:
        raise RobotStoppedError(robot, None, "no program", f"robot {robot!r}: no program was sent to it (set its "
                                "servo's sequence first)")
    if not program.get("forwarded"):
        raise RobotStoppedError(robot, program.get("tick"), str(program.get("reason")),
                                f"robot {robot!r}: the program of tick {program.get('tick')} was "
                                f"{'ignored' if program.get('ignored') else 'not sent'}: {program.get('reason')}")
    played = program.get("robot") or {}
    if played.get("state") in ("ignored", "refused", "stopped", "replaced"):
        tick = status.get("mode_tick") if played["state"] == "stopped" else program.get("tick")
        raise RobotStoppedError(robot, tick, str(played.get("reason")),
                                f"robot {robot!r}: {played['state']} the program of tick {program.get('tick')} "
                                f"at tick {tick}: {played.get('reason')}")
    tick = status.get("mode_tick")
    if status.get("mode") == "safe_stop" and played.get("state") != "done" and (tick or 0) >= program["tick"]:
        raise RobotStoppedError(robot, tick, str(status.get("reason")),
                                f"robot {robot!r}: safe-stopped at tick {tick}: {status.get('reason')}")


def target_values(targets: Sequence[float] | dict[str, float]) -> list[float] | dict[str, float]:
    if isinstance(targets, dict):
        return {str(k): float(v) for k, v in targets.items()}
    return [float(v) for v in targets]
