"""The limits a scenario's values are held to: each value outside them is refused before t=0, with
its file:line, instead of failing (or running away) during the run. ``docs/scenarios.md`` lists
them. Every number must be finite (NaN and infinity are refused everywhere); the
constants below bound them further, in SI units. The pydantic field types at the end (`Duration`,
`PositiveDuration`, `Name`, `Realtime`) apply them where the scenario's shape is checked.
"""

from __future__ import annotations

import math
from typing import Annotated, Any

import numpy as np
from pydantic import PlainValidator

from ..kernel.errors import DynabrainError, UnitError
from ..kernel.history import parse_bytes
from ..kernel.units import NS_PER_S, parse_duration_ns, parse_exact

MAX_NAME = 200
"""The longest name (of the scenario, a body, a module), in characters."""
MAX_DURATION_S = 1e6
"""The longest duration: a run, a step, an event's or an expectation's time (about 11.6 days)."""
MAX_MASS_KG = 1e6
"""The heaviest body (1000 t)."""
MAX_LENGTH_M = 1e5
"""The largest size or coordinate (100 km)."""
MAX_FRICTION = 100.0
"""The largest friction coefficient."""
MAX_GRAVITY = 1000.0
"""The largest gravity component, in m/s^2 (about 100 g)."""
MAX_SUBSTEPS = 10_000
"""The most physics steps per module step."""
MAX_MAGNITUDE = 1e15
"""The largest magnitude of any other number: module parameters, stiffness, damping, event values."""
MAX_PARAM_ITEMS = 1_000_000
"""The most numbers (or items) one list in a module parameter holds."""
MAX_PORT_VALUES = 50_000_000
"""The most numbers a module's ports hold together (400 MB of the bus: a 4K colour image is 25 million), so
that a count parameter (``n: 1e12``) is refused before the bus is laid out."""
DURATION_KEYS = frozenset({"duration", "period", "delay", "timeout", "at", "every", "hold", "dwell", "start_time"})
"""Keys of a parameter's mappings whose values are durations (``sequence: [{pose, duration}]``): a number or
a quantity there is bounded by `MAX_DURATION_S`, as a value with a time unit anywhere is."""
MAX_BODIES = 10_000
"""The most bodies a scene has: its shapes but planes, each copy a ``grid`` makes, each body of a model file.
Compiling a physics model costs time that grows with the square of its free bodies (MuJoCo works out
each body's inertia over all the model's degrees of freedom: 1,000 boxes take 0.1 s, 10,000 about 11 s),
so a larger scene is refused before anything is made."""
MAX_GRID = MAX_BODIES
"""The most copies one ``grid`` makes (as many as a scene holds)."""
MAX_MODEL_BYTES = 16 * 1024 * 1024
"""The largest model file (MJCF, URDF), its includes counted with it: 16 MiB, read with that bound; only a
regular file is read (no device, FIFO or folder). See `scenario.modelfile`."""
MAX_ASSET_BYTES = 256 * 1024 * 1024
"""The largest asset a model file names (a mesh, a texture, a height field): 256 MiB, a regular file."""

CORE_LIMITS: dict[str, tuple[float, float]] = {
    "friction": (0.0, MAX_FRICTION), "restitution": (0.0, 1.0), "gravity": (-MAX_GRAVITY, MAX_GRAVITY),
    "substeps": (0, MAX_SUBSTEPS),
}
"""Ranges of the physics core's parameters (``core:`` and ``set: {core.<name>: ...}``), both ends included."""


def scene_bodies(scene: Any) -> int:
    """How many bodies the ``scene:`` list makes, counted without making them: one per item but a plane
    (static ground), a grid's ``nx * ny`` (a grid of more than `MAX_GRID` copies counts 0: the scene's
    parser refuses it on its own line). What is malformed counts 1; the parser says what is wrong with it."""
    if not isinstance(scene, list):
        return 0
    total = 0
    for item in scene:
        if isinstance(item, dict) and len(item) == 1 and "plane" in item:
            continue
        fields = item.get("grid") if isinstance(item, dict) and len(item) == 1 else None
        count = fields.get("count") if isinstance(fields, dict) else None
        if (isinstance(count, list) and len(count) == 2
                and all(isinstance(c, int) and not isinstance(c, bool) and c >= 1 for c in count)):
            total += count[0] * count[1] if count[0] * count[1] <= MAX_GRID else 0
        else:
            total += 1
    return total


def too_many_bodies(n: int) -> str | None:
    """What is wrong with a scene of ``n`` bodies, or None."""
    if n <= MAX_BODIES:
        return None
    return f"{n} bodies: a scene has at most {MAX_BODIES} (MAX_BODIES), grids counted copy by copy"


def bounded(value: float, what: str, low: float | None = None, high: float | None = None) -> float:
    """``value`` when it is finite and within [low, high]; else a `UnitError` naming ``what`` and the limit."""
    if not math.isfinite(value):
        raise UnitError(f"{what} must be a finite number, got {value}")
    if low is not None and value < low:
        raise UnitError(f"{what} must be at least {low:g}, got {value:g}")
    if high is not None and value > high:
        raise UnitError(f"{what} must be at most {high:g}, got {value:g}")
    return value


