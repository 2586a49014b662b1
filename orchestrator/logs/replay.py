"""``dynabrain replay LOG``: what a log holds (duration, channels, events), ``--publish`` and ``--live``.

The summary reads any MCAP file; for a dynabrain log it adds the run's metadata, the run's tick range
(after rollbacks), and its events. ``--publish`` is the bridge's (`dynabrain.bridge.publish_recording`),
called by the CLI: this room does not import the bridge. ``--live`` is `LogView`: the log played to
Foxglove through the live view's server (`logs.live.FoxgloveServer`).
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections import Counter
from dataclasses import dataclass

from ..kernel.errors import DynabrainError
from .read import LogIndex, read_index
from .scan import Message, scan
from .schema import DISCARDED, TOPIC_BUS, TOPIC_EVENTS

QUIET_KINDS = ("layout",)
"""Event kinds left out of the event list (they are counted)."""


def summarize(index: LogIndex, *, max_events: int = 40) -> list[str]:
    """The lines of a log's summary."""
    lines = [f"{index.path}: {'complete' if index.report.complete else 'INCOMPLETE'} MCAP, "
             f"{index.report.size / 1024:.1f} KiB, {index.report.chunks} chunks, "
             f"written by {index.header.library if index.header else 'unknown'}"]
    info = index.info
    span = index.time_range
    if info is None:
        lines.append("not a dynabrain recording (no dynabrain metadata)")
        if span is not None:
            lines.append(f"duration: {(span[1] - span[0]) / 1e9:.3f} s of log time")
    else:
        lines += _run_lines(index)
    lines.append("channels:")
    width = max((len(c.topic) for c in index.channels.values()), default=0)
    for cid, ch in sorted(index.channels.items()):
        schema = index.schemas.get(ch.schema_id)
        name = f"{schema.name} ({schema.encoding})" if schema else f"no schema ({ch.encoding})"
        lines.append(f"  {ch.topic:<{width}}  {index.counts.get(cid, 0):>8} messages  {name}")
    if info is not None:
        lines += _event_lines(index, max_events)
    return lines


def _run_lines(index: LogIndex) -> list[str]:
    info = index.info
    assert info is not None
    src = f"scenario {info.scenario_name} ({info.scenario_path})" if info.scenario_name else "a world built in code"
    out = [f"dynabrain recording of {src}, world {info.world!r}, step {info.dt_ns / 1e6:g} ms, seed {info.seed}",
           f"recorded {info.start_time} with dynabrain {info.versions.get('dynabrain', '?')}, "
           f"python {info.versions.get('python', '?')}, mujoco {info.versions.get('mujoco', '-')}"]
    final = index.final(TOPIC_BUS)
    ticks = [t for _e, t, p in index.keys.get(TOPIC_BUS, []) if p in final]
    if ticks:
        first, last = min(ticks), max(ticks)
        out.append(f"duration: {(last - first) * info.dt_ns / 1e9:.3f} s simulated, ticks {first}..{last}")
    rollbacks = [e for e in index.events if e.get("kind") == "rollback"]
    discarded = len(index.keys.get(TOPIC_BUS, [])) - len(final)
    if rollbacks:
        out.append(f"rollbacks: {len(rollbacks)}; {discarded} bus messages are discarded ticks "
                   f"(on {DISCARDED}/... topics once the log is closed or recovered)")
    return out


def _event_lines(index: LogIndex, max_events: int) -> list[str]:
    counts = Counter(e.get("kind") for e in index.events)
    out = [f"events: {len(index.events)}" + (" (" + ", ".join(f"{k} {n}" for k, n in sorted(counts.items())) + ")"
                                             if counts else "")]
    shown = [e for e in index.events if e.get("kind") not in QUIET_KINDS]
    for ev in shown[:max_events]:
        out.append(f"  t={ev.get('time', 0):9.3f}s tick {ev.get('tick'):>7} [{ev.get('source', '?')}] "
                   f"{ev.get('kind')} {describe(ev)}")
    if len(shown) > max_events:
        out.append(f"  ... and {len(shown) - max_events} more")
    return out


