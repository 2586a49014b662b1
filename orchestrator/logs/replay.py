"""``dynabrain replay LOG``: what a log holds (duration, channels, events), and ``--publish``.

The summary reads any MCAP file; for a dynabrain log it adds the run's metadata, the run's tick range
(after rollbacks), and its events. ``--publish`` is the bridge's (`dynabrain.bridge.publish_recording`),
called by the CLI: this room does not import the bridge.
"""

from __future__ import annotations

import json
from collections import Counter

from .read import LogIndex
from .schema import DISCARDED, TOPIC_BUS

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
