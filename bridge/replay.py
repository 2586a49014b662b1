"""``dynabrain replay LOG --publish``: a recorded run played back over Zenoh, as its world served it.

A recording (`dynabrain.orchestrator.logs.logger`) is read with the project's own reader; the run (the
ticks a rollback did not discard) is published under ``dynabrain/<world>/...`` with the frames a served
world publishes (`PROTOCOL.md`, *Replaying a recording*):

- ``state``: one STATE frame (view 0) per recorded tick, holding the served world's default stream
  (the core's ``body_pos``, ``body_quat``, ``joint_q``, ``joint_qd``: the signals and the poses) or the
  signals asked for, bit-identical to the recorded bus rows;
- ``events``: the recorded events of the run (``{"tick", "kind", "detail", "source"}``), each after the
  frame of its tick; the logger's own ``layout`` events and events of ticks a later rollback discarded
  are left out;
- ``call/status`` answers the stream layout (so `BrainClient.subscribe_state` works unchanged); every
  other call is refused; ``alive`` is present while the replay runs.

Frames go out at simulated time / ``speed`` of wall-clock time from the first frame (``speed`` may be
``inf``: as fast as possible). Playing starts once a subscriber to ``state`` or ``events`` is there, or
after ``wait_s`` seconds without one, so the first frames are not sent to nobody. Once one of the two
has a subscriber, playing waits up to ``SETTLE_S`` for the other too: a client declares its
subscriptions one after the other, and the first frame must not leave before the second one is there.

Where it listens: ``settings`` in code; from the command line the environment variable
``DYNABRAIN_REPLAY_LISTEN`` (endpoints separated by commas; default ``tcp/127.0.0.1:7447``, port 0 picks a
free one, printed on the ready line).
"""

from __future__ import annotations

import contextlib
import fnmatch
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.logs.read import LogIndex, iter_bus, read_index
from dynabrain.orchestrator.logs.schema import TOPIC_BUS, BusCodec

from . import frames
from . import protocol as p
from .calls import STREAM_VIEW
from .zenoh_io import FRAME, JSON, Settings, open_session, payload_bytes

LISTEN_ENV = "DYNABRAIN_REPLAY_LISTEN"
"""Environment variable: the endpoints ``dynabrain replay --publish`` listens on (comma-separated)."""
DEFAULT_STREAM = ("body_pos", "body_quat", "joint_q", "joint_qd")
SKIPPED_EVENTS = frozenset({"layout"})
SETTLE_S = 0.5
"""After the first subscriber (to the state or the events) appears, how long playing waits for one to
the other as well."""
"""Logger bookkeeping, not events of the world."""


@dataclass
class Recording:
    """The run of a recording, ready to publish: per tick the stream's values, and the run's events."""

    path: str
    world: str
    dt_ns: int
    names: tuple[str, ...]
    shapes: tuple[tuple[int, ...], ...]
    units: tuple[str, ...]
    ticks: np.ndarray
    """(n,) int64, increasing: the ticks of the run that carry the stream's signals."""
    values: np.ndarray
    """(n, size) float64: the stream's values at each tick, as the bus rows hold them."""
    events: list[dict[str, Any]] = field(default_factory=list)
    """``{"tick", "kind", "detail", "source"}``, by tick, then in recorded order."""
    skipped_ticks: int = 0
    """Ticks of the run whose bus layout lacks a stream signal (a module that left): no frame for them."""

    def layout(self) -> dict[str, Any]:
        """The stream's layout as ``status().stream`` gives it for a served world."""
        signals, at = [], 0
        for name, shape, unit in zip(self.names, self.shapes, self.units, strict=True):
            signals.append({"name": name, "shape": list(shape), "unit": unit, "offset": at})
            at += int(np.prod(shape, dtype=np.int64))
        return {"view": STREAM_VIEW, "size": at, "signals": signals}