def describe(event: dict) -> str:
    """A short text of an event's detail."""
    d = event.get("detail", {})
    kind = event.get("kind")
    if kind in ("param", "set"):
        return f"{d.get('name')} = {d.get('value')}"
    if kind == "rollback":
        return f"{d.get('from_tick')} -> {d.get('to_tick')} ({d.get('cause')})"
    if kind == "module_added":
        return f"{d.get('module')} ({d.get('spec', {}).get('python', '?')})"
    if kind == "expect":
        return f"{'pass' if d.get('passed') else 'FAIL'}: {d.get('name')}" + (f" ({d['detail']})" if d.get("detail")
                                                                                else "")
    if kind == "error":
        return str(d.get("message"))
    if kind == "imagined":
        return f"{d.get('topic')}: {d.get('ticks')} ticks from tick {d.get('start_tick')}"
    text = json.dumps(d, separators=(", ", ": "))
    return text if len(text) < 100 else text[:97] + "..."


# -- a log played to Foxglove ------------------------------------------------------------------------------
SETTLE_S = 0.05
"""After a client's first subscription, how long playing waits for no further one (its other channels)."""


@dataclass
class LogViewResult:
    messages: int
    wall_s: float


class LogView:
    """A recorded run played to Foxglove over the live view's WebSocket server (loopback): every channel of
    the log except the ``/discarded/...`` ones (what rollbacks discarded), each with its recorded schema and
    encoding, every message at its log time, paced: ``speed`` 1 is the run's own pace (``inf``: as fast as
    possible). As in a live view, a client that subscribes late gets each channel's latest message (the
    recent events). ``start()`` serves (a port in use raises naming ``port_option``, see
    `logs.live.LiveOptions`); ``play()`` waits for a subscriber (up to ``wait_s``), then plays."""

    def __init__(self, path: str | os.PathLike[str], *, host: str = "127.0.0.1", port: int = 8765,
                 port_option: str | None = None, speed: float = 1.0):
        from .live import FoxgloveServer, check_host  # foxglove-sdk is loaded only when a view is asked for

        if isinstance(speed, bool) or not isinstance(speed, (int, float)) or not speed > 0:
            raise DynabrainError(f"--speed is a positive factor (1 = real time, inf = as fast as possible), "
                                 f"got {speed!r}")
        self.path, self.host, self.speed = os.fspath(path), check_host(host), float(speed)
        self.requested_port, self.port_option = port, port_option
        self.index: LogIndex | None = None
        self.sent = 0
        self._fox = FoxgloveServer(f"dynabrain replay {os.path.basename(self.path)}")
        self._channels: dict[int, object] = {}

    @property
    def port(self) -> int:
        return self._fox.server.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def start(self) -> LogView:
        index = self.index = read_index(self.path)
        for cid, ch in sorted(index.channels.items()):
            if ch.topic.startswith(DISCARDED + "/"):
                continue
            schema = index.schemas.get(ch.schema_id)
            name, encoding, data = (schema.name, schema.encoding, schema.data) if schema else ("", "", b"")
            self._channels[cid] = self._fox.channel(ch.topic, name, encoding, data, ch.encoding, dict(ch.metadata),
                                                    events=ch.topic == TOPIC_EVENTS)
        self._fox.start(self.host, self.requested_port, self.port_option)
        return self

    def play(self, stop: threading.Event | None = None, wait_s: float = 30.0) -> LogViewResult:
        """Send every message at its time (see the class docstring); ``stop`` ends early."""
        stop = stop or threading.Event()
        fox = self._fox
        if fox.subscribed.wait(wait_s):
            fox.subscribed.clear()
            end = time.monotonic() + 10 * SETTLE_S
            while time.monotonic() < end and fox.subscribed.wait(SETTLE_S):  # the client's other channels
                fox.subscribed.clear()
        t0, first = time.perf_counter(), None
        for rec in scan(self.path):
            if stop.is_set():
                break
            if not isinstance(rec, Message):
                continue
            channel = self._channels.get(rec.channel_id)
            if channel is None:
                continue
            first = rec.log_time if first is None else first
            if self.speed != math.inf:
                ahead = t0 + (rec.log_time - first) / 1e9 / self.speed - time.perf_counter()
                if ahead > 0 and stop.wait(ahead):
                    break
            fox.send(channel, rec.data, rec.log_time)
            self.sent += 1
        return LogViewResult(self.sent, time.perf_counter() - t0)

    def close(self) -> None:
        self._fox.close()
