"""``dynabrain fmu new|build|check``: FMU authoring (to be built with the FMU adapter)."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    """Add the ``fmu`` command group to the main CLI (nothing yet)."""