def load_recording(path: str | os.PathLike[str], signals: Sequence[str] | None = None) -> Recording:
    """Read the run of a dynabrain log. ``signals``: names or glob patterns of the stream (default: the
    served world's default stream). Raises `DynabrainError` naming the file for a missing, foreign or
    damaged log, or a signal it does not have."""
    path = os.fspath(path)
    index = read_index(path)
    info = index.info
    if info is None:
        writer = index.header.library if index.header else "unknown"
        raise DynabrainError(f"{path} is not a dynabrain recording (written by {writer!r}, no dynabrain "
                             "metadata): there is no run to publish")
    codecs = _codecs(index)
    if not codecs:
        raise DynabrainError(f"{path} has no bus channel: there is no run to publish")
    names = _stream_names(codecs[0], signals, path)
    final = index.final(TOPIC_BUS)
    plans: dict[int, np.ndarray | None] = {}
    ticks, rows, skipped = [], [], 0
    for codec, _epoch, tick, row, pos, _topic in iter_bus(path, index):
        if pos not in final:
            continue
        take = plans.get(id(codec), False)
        if take is False:
            take = plans[id(codec)] = _columns(codec, names, codecs[0])
        if take is None:
            skipped += 1
            continue
        ticks.append(tick)
        rows.append(row[take])
    order = np.argsort(np.asarray(ticks, dtype=np.int64), kind="stable")
    first = codecs[0].by_name
    size = sum(first[n].size for n in names)
    values = np.asarray(rows, dtype=np.float64).reshape(-1, size)[order] if rows else np.zeros((0, size))
    return Recording(path, info.world, info.dt_ns, tuple(names), tuple(first[n].shape for n in names),
                     tuple(first[n].unit for n in names), np.asarray(ticks, dtype=np.int64)[order], values,
                     run_events(index.events), skipped)


def _codecs(index: LogIndex) -> list[BusCodec]:
    return [index.bus_codec(cid) for cid in sorted(index.channels) if index.is_bus(cid)]


def _stream_names(codec: BusCodec, signals: Sequence[str] | None, path: str) -> list[str]:
    slots = codec.by_name
    if signals is None:
        cores = [n.split(".")[0] for n in slots if n.count(".") == 1 and n.endswith(".body_pos")]
        return [f"{cores[0]}.{s}" for s in DEFAULT_STREAM if f"{cores[0]}.{s}" in slots] if cores else []
    names: list[str] = []
    for pattern in signals:
        matched = fnmatch.filter(slots, pattern) if any(c in pattern for c in "*?[") else (
            [pattern] if pattern in slots else [n for n in slots if n.split(".", 1)[1:] == [pattern]][:1])
        if not matched:
            from dynabrain.orchestrator.kernel.suggest import did_you_mean

            raise DynabrainError(f"{path}: no signal {pattern!r} in the recording" + did_you_mean(pattern, slots))
        names += [n for n in matched if n not in names]
    return names


def _columns(codec: BusCodec, names: Sequence[str], first: BusCodec) -> np.ndarray | None:
    """The bus columns of the stream in a layout, or None when a signal is missing or changed shape."""
    cols = []
    for name in names:
        slot = codec.by_name.get(name)
        if slot is None or slot.shape != first.by_name[name].shape:
            return None
        cols.append(np.arange(slot.offset, slot.offset + slot.size))
    return np.concatenate(cols).astype(np.intp) if cols else np.zeros(0, dtype=np.intp)


