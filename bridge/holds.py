"""Holds: one brain keeps a served world to itself (`acquire`), other brains get read-only calls.

A hold ends when its brain releases it, when that brain makes no call for the hold's lease, or when
the brain's liveliness token goes away (`forget`); it does not end while one of its brain's calls runs
(`calling`: a long tick or batch), and each call starts its lease again. A brain the server has seen no
liveliness token of (a client that declares none) could die holding the world with nothing to tell: its
lease is at most ``tokenless_lease`` seconds, renewed by each of its calls, until its token appears
(`token_seen`). The hold is one tuple, replaced whole, so readers on other threads see either the old
hold or the new one.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from typing import Any, NamedTuple

from dynabrain.orchestrator.kernel.errors import DynabrainError

from .protocol import READ_ONLY, TOKENLESS_LEASE_S


class BusyError(DynabrainError):
    """Another brain holds the world (or owns the fork): the ``busy`` error reply."""


class _Held(NamedTuple):
    brain: str
    expiry: float
    """time.monotonic() after which the hold is over."""
    lease: float
    """Seconds of silence the hold lasts now."""
    asked: float
    """The lease the brain asked for (more than ``lease`` while it has no liveliness token)."""


class Hold:
    """Who holds world ``world``; ``emit(kind, **detail)`` publishes hold and release events."""

    def __init__(self, world: str, emit: Callable[..., Any], *, tokenless_lease: float = TOKENLESS_LEASE_S):
        self._world, self._emit = world, emit
        self.tokenless_lease = tokenless_lease
        self._hold: _Held | None = None
        self._calling: list[str | None] = []  # brains whose calls run now (nested: a call answered inside a long one)

    @property
    def held(self) -> bool:
        """A brain holds the world, or did until its lease ran out (`holder` tells which, if any)."""
        return self._hold is not None

    def holder(self) -> str | None:
        """The holding brain, or None (a hold whose lease ran out is released here)."""
        hold = self._hold
        if hold is None:
            return None
        if time.monotonic() > hold.expiry and hold.brain not in self._calling:
            self._hold = None
            self._emit("release", brain=hold.brain, reason="lease ended")
            return None
        return hold.brain

    def check(self, call: str, brain: str | None) -> None:
        """Refuse ``call`` from ``brain`` when another brain holds the world and the call is not read-only."""
        holder = self.holder()
        hold = self._hold
        if holder is not None and holder != brain and call not in READ_ONLY:
            left = hold.expiry - time.monotonic() if hold is not None else 0.0
            raise BusyError(f"world {self._world!r} is held by brain {holder!r} (lease ends in {left:.1f} s "
                            f"unless it calls again); {call} refused, read-only calls are allowed")

    def acquire(self, brain: str | None, lease: float, *, has_token: bool) -> dict[str, Any]:
        """``brain`` holds the world for ``lease`` s of silence (at most ``tokenless_lease`` without a token)."""
        if brain is None:
            raise DynabrainError("acquire needs a brain id in the command (the `brain` field)")
        holder = self.holder()
        if holder is not None and holder != brain:
            raise BusyError(f"world {self._world!r} is held by brain {holder!r}")
        granted = lease if has_token else min(lease, self.tokenless_lease)
        self._hold = _Held(brain, time.monotonic() + granted, granted, lease)
        self._emit("hold", brain=brain, lease=granted)
        out: dict[str, Any] = {"holder": brain, "lease": granted}
        if granted < lease:
            out["note"] = (f"brain {brain!r} has no liveliness token here (dynabrain/{self._world}/brain/{brain}): "
                           f"the hold lasts {granted:g} s without a call from it (not {lease:g}) until the token "
                           "appears")
        return out

    def release(self, brain: str | None) -> dict[str, Any]:
        holder = self.holder()
        if holder is not None:
            if holder != brain:
                raise BusyError(f"world {self._world!r} is held by brain {holder!r}, not by {brain!r}")
            self._hold = None
            self._emit("release", brain=brain, reason="released")
        return {"holder": None}

    @contextlib.contextmanager
    def calling(self, brain: str | None) -> Iterator[None]:
        """While a call of ``brain`` runs: its hold does not end, and its lease starts again at both ends."""
        self.enter(brain)
        try:
            yield
        finally:
            self.leave(brain)

    def enter(self, brain: str | None) -> None:
        """A call of ``brain`` starts (`calling` without a generator, for the server's hot path); pair it
        with `leave` in a ``finally``."""
        self.touch(brain)
        self._calling.append(brain)

    def leave(self, brain: str | None) -> None:
        """The call `enter` started has ended."""
        self._calling.pop()
        self.touch(brain)

    def touch(self, brain: str | None) -> None:
        """A call from ``brain`` (or one of its calls still running): if it holds the world, its lease
        starts again."""
        hold = self._hold
        if hold is not None and hold.brain == brain:
            self._hold = hold._replace(expiry=time.monotonic() + hold.lease)

    def token_seen(self, brain: str) -> None:
        """``brain``'s liveliness token appeared: its hold gets the lease it asked for."""
        hold = self._hold
        if hold is not None and hold.brain == brain and hold.lease < hold.asked:
            self._hold = hold._replace(expiry=time.monotonic() + hold.asked, lease=hold.asked)

    def forget(self, brain: str) -> None:
        """``brain`` is gone: its hold ends."""
        hold = self._hold
        if hold is not None and hold.brain == brain:
            self._hold = None
            self._emit("release", brain=brain, reason="brain gone")
