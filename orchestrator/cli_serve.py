"""``dynabrain serve``: expose a World over Zenoh (to be built with the bridge)."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    """Add ``serve`` (and the robot emulator command) to the main CLI (nothing yet)."""