def check_magnitudes(value: Any, what: str, limit: float = MAX_MAGNITUDE, *, duration: bool = False) -> None:
    """Raise a `UnitError` when a number in ``value`` (a number, an array, a list or mapping of them)
    is not finite or beyond ±``limit``; a string that is a quantity (``1e300s``, ``5e20``) is read and
    held to the same; a duration (under a `DURATION_KEYS` key, or with a time unit) to `MAX_DURATION_S`;
    a list to `MAX_PARAM_ITEMS` items. Other values (text, flags) pass."""
    if isinstance(value, bool) or value is None:
        return
    if isinstance(value, str):
        _check_quantity(value, what, limit, duration)
        return
    if duration and isinstance(value, (int, float, np.integer, np.floating)):
        bounded(float(value), what, -MAX_DURATION_S, MAX_DURATION_S)
    if isinstance(value, (list, tuple, np.ndarray)) and len(value) > MAX_PARAM_ITEMS:
        raise UnitError(f"{what} holds {len(value)} items, more than {MAX_PARAM_ITEMS} (MAX_PARAM_ITEMS)")
    if isinstance(value, (int, np.integer)):
        if abs(int(value)) > limit:
            raise UnitError(f"{what} must be within ±{limit:g}, got a whole number of {int(value).bit_length()} bits")
    elif isinstance(value, (float, np.floating)):
        bounded(float(value), what, -limit, limit)
    elif isinstance(value, np.ndarray) and value.dtype.kind in "biuf":
        if value.size and not (np.all(np.isfinite(value)) and np.max(np.abs(value)) <= limit):
            bad = value[~(np.isfinite(value) & (np.abs(value) <= limit))].flat[0]
            bounded(float(bad), what, -limit, limit)
    elif isinstance(value, (list, tuple)):
        for item in value:
            check_magnitudes(item, what, limit, duration=duration)
    elif isinstance(value, dict):
        for key, item in value.items():
            check_magnitudes(item, f"{what}.{key}", limit, duration=str(key) in DURATION_KEYS)


def _check_quantity(text: str, what: str, limit: float, duration: bool) -> None:
    """Hold a string that is a number with an optional unit (text that is not one passes) to the limits."""
    try:
        value = abs(parse_exact(text))
    except UnitError:
        return
    if not duration and not _is_number(text):  # a unit: a time is a duration
        try:
            parse_exact(text, "time")
            duration = True
        except UnitError:
            pass
    if duration and value > MAX_DURATION_S:
        raise UnitError(f"{what} {short(text)} is longer than {MAX_DURATION_S:g} s (MAX_DURATION_S)")
    if value > limit:
        raise UnitError(f"{what} must be within ±{limit:g}, got {short(text)}")


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def param_problem(spec: Any, value: Any, limits: tuple[float, float] | None = None) -> str | None:
    """What is wrong with ``value`` for the parameter ``spec`` (a `Param`: its type and unit), its
    finiteness and its range (``limits``, else `MAX_MAGNITUDE`; a time parameter's `MAX_DURATION_S`), or
    None. The value as written is held to `check_magnitudes` too: a parameter the module reads itself
    (a servo's ``sequence``) may hold quantities as text."""
    try:
        converted = spec.convert(value)
        if limits is None:
            duration = getattr(spec, "dimension", None) == "time"
            check_magnitudes(converted, "the value", duration=duration)
            check_magnitudes(value, "the value", duration=duration)
        elif isinstance(converted, (int, float, np.ndarray, np.number)) and not isinstance(converted, bool):
            for x in np.ravel(converted):
                bounded(float(x), "the value", *limits)
    except (UnitError, TypeError, ValueError) as exc:
        return str(exc)
    return None


def short(value: Any, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters, for a message about a value that may be huge."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


# -- pydantic field types that hold these limits ----------------------------------------------------------
def _duration(*, positive: bool) -> PlainValidator:
    def check(value: Any) -> Any:
        if isinstance(value, bool) or not isinstance(value, (str, int, float)):
            raise ValueError(f"expected a duration (2ms, 1.5s, or seconds as a number), got {short(value)}")
        ns = parse_duration_ns(value)
        if ns < 0 or (positive and ns == 0):
            raise ValueError(f"a duration must be {'positive' if positive else 'zero or more'}, got {short(value)}")
        if ns > MAX_DURATION_S * NS_PER_S:
            raise ValueError(f"{short(value)} is longer than {MAX_DURATION_S:g} s (MAX_DURATION_S)")
        return value

    return PlainValidator(check)


def _name(value: Any) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ValueError(f"a name is a non-empty string, got {short(value)}")
    if len(value) > MAX_NAME:
        raise ValueError(f"a name is at most {MAX_NAME} characters (MAX_NAME), got {len(value)}")
    return value


def _realtime(value: Any) -> bool | float:
    if isinstance(value, bool):
        return value
    if not isinstance(value, (int, float)):
        raise ValueError(f"realtime is true, false or a speed factor (0.5: half speed), got {short(value)}")
    return bounded(float(value), "the real-time factor", 1e-6, 1e6)


def _byte_size(value: Any) -> int:
    try:
        return parse_bytes(value, "the history budget")
    except DynabrainError as exc:
        raise ValueError(str(exc)) from None


Duration = Annotated[str | int | float, _duration(positive=False)]
"""A time from the start: ``2ms``, ``1.5s``, seconds as a number; at least 0, at most `MAX_DURATION_S`."""
PositiveDuration = Annotated[str | int | float, _duration(positive=True)]
"""A duration above 0 (a step, a period, the length of a run), at most `MAX_DURATION_S`."""
Name = Annotated[str, PlainValidator(_name)]
"""A name: a non-empty string of at most `MAX_NAME` characters."""
Realtime = Annotated[bool | float, PlainValidator(_realtime)]
"""``true``, ``false`` or a positive speed factor."""
ByteSize = Annotated[int | str, PlainValidator(_byte_size)]
"""A memory size in bytes: a whole number, ``2GiB``, ``500MB``, or a share of the machine's memory (``25%``)."""
