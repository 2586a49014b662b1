"""Holds: one brain keeps a served world to itself (`acquire`), other brains get read-only calls.

A hold ends when its brain releases it, when that brain makes no call for the hold's lease, or when
the brain's liveliness token goes away (`forget`). Its state is one tuple, replaced whole, so readers
on other threads see either the old hold or the new one.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from dynabrain.orchestrator.kernel.errors import DynabrainError

from .protocol import READ_ONLY


class BusyError(DynabrainError):
    """Another brain holds the world (or owns the fork): the ``busy`` error reply."""


class Hold:
    """Who holds world ``world``; ``emit(kind, **detail)`` publishes hold and release events."""

    def __init__(self, world: str, emit: Callable[..., Any]):
        self._world, self._emit = world, emit
        self._hold: tuple[str, float, float] | None = None  # brain, expiry (monotonic s), lease (s)

    def holder(self) -> str | None:
        """The holding brain, or None (a hold whose lease ran out is released here)."""
        hold = self._hold
        if hold is None:
            return None
        if time.monotonic() > hold[1]:
            self._hold = None
            self._emit("release", brain=hold[0], reason="lease ended")
            return None
        return hold[0]

    def check(self, call: str, brain: str | None) -> None:
        """Refuse ``call`` from ``brain`` when another brain holds the world and the call is not read-only."""
        holder = self.holder()
        if holder is not None and holder != brain and call not in READ_ONLY:
            left = self._hold[1] - time.monotonic() if self._hold else 0.0
            raise BusyError(f"world {self._world!r} is held by brain {holder!r} (lease ends in {left:.1f} s "
                            f"unless it calls again); {call} refused, read-only calls are allowed")

    def acquire(self, brain: str | None, lease: float) -> dict[str, Any]:
        if brain is None:
            raise DynabrainError("acquire needs a brain id in the command (the `brain` field)")
        holder = self.holder()
        if holder is not None and holder != brain:
            raise BusyError(f"world {self._world!r} is held by brain {holder!r}")
        self._hold = (brain, time.monotonic() + lease, lease)
        self._emit("hold", brain=brain, lease=lease)
        return {"holder": brain, "lease": lease}

    def release(self, brain: str | None) -> dict[str, Any]:
        holder = self.holder()
        if holder is not None:
            if holder != brain:
                raise BusyError(f"world {self._world!r} is held by brain {holder!r}, not by {brain!r}")
            self._hold = None
            self._emit("release", brain=brain, reason="released")
        return {"holder": None}

    def touch(self, brain: str | None) -> None:
        """A call from ``brain``: if it holds the world, its lease starts again."""
        hold = self._hold
        if hold is not None and hold[0] == brain:
            self._hold = (brain, time.monotonic() + hold[2], hold[2])

    def forget(self, brain: str) -> None:
        """``brain`` is gone: its hold ends."""
        hold = self._hold
        if hold is not None and hold[0] == brain:
            self._hold = None
            self._emit("release", brain=brain, reason="brain gone")
