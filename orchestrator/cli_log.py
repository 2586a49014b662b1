"""Run outputs (``--log``, ``--live``) and the log commands (``replay``, ``plot``, ``log recover``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer
from rich.console import Console


class RunOutputs:
    """What a run writes besides its summary; `finish` is called with the run's result."""

    def finish(self, result: Any) -> None:
        """Nothing to finish."""


def attach_run_outputs(world: Any, scenario: Any, *, log: Path | None, live: bool, console: Console) -> RunOutputs:
    """Attach the MCAP logger / live view a run asks for (``--log``, ``log:``, ``--live``)."""
    if log is not None or scenario.model.log.mcap or live:
        console.print("note: MCAP logging and the live view are not available in this version; running without")
    return RunOutputs()


def register(app: typer.Typer) -> None:
    """Add ``replay``, ``plot`` and ``log`` to the main CLI (nothing yet)."""
