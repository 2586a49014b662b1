"""What the bridge's client hands a brain back: a `View` of named signals, the `StateFrame` of a view at one
tick, a `Snapshot` the server keeps, and a `BatchReply` (futures run on the server's batch)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import numpy as np

from dynabrain.orchestrator.brain import BranchStatus
from dynabrain.orchestrator.brain.batch import BranchStatuses

from . import frames
from .errors import BridgeError


@dataclass(frozen=True)
class View:
    """Named signals the server reads as one frame (`BrainClient.view`)."""

    id: int
    names: tuple[str, ...]
    shapes: tuple[tuple[int, ...], ...]
    offsets: tuple[int, ...]
    size: int

    def index(self, name: str) -> int:
        """Position of a signal; ``cube.pos`` finds the core's ``core.cube.pos``, as `World.get` does."""
        if name in self.names:
            return self.names.index(name)
        short = [i for i, n in enumerate(self.names) if n.split(".", 1)[1:] == [name]]
        if len(short) == 1:
            return short[0]
        raise KeyError(f"{name!r} is not in view {self.id} ({', '.join(self.names)})")

    @classmethod
    def from_reply(cls, d: dict[str, Any]) -> View:
        sig = d["signals"]
        return cls(int(d["view"]), tuple(s["name"] for s in sig), tuple(tuple(s["shape"]) for s in sig),
                   tuple(int(s["offset"]) for s in sig), int(d["size"]))


@dataclass(frozen=True)
class StateFrame:
    """The values of a view at one tick."""

    tick: int
    time_ns: int
    values: np.ndarray
    view: View

    def __getitem__(self, name: str) -> float | np.ndarray:
        i = self.view.index(name)
        shape = self.view.shapes[i]
        size = int(np.prod(shape, dtype=np.int64))
        chunk = self.values[self.view.offsets[i]:self.view.offsets[i] + size]
        return float(chunk[0]) if shape == () else chunk.reshape(shape)

    def as_dict(self) -> dict[str, float | np.ndarray]:
        return {n: self[n] for n in self.view.names}


@dataclass(frozen=True)
class Snapshot:
    """A whole-world state kept by the server (`BrainClient.snapshot`)."""

    id: int
    tick: int


@dataclass(frozen=True)
class BatchReply(BranchStatuses):
    """What `BrainClient.batch` returns: ``signals[name]`` of shape ``(branches, ticks, *shape)`` (row k the
    value after tick k+1; NaN for ticks a failed branch did not run), ``status[b]`` how branch b ended,
    ``snapshots[b]`` the snapshot that keeps its final state (with ``keep_states``; else None), which
    `BrainClient.restore` continues from. ``tick``: the served world's tick, which the batch left as it was."""

    signals: dict[str, np.ndarray]
    status: list[BranchStatus]
    snapshots: list[Snapshot | None]
    ticks: int
    tick: int
    backend: str
    wall_s: float
    evicted: list[int]
    """Snapshots the server dropped to make room for these (it keeps 64)."""

    @classmethod
    def from_frame(cls, frame: frames.Frame) -> BatchReply:
        meta = json.loads(frame.meta)
        branches, ticks = int(meta["branches"]), int(meta["ticks"])
        if frame.values.size != int(meta["size"]):
            raise BridgeError(f"batch frame of {frame.values.size} values does not match its description "
                              f"({meta['size']} values)")
        signals = {}
        for sig in meta["signals"]:
            shape = (branches, ticks, *sig["shape"])
            at, size = int(sig["offset"]), int(np.prod(shape, dtype=np.int64))
            signals[sig["name"]] = frame.values[at:at + size].reshape(shape).copy()
        status = [BranchStatus(bool(s["ok"]), s["reason"], s["failed_tick"], int(s["ticks_done"]))
                  for s in meta["status"]]
        kept = [None if k is None else Snapshot(int(k["snapshot"]), int(k["tick"])) for k in meta["snapshots"]]
        return cls(signals, status, kept, ticks, frame.seq, str(meta["backend"]), float(meta["wall_s"]),
                   [int(e) for e in meta["evicted"]])
