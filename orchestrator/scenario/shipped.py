"""The example scenarios shipped with dynabrain, by name: ``load_world("two_cubes")`` and ``dynabrain run
two_cubes`` load one when no file of that name is here.

An installed dynabrain holds them as package data, ``dynabrain/scenarios`` (with ``models/``) beside
``dynabrain/fmus`` (the FMU sources the FMU scenarios build); a source checkout holds the same folders
at its top, ``scenarios/`` and ``fmus/``.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

SCENARIOS, FMUS = "scenarios", "fmus"


def shipped_dir(kind: str = SCENARIOS) -> Path | None:
    """Where the shipped ``scenarios`` (or ``fmus``) are: in the installed package, else in the source
    checkout this code runs from; None when neither has them."""
    try:
        spec = importlib.util.find_spec(f"dynabrain.{kind}")
    except (ImportError, ValueError):
        spec = None
    places = [Path(p) for p in (spec.submodule_search_locations or [])] if spec is not None else []
    places.append(Path(__file__).resolve().parents[2] / kind)  # a checkout: orchestrator/scenario/ -> the top
    return next((p for p in places if p.is_dir() and any(p.iterdir())), None)


def shipped_scenarios() -> dict[str, Path]:
    """Name -> file of every shipped scenario."""
    folder = shipped_dir()
    return {p.stem: p for p in sorted(folder.glob("*.yaml"))} if folder is not None else {}


def resolve_scenario(path: Path) -> Path:
    """``path`` itself when it exists (or names a file in a folder), else the shipped scenario of that
    name (``two_cubes`` or ``two_cubes.yaml``), else ``path`` (its loading then says it is missing)."""
    if path.exists() or path.parent != Path("."):
        return path
    return shipped_scenarios().get(path.stem if path.suffix in (".yaml", ".yml") else path.name, path)
