"""Timing helpers shared by the benchmark scripts (imported as ``timing``: scripts run from bench/)."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence


def best_of(fn: Callable[[], object], repeats: int = 5) -> float:
    """The smallest wall time, in seconds, of ``repeats`` calls of ``fn()``."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def best_of_each(fns: Sequence[Callable[[], object]], repeats: int = 7) -> list[float]:
    """The smallest time of each function over ``repeats`` rounds, the functions interleaved in each
    round (so that a busy machine slows them alike)."""
    best = [float("inf")] * len(fns)
    for _ in range(repeats):
        for i, fn in enumerate(fns):
            t0 = time.perf_counter()
            fn()
            best[i] = min(best[i], time.perf_counter() - t0)
    return best
