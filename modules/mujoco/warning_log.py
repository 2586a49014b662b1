"""MuJoCo's warnings, counted: the first of each kind is logged, the others only counted.

MuJoCo reports a warning (``Nan, Inf or huge value in QACC at DOF 2. The simulation is unstable. Time =
0.1000.``) once per data and kind, but a run that keeps failing and rolling back, forks, and every
structure compiled again (new data) report it again: one diverging run printed 174 such lines. Here a
warning's kind is its text with the numbers taken out; the first of each kind goes to the
``dynabrain.mujoco`` log at WARNING, the repeats at DEBUG, and `summary` says how many of each were
not shown (`dynabrain run` prints it once at the end of a run).

MuJoCo's default handler would append the warnings to MUJOCO_LOG.TXT in the working folder; the core
writes no files, and it finds divergence from the data's warning counters, which this keeps intact.
"""

from __future__ import annotations

import logging
import re
import threading

import mujoco

_log = logging.getLogger("dynabrain.mujoco")
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_lock = threading.Lock()  # forks step in threads
_counts: dict[str, int] = {}  # kind -> how many times


def kind_of(message: str) -> str:
    """The kind of a warning: its text with every number written ``#``."""
    return _NUMBER.sub("#", message.strip())


def record(message: str) -> None:
    """MuJoCo's warning handler (`install`): count ``message``; log it when it is the first of its kind."""
    text = message.strip()
    kind = kind_of(text)
    with _lock:
        seen = _counts.get(kind, 0)
        _counts[kind] = seen + 1
    if seen:
        _log.debug("MuJoCo (again, %d times): %s", seen + 1, text)
    else:
        _log.warning("MuJoCo: %s", text)


def counts() -> dict[str, int]:
    """How many times each kind of warning came (since the last `summary` with ``reset``)."""
    with _lock:
        return dict(_counts)


def summary(*, reset: bool = True) -> str | None:
    """A line about the warnings that were counted but not shown (each kind's repeats), or None when
    every warning was shown; ``reset``: start counting again."""
    with _lock:
        repeats = {kind: n - 1 for kind, n in _counts.items() if n > 1}
        if reset:
            _counts.clear()
    if not repeats:
        return None
    parts = [f"{n} x {kind!r}" for kind, n in sorted(repeats.items(), key=lambda item: -item[1])]
    total = sum(repeats.values())
    return (f"MuJoCo: {total} more warning{'s' if total > 1 else ''} of the kinds shown above (numbers as #): "
            + "; ".join(parts))


def install() -> None:
    """Make `record` MuJoCo's warning handler, unless the program set one of its own."""
    if mujoco.get_mju_user_warning() is None:
        mujoco.set_mju_user_warning(record)
