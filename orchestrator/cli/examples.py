"""The example scenarios shipped with dynabrain: ``dynabrain examples`` lists them and copies them, and
``dynabrain run NAME`` runs one by name when no file of that name is here.

An installed dynabrain holds them as package data, ``dynabrain/scenarios`` (with ``models/``) beside
``dynabrain/fmus`` (the FMU sources the FMU scenarios build); a source checkout holds the same folders
at its top, ``scenarios/`` and ``fmus/``.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from ..kernel.errors import DynabrainError
from ..scenario.shipped import FMUS, SCENARIOS, resolve_scenario, shipped_dir, shipped_scenarios
from .common import console

__all__ = ["FMUS", "SCENARIOS", "resolve_scenario", "shipped_dir", "shipped_scenarios"]


def _title(path: Path) -> str:
    """The first comment line of a scenario file (what it shows), or empty."""
    try:
        for line in path.read_text(encoding="utf-8").splitlines():
            if line.startswith("#"):
                return line.lstrip("# ").strip()
            if line.strip():
                break
    except OSError:
        pass
    return ""


def examples(copy: Annotated[Path | None, typer.Option(
        "--copy", help="copy every example (with its models and FMU sources) into this folder")] = None) -> None:
    """List the example scenarios shipped with dynabrain (run one with `dynabrain run NAME`)."""
    found = shipped_scenarios()
    if not found:
        raise DynabrainError("this dynabrain has no shipped scenarios (neither dynabrain/scenarios nor a checkout's "
                             "scenarios/ was found)")
    if copy is not None:
        _copy(copy)
        console.print(f"copied {len(found)} scenarios to {copy}: run one with `dynabrain run "
                      f"{copy / 'scenarios' / 'two_cubes.yaml'}`", markup=False)
        return
    table = Table("name", "what", header_style="bold")
    for name, path in found.items():
        table.add_row(name, _title(path))
    console.print(table)
    console.print(f"in {shipped_dir()}; `dynabrain run NAME` runs one, `dynabrain examples --copy DIR` copies them",
                  markup=False)


def _copy(target: Path) -> None:
    """``target/scenarios`` and ``target/fmus`` (the FMU scenarios find ``fmus/`` in a parent folder)."""
    for kind in (SCENARIOS, FMUS):
        src = shipped_dir(kind)
        if src is None:
            continue
        dst = target / kind
        if dst.exists() and any(dst.iterdir()):
            raise DynabrainError(f"{dst} exists and is not empty: copy the examples somewhere else")
        try:
            shutil.copytree(src, dst, dirs_exist_ok=True,
                            ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "__init__.py"))
        except OSError as exc:
            raise DynabrainError(f"cannot copy the examples to {dst}: {exc.strerror or exc}") from None


def register(app: typer.Typer) -> None:
    """Add ``examples`` to the main CLI."""
    app.command()(examples)
