"""What every command of the CLI shares: the consoles, and how a scenario that does not validate ends a
command (every problem, file:line [field], then exit code 2)."""

from __future__ import annotations

import os

import typer
from rich.console import Console

from ..kernel.errors import ScenarioError
from ..scenario.model import Scenario, load_scenario

console = Console(highlight=False)
err_console = Console(stderr=True, highlight=False, soft_wrap=True)


def fail_scenario(exc: ScenarioError) -> None:
    """Print every problem of ``exc`` and exit with code 2."""
    err_console.print(f"[bold red]{len(exc.problems)} problem(s):[/]")
    for problem in exc.problems:
        err_console.print(f"  {problem}", markup=False)
    raise typer.Exit(2)


def load_or_exit(path: str | os.PathLike[str]) -> Scenario:
    """The scenario at ``path``, or exit 2 with its problems."""
    try:
        return load_scenario(path)
    except ScenarioError as exc:
        fail_scenario(exc)
        raise  # not reached: fail_scenario exits
