"""Values with units, as scenario files write them (``2ms``, ``3s``, ``2Hz``, ``50g``, ``90deg``).

Everything inside dynabrain is SI; time is integer nanoseconds. This module turns the strings of a
scenario into those numbers, exactly where it matters (durations are parsed as fractions, never as
floats, so ``0.1ms`` is exactly 100000 ns).
"""

from __future__ import annotations

import re
from fractions import Fraction

from .errors import UnitError

# unit symbol -> (dimension, factor to the SI unit of that dimension)
_UNITS: dict[str, tuple[str, Fraction]] = {
    "s": ("time", Fraction(1)),
    "ms": ("time", Fraction(1, 1000)),
    "us": ("time", Fraction(1, 1_000_000)),
    "µs": ("time", Fraction(1, 1_000_000)),
    "ns": ("time", Fraction(1, 1_000_000_000)),
    "min": ("time", Fraction(60)),
    "Hz": ("frequency", Fraction(1)),
    "kHz": ("frequency", Fraction(1000)),
    "kg": ("mass", Fraction(1)),
    "g": ("mass", Fraction(1, 1000)),
    "mg": ("mass", Fraction(1, 1_000_000)),
    "m": ("length", Fraction(1)),
    "cm": ("length", Fraction(1, 100)),
    "mm": ("length", Fraction(1, 1000)),
    "km": ("length", Fraction(1000)),
    "rad": ("angle", Fraction(1)),
    "deg": ("angle", Fraction(314159265358979323846, 180 * 10**20)),
    "N": ("force", Fraction(1)),
    "Nm": ("torque", Fraction(1)),
    "N*m": ("torque", Fraction(1)),
    "m/s": ("velocity", Fraction(1)),
    "rad/s": ("angular_velocity", Fraction(1)),
    "deg/s": ("angular_velocity", Fraction(314159265358979323846, 180 * 10**20)),
    "m/s2": ("acceleration", Fraction(1)),
    "m/s^2": ("acceleration", Fraction(1)),
    "rad/s2": ("angular_acceleration", Fraction(1)),
    "rad/s^2": ("angular_acceleration", Fraction(1)),
}
_SI_SYMBOL = {
    "time": "s", "frequency": "Hz", "mass": "kg", "length": "m", "angle": "rad", "force": "N",
    "torque": "N*m", "velocity": "m/s", "angular_velocity": "rad/s", "acceleration": "m/s^2",
    "angular_acceleration": "rad/s^2",
}
_QUANTITY = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([^\d\s].*?)?\s*$")

NS_PER_S = 1_000_000_000


MAX_EXPONENT = 400
"""Largest decimal exponent a quantity may have: beyond a float's range (1e308) with room to spare; an
exact Fraction of 1e100000000 would take minutes to build."""
MAX_DIGITS = 400
"""Most digits a quantity's mantissa may have."""


def known_units() -> list[str]:
    """Every unit symbol a scenario may use."""
    return sorted(_UNITS)


def _split(text: str) -> tuple[Fraction, str | None]:
    match = _QUANTITY.match(text)
    if not match:
        raise UnitError(f"{text!r} is not a number with an optional unit (like 2ms, 50g, 2Hz)")
    number, unit = match.groups()
    if unit is not None and unit not in _UNITS:
        from .suggest import closest

        hint = closest(unit, _UNITS)
        raise UnitError(f"unknown unit {unit!r} in {text!r}" + (f" (did you mean {hint!r}?)" if hint else ""))
    mantissa, _, exponent = number.lower().partition("e")
    if (exponent and abs(int(exponent)) > MAX_EXPONENT) or len(mantissa) > MAX_DIGITS:
        shown = text if len(text) <= 40 else text[:37] + "..."
        raise UnitError(f"{shown!r} is out of range: a quantity has at most {MAX_DIGITS} digits and a decimal "
                        f"exponent within +-{MAX_EXPONENT}")
    return Fraction(number), unit


def parse_quantity(value: object, dimension: str | None = None) -> float:
    """Return ``value`` in SI units as a float.

    ``value`` is a number (already SI) or a string such as ``"50g"``. When ``dimension`` is given
    (``"time"``, ``"mass"``, ...), a unit of another dimension is refused.
    """
    exact = parse_exact(value, dimension)
    return float(exact)


def parse_exact(value: object, dimension: str | None = None) -> Fraction:
    """Like :func:`parse_quantity`, but exact (a :class:`~fractions.Fraction`)."""
    if isinstance(value, bool):
        raise UnitError(f"expected a quantity, got a boolean ({value})")
    if isinstance(value, int):
        return Fraction(value)
    if isinstance(value, float):
        if value != value or value in (float("inf"), float("-inf")):
            raise UnitError(f"expected a finite quantity, got {value}")
        return Fraction(str(value))
    if not isinstance(value, str):
        raise UnitError(f"expected a number or a string with a unit, got {type(value).__name__}")
    number, unit = _split(value)
    if unit is None:
        return number
    unit_dim, factor = _UNITS[unit]
    if dimension is not None and unit_dim != dimension:
        raise UnitError(f"{value!r} is a {unit_dim}, expected a {dimension} (in {_SI_SYMBOL[dimension]})")
    return number * factor


def parse_duration_ns(value: object, *, allow_frequency: bool = True) -> int:
    """Parse a duration to integer nanoseconds. ``"2ms"`` -> 2_000_000; ``"500Hz"`` -> 2_000_000.

    A plain number is seconds. A duration that is not a whole number of nanoseconds is refused.
    """
    if isinstance(value, str) and allow_frequency:
        _, unit = _split(value)
        if unit is not None and _UNITS[unit][0] == "frequency":
            hz = parse_exact(value, "frequency")
            if hz <= 0:
                raise UnitError(f"a frequency must be positive, got {value!r}")
            seconds = 1 / hz
        else:
            seconds = parse_exact(value, "time")
    else:
        seconds = parse_exact(value, "time")
    ns = seconds * NS_PER_S
    if ns.denominator != 1:
        raise UnitError(f"{value!r} is not a whole number of nanoseconds")
    return int(ns)


def format_duration(ns: int) -> str:
    """Human form of a duration in nanoseconds (``2ms``, ``1.5s``)."""
    for unit, scale in (("s", NS_PER_S), ("ms", 1_000_000), ("us", 1000)):
        if abs(ns) >= scale:
            value = Fraction(ns, scale)
            return f"{float(value):g}{unit}"
    return f"{ns}ns"


def same_unit(a: str, b: str) -> bool:
    """Whether two port units are the same unit (``N*m`` and ``Nm`` are; ``m`` and ``mm`` are not)."""
    norm = {"": "1", "Nm": "N*m", "m/s2": "m/s^2", "rad/s2": "rad/s^2", "µs": "us"}
    return norm.get(a, a) == norm.get(b, b)
