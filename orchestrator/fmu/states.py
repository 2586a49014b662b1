"""FMU states for history: handles from ``GetFMUstate``, kept in reusable slots.

History saves every module's state every tick, so an FMU state must be cheap to take and must not
leak. A `StatePool` keeps FMU state handles in a slot array; `FMUState` owns one slot while
something (history, a snapshot) refers to it, and gives it back when dropped. Taking a state into a
slot that held one before overwrites it in place (the FMI standard allows ``GetFMUstate`` on a
handle it returned), so the steady state allocates nothing. The pool frees every handle when the
module closes; a state dropped after that does nothing.

Pickling an `FMUState` serializes it (`SerializedFMUState`, plain bytes), when the FMU can.

A pool may carry state of the master's own beside each FMU state (``aux``: an object with ``save()
-> bytes`` and ``load(bytes)``; the schedule of the clocks whose interval the FMU gives, see
`events.Schedule`): it is saved with every capture, loaded with every restore, and appended to the
serialized bytes (its length in the last 4), so a fork or an isolated restart gets it too.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from .api import FmuApi
from .errors import FMUError


@dataclass(frozen=True)
class SerializedFMUState:
    """An FMU state as bytes (``SerializeFMUstate``): it survives the FMU instance and the process,
    and any instance of the same FMU (same token) can take it back."""

    token: str
    data: bytes

    def __repr__(self) -> str:
        return f"<SerializedFMUState {len(self.data)} bytes>"


class StatePool:
    """The state slots of one FMU instance."""

    def __init__(self, api: FmuApi, capacity: int = 16):
        self.api = api
        self.token = api.info.token
        self.slots = np.zeros(capacity, dtype=np.uint64)
        self.base = self.slots.ctypes.data
        self.free = list(range(capacity - 1, -1, -1))
        self.alive = True
        self.aux: Any = None
        """The master's own state saved with each FMU state (see the module docstring), or None."""
        self.aux_of: dict[int, bytes] = {}

    def take(self) -> int:
        """A free slot (its handle, if any, is overwritten by the next save into it)."""
        try:
            return self.free.pop()
        except IndexError:
            return self._grow()

    def _grow(self) -> int:
        n = len(self.slots)
        bigger = np.zeros(2 * n, dtype=np.uint64)
        bigger[:n] = self.slots
        self.slots, self.base = bigger, bigger.ctypes.data
        self.free.extend(range(2 * n - 1, n, -1))
        return n

    def address(self, slot: int) -> int:
        return self.base + 8 * slot

    def capture(self) -> FMUState:
        """Save the FMU's state now."""
        slot = self.take()
        try:
            self.api.get_state(self.address(slot))
        except BaseException:
            self.free.append(slot)
            raise
        if self.aux is not None:
            self.aux_of[slot] = self.aux.save()
        return FMUState(self, slot)

    def restore(self, state: FMUState) -> None:
        self.api.set_state(int(self.slots[state.slot]))
        if self.aux is not None:
            self.aux.load(self.aux_of[state.slot])

    def serialize(self, slot: int) -> SerializedFMUState:
        if not self.alive:
            raise FMUError(f"{self.api.info.label}: this state belongs to a closed FMU instance")
        data = self.api.serialize(int(self.slots[slot]))
        if self.aux is not None:
            extra = self.aux_of[slot]
            data += extra + struct.pack("<I", len(extra))
        return SerializedFMUState(self.token, data)

    def load(self, state: SerializedFMUState) -> FMUState:
        """Deserialize ``state`` into a slot of this pool."""
        if state.token != self.token:
            raise FMUError(f"{self.api.info.label}: the state is of another FMU (token {state.token})")
        data = state.data
        extra = None
        if self.aux is not None:
            (n,) = struct.unpack("<I", data[-4:])
            data, extra = data[:-4 - n], data[-4 - n:-4]
        slot = self.take()
        try:
            self.api.deserialize(data, self.address(slot))
        except BaseException:
            self.free.append(slot)
            raise
        if extra is not None:
            self.aux_of[slot] = extra
        return FMUState(self, slot)

    def in_use(self) -> int:
        return len(self.slots) - len(self.free)

    def close(self) -> None:
        """Free every handle (before the instance is freed)."""
        if not self.alive:
            return
        self.alive = False
        api = self.api
        if api.instance is None or api.dead:
            return
        for slot in np.flatnonzero(self.slots):
            try:
                api.free_state(self.address(int(slot)))
            except Exception:  # a state the FMU refuses to free is its leak, not a reason to stop
                continue


class FMUState:
    """One saved FMU state (a slot of a `StatePool`). Immutable; dropping it frees its slot."""

    __slots__ = ("pool", "slot")

    def __init__(self, pool: StatePool, slot: int):
        self.pool = pool
        self.slot = slot

    def __del__(self) -> None:
        pool = self.pool
        if pool.alive:
            pool.free.append(self.slot)

    def __reduce__(self) -> tuple:
        serialized = self.pool.serialize(self.slot)
        return (SerializedFMUState, (serialized.token, serialized.data))

    def __repr__(self) -> str:  # no slot number: equal states of one instance print alike
        return f"<FMUState of {self.pool.api.name}>"
