"""The ``dynabrain`` metadata record of a log: what ran, from which scenario, with what, when.

Keys (all strings, as MCAP metadata is): ``format``; ``world``, ``dt_ns``, ``seed``, ``history``,
``start_tick``; ``scenario_name``, ``scenario_path`` (absolute, as it was), ``scenario_dir`` (where
its relative paths such as ``model:`` resolve), ``scenario_text`` (the file's text, verbatim),
``duration_ns``; ``start_time`` (UTC, ISO 8601); ``time_origin_ns`` (the log time of tick 0, ns since
1970: a message's simulated time is its log time less this; see `logs.schema`); ``versions`` and
``settings`` (JSON).
A world built in code has no scenario keys; `--verify` then has nothing to rebuild from.
"""

from __future__ import annotations

import datetime
import json
import platform
import time
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import metadata as importlib_metadata
from typing import Any

from .schema import FORMAT

PACKAGES = ("dynabrain", "numpy", "mujoco", "exudyn", "fmpy", "zstandard", "protobuf",
            "foxglove-schemas-protobuf", "foxglove-sdk", "eclipse-zenoh", "pydantic", "pyyaml")


def versions() -> dict[str, str]:
    """Python and the installed versions of the packages a run depends on."""
    out = {"python": platform.python_version(), "platform": platform.platform()}
    for name in PACKAGES:
        try:
            out[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            continue
    return out


def run_metadata(world: Any, scenario: Any, settings: Mapping[str, Any], *, wall_ns: int | None = None,
                 origin_ns: int | None = None) -> dict[str, str]:
    """The metadata of a run starting now (``wall_ns``: the wall-clock time it starts at, ns since 1970;
    ``origin_ns``: the log time of its tick 0)."""
    wall_ns = time.time_ns() if wall_ns is None else wall_ns
    start = datetime.datetime.fromtimestamp(wall_ns / 1e9, datetime.UTC)
    meta = {
        "format": FORMAT, "world": world.name, "dt_ns": str(world.dt_ns), "seed": str(world.seed),
        "history": str(world.history.depth), "start_tick": str(world.tick_count),
        "start_time": start.isoformat(timespec="milliseconds"),
        "versions": json.dumps(versions()), "settings": json.dumps(dict(settings)),
    }
    if origin_ns is not None:
        meta["time_origin_ns"] = str(origin_ns)
    if scenario is not None:
        meta.update({"scenario_name": scenario.model.name, "scenario_path": str(scenario.path),
                     "scenario_dir": scenario.dir, "scenario_text": scenario.source.text,
                     "duration_ns": str(scenario.duration_ns)})
    return meta


@dataclass(frozen=True)
class RunInfo:
    """The metadata of a dynabrain log, typed."""

    world: str
    dt_ns: int
    seed: int
    history: int
    start_tick: int
    start_time: str
    versions: dict[str, str]
    settings: dict[str, Any]
    scenario_name: str | None = None
    scenario_path: str | None = None
    scenario_dir: str | None = None
    scenario_text: str | None = None
    duration_ns: int | None = None
    time_origin_ns: int = 0
    """The log time of tick 0 (0 in logs written before log times were anchored to the wall clock)."""

    @classmethod
    def parse(cls, meta: Mapping[str, str]) -> RunInfo:
        opt = meta.get
        return cls(world=meta["world"], dt_ns=int(meta["dt_ns"]), seed=int(meta["seed"]),
                   history=int(meta["history"]), start_tick=int(meta["start_tick"]), start_time=meta["start_time"],
                   versions=json.loads(meta.get("versions", "{}")), settings=json.loads(meta.get("settings", "{}")),
                   scenario_name=opt("scenario_name"), scenario_path=opt("scenario_path"),
                   scenario_dir=opt("scenario_dir"), scenario_text=opt("scenario_text"),
                   duration_ns=int(meta["duration_ns"]) if "duration_ns" in meta else None,
                   time_origin_ns=int(meta.get("time_origin_ns", "0")))
