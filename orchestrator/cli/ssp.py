"""``dynabrain ssp import|export``: systems of FMUs described in SSP (System Structure and
Parameterization).

- ``import SYSTEM.ssp [-o scenario.yaml] [--fmu-dir DIR] [--run]``: a scenario from the SSP (its
  FMUs extracted to DIR, by default a folder named after the scenario beside it), checked by building
  it once; ``--run`` runs it as ``dynabrain run`` does;
- ``export SCENARIO [-o system.ssp]``: the SSP of a scenario whose modules all are FMUs (SSD 1.0,
  checked against the SSP schemas FMPy ships); what SSP cannot hold (events, expectations) is listed.

Exit codes: 0 ok, 2 bad input (an SSP or a scenario that cannot be converted: every reason, naming the
file and the element); with ``--run``, those of ``dynabrain run``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Annotated

import typer

from ..kernel.errors import ScenarioError
from ..scenario.ssp import SSPError, export_ssp, import_ssp
from .common import console, err_console, fail_scenario

ssp_app = typer.Typer(add_completion=False, no_args_is_help=True,
                      help="SSP (System Structure and Parameterization): systems of FMUs in and out.")


def _fail(exc: SSPError) -> None:
    err_console.print(f"[bold red]{len(exc.problems)} problem(s):[/]")
    for problem in exc.problems:
        err_console.print(f"  {problem}", markup=False, soft_wrap=True)
    raise typer.Exit(2)


@ssp_app.command("import")
def import_command(
        ssp: Annotated[Path, typer.Argument(help="the .ssp file (a zip with SystemStructure.ssd)")],
        output: Annotated[Path | None, typer.Option("--output", "-o", help="the scenario to write (default: "
                                                    "the SSP's name with .yaml, beside it)")] = None,
        fmu_dir: Annotated[Path | None, typer.Option("--fmu-dir", help="where the FMUs go (default: a folder "
                                                     "named after the scenario, beside it)")] = None,
        run: Annotated[bool, typer.Option("--run", help="run the scenario once written")] = False,
        loops: Annotated[str, typer.Option("--loops", help="a loop of feedthrough FMUs that declare no "
                                           "dependencies: 'delay' a connection of it, or 'iterate' it")] = "delay",
) -> None:
    """Turn an SSP into a scenario: components become FMU modules, connections `connect` entries,
    parameter bindings module params, the default experiment `world:`."""
    try:
        result = import_ssp(ssp, output, fmu_dir=fmu_dir, loops=loops)
    except SSPError as exc:
        _fail(exc)
        return
    sc = result.scenario
    world = sc["world"]
    console.print(f"{result.path}: {len(sc['modules'])} FMU modules, {len(sc['connect'])} connections, step "
                  f"{world['step']}, duration {world['duration']}; FMUs in {_folder(result.fmus)}",
                  markup=False, soft_wrap=True)
    for note in result.notes:
        console.print(f"  note: {note}", markup=False, soft_wrap=True)
    if run:
        _RUN_COMMAND[0](result.path, realtime=None, duration=None, log=None, live=False, live_rate=0.0, quiet=False)
    else:
        console.print(f"run it: dynabrain run {result.path}", markup=False, soft_wrap=True)


@ssp_app.command("export")
def export_command(
        scenario: Annotated[Path, typer.Argument(help="a scenario whose modules all are FMUs (world.core: null)")],
        output: Annotated[Path | None, typer.Option("--output", "-o", help="the .ssp to write (default: the "
                                                    "scenario's name with .ssp, here)")] = None) -> None:
    """Write the SSP of a scenario of FMUs: SystemStructure.ssd (SSP 1.0) and the FMUs under resources/."""
    target = output if output is not None else Path(scenario.with_suffix(".ssp").name)
    try:
        result = export_ssp(scenario, target)
    except ScenarioError as exc:
        fail_scenario(exc)
        return
    except SSPError as exc:
        _fail(exc)
        return
    checked = "checked against the SSP 1.0 schema" if result.validated else "not checked (FMPy ships no SSP schema)"
    console.print(f"{result.path}: SSD {result.version} ({checked}), {len(result.components)} components, "
                  f"{result.connections} connections, {len(result.resources)} FMUs", markup=False, soft_wrap=True)
    for item in result.left_out:
        console.print(f"  not in the SSP: {item}", markup=False, soft_wrap=True)


def _folder(paths: tuple[Path, ...]) -> str:
    if not paths:
        return "-"
    parents = {p.parent for p in paths}
    return str(parents.pop()) if len(parents) == 1 else ", ".join(sorted(str(p) for p in parents))


_RUN_COMMAND: list[Callable[..., None]] = []
"""The main CLI's ``run`` command, handed over by `register` (this file does not import the main one)."""


def register(app: typer.Typer, run_command: Callable[..., None]) -> None:
    """Add the ``ssp`` command group to the main CLI; ``run_command`` is its ``run``, for ``--run``."""
    _RUN_COMMAND[:] = [run_command]
    app.add_typer(ssp_app, name="ssp")