def run_events(events: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The recorded events of the run as the bridge publishes them, by tick then in recorded order.

    An event is left out when a later rollback went back to a tick before its own (it belongs to a
    discarded future), and so are the logger's ``layout`` events; rollbacks themselves stay (at the tick
    the world went back to: a subscriber that never saw the discarded ticks has nothing to drop)."""
    kept = []
    back = math.inf  # the earliest tick a later rollback went back to
    for i in range(len(events) - 1, -1, -1):
        ev = events[i]
        tick = int(ev.get("tick", 0))
        if ev.get("kind") not in SKIPPED_EVENTS and tick <= back:
            kept.append((tick, i, {"tick": tick, "kind": str(ev.get("kind")), "detail": ev.get("detail", {}),
                                   "source": str(ev.get("source", "log"))}))
        if ev.get("kind") == "rollback":
            back = min(back, int(ev.get("detail", {}).get("to_tick", tick)))
    return [ev for _t, _i, ev in sorted(kept, key=lambda k: (k[0], k[1]))]


@dataclass
class ReplayResult:
    frames: int
    events: int
    first_tick: int
    last_tick: int
    sim_s: float
    wall_s: float
    speed: float


class RecordingPublisher:
    """Publishes a `Recording` on one Zenoh session: ``open()``, ``play()``, ``close()``."""

    def __init__(self, recording: Recording, settings: Settings, *, name: str | None = None, speed: float = 1.0):
        if isinstance(speed, bool) or not isinstance(speed, (int, float)) or not speed > 0:
            raise DynabrainError(f"--speed is a positive factor (1 = real time, inf = as fast as possible), "
                                 f"got {speed!r}")
        self.rec, self.settings, self.speed = recording, settings, float(speed)
        self.name = p.check_world_name(name or recording.world)
        self.instance = int.from_bytes(os.urandom(6), "little")
        self.endpoints: list[str] = []
        self.session: zenoh.Session | None = None
        self.tick = int(recording.ticks[0]) if len(recording.ticks) else 0
        self.frames_sent = self.events_sent = 0
        self.done = False
        self._entities: list[Any] = []

    def open(self) -> list[str]:
        self.session, self.endpoints = open_session(self.settings)
        s, name = self.session, self.name
        try:
            self._state = s.declare_publisher(p.key(name, "state"), encoding=FRAME)
            self._events = s.declare_publisher(p.key(name, "events"), encoding=JSON)
            self._entities += [self._state, self._events,
                               s.declare_queryable(p.key(name, "call", "*"), self._on_query, complete=True),
                               s.liveliness().declare_token(p.key(name, "alive"))]
        except BaseException:
            self.close()
            raise
        return self.endpoints

    def wait_for_subscriber(self, timeout_s: float, stop: threading.Event) -> bool:
        """True once something subscribes to the state or the events (False after ``timeout_s``)."""
        end = time.monotonic() + timeout_s
        while not stop.is_set():
            if self._state.matching_status.matching or self._events.matching_status.matching:
                settle = time.monotonic() + SETTLE_S  # the same client's other subscription, if it has one
                while not stop.is_set() and time.monotonic() < settle and not (
                        self._state.matching_status.matching and self._events.matching_status.matching):
                    stop.wait(0.01)
                return True
            if time.monotonic() >= end:
                return False
            stop.wait(0.02)
        return False

    def play(self, stop: threading.Event | None = None) -> ReplayResult:
        """Publish every frame and event at its time (see the module docstring); ``stop`` ends early."""
        stop = stop or threading.Event()
        rec, dt, events = self.rec, self.rec.dt_ns, self.rec.events
        t0 = time.perf_counter()
        tick0 = int(rec.ticks[0]) if len(rec.ticks) else 0
        e = 0
        head = frames.pack_header(frames.STATE, rec.values.shape[1], source=self.instance, aux=STREAM_VIEW)
        for i, tick in enumerate(rec.ticks.tolist()):
            while e < len(events) and events[e]["tick"] < tick:
                e = self._event(e)
            if self.speed != math.inf:
                ahead = t0 + (tick - tick0) * dt / 1e9 / self.speed - time.perf_counter()
                if ahead > 0 and stop.wait(ahead):
                    break
            if stop.is_set():
                break
            self.tick = tick
            self._state.put(_stamped(head, tick, tick * dt) + rec.values[i].astype("<f8", copy=False).tobytes())
            self.frames_sent += 1
            while e < len(events) and events[e]["tick"] <= tick:
                e = self._event(e)
        while e < len(events) and not stop.is_set():
            e = self._event(e)
        self.done = True
        last = self.tick
        return ReplayResult(self.frames_sent, self.events_sent, tick0, last, (last - tick0) * dt / 1e9,
                            time.perf_counter() - t0, self.speed)

    def _event(self, e: int) -> int:
        self._events.put(p.encode(p.plain(self.rec.events[e])))
        self.events_sent += 1
        return e + 1

    def status(self) -> dict[str, Any]:
        rec = self.rec
        out: dict[str, Any] = {
            "world": self.name, "tick": self.tick, "time": self.tick * rec.dt_ns / 1e9, "step_ns": rec.dt_ns,
            "instance": self.instance, "robots": {},
            "replay": {"file": os.path.basename(rec.path), "speed": None if self.speed == math.inf else self.speed,
                       "ticks": [int(rec.ticks[0]), int(rec.ticks[-1])] if len(rec.ticks) else None,
                       "frames_sent": self.frames_sent, "events_sent": self.events_sent, "done": self.done}}
        if rec.names:
            out["stream"] = rec.layout()
        return out

    def _on_query(self, query: zenoh.Query) -> None:
        call = str(query.key_expr).rsplit("/", 1)[-1]
        try:
            p.decode_command(call, payload_bytes(query.payload))
            if call != "status":
                raise p.ProtocolError(f"world {self.name!r} is a replay of {os.path.basename(self.rec.path)}: "
                                      "it answers status only", "refused")
            body = {"tick": self.tick, "instance": self.instance, "result": self.status()}
            query.reply(query.key_expr, p.encode(body), encoding=JSON)
        except p.ProtocolError as exc:
            err = {"error": exc.kind, "message": str(exc), "call": call, "instance": self.instance}
            with contextlib.suppress(Exception):
                query.reply_err(p.encode(err), encoding=JSON)
        finally:
            with contextlib.suppress(Exception):
                query.drop()

    def close(self) -> None:
        for ent in reversed(self._entities):
            with contextlib.suppress(Exception):
                ent.undeclare()
        self._entities = []
        session, self.session = self.session, None
        if session is not None:
            session.close()


def _stamped(head: bytes, tick: int, stamp_ns: int) -> bytes:
    """The STATE header with its tick and simulated time filled in (bytes 16..32)."""
    return head[:16] + int(tick).to_bytes(8, "little", signed=True) + int(stamp_ns).to_bytes(8, "little",
                                                                                             signed=True) + head[32:]


def _default_settings() -> Settings:
    listen = [ep.strip() for ep in os.environ.get(LISTEN_ENV, "").split(",") if ep.strip()]
    return Settings(listen=listen or ["tcp/127.0.0.1:7447"])


def _say(line: str) -> None:
    print(line, flush=True)


def publish_recording(path: str | os.PathLike[str], *, speed: float = 1.0, settings: Settings | None = None,
                      name: str | None = None, signals: Sequence[str] | None = None, wait_s: float = 30.0,
                      stop: threading.Event | None = None, log: Callable[[str], None] = _say) -> ReplayResult:
    """Publish a recorded run over Zenoh (see the module docstring) and return what was sent. Prints a
    ready line (``replaying world 'arm' (dynabrain/arm/**) ... on ENDPOINT instance N``) and a summary."""
    rec = load_recording(path, signals)
    stop = stop or threading.Event()
    pub = RecordingPublisher(rec, settings or _default_settings(), name=name, speed=speed)
    pub.open()
    try:
        span = f"ticks {rec.ticks[0]}..{rec.ticks[-1]}" if len(rec.ticks) else "no ticks"
        log(f"replaying world {pub.name!r} (dynabrain/{pub.name}/**) from {os.path.basename(rec.path)}: {span}, "
            f"{len(rec.events)} events, speed {speed:g}, on {' '.join(pub.endpoints) or '(configured)'} "
            f"instance {pub.instance}")
        if not pub.wait_for_subscriber(wait_s, stop) and not stop.is_set():
            log(f"no subscriber after {wait_s:g} s: playing anyway")
        result = pub.play(stop)
        if rec.skipped_ticks:
            log(f"{rec.skipped_ticks} ticks had no frame: their bus layout lacks a stream signal")
        log(f"replayed {result.frames} frames and {result.events} events ({result.sim_s:.3f} s simulated) "
            f"in {result.wall_s:.3f} s")
        return result
    finally:
        pub.close()
