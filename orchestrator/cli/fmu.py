"""``dynabrain fmu new|build|check``: FMU authoring.

- ``new NAME``: a C FMU folder (fmu.yaml and NAME.c) that builds and passes its check as generated;
- ``build DIR``: compile against the FMI headers, package and validate (``--fmi 2|3``, default every
  version fmu.yaml lists; ``-o`` a folder to copy the .fmu files into, else they stay in the cache);
- ``check FILE``: validate a .fmu (or a source folder, built first), run it briefly, check the
  save/restore round trip, replay equality and fork, in a child process (an FMU that crashes gets a
  verdict; ``--ticks``: no run goes further; an FMU that asks to end the simulation is checked up
  to there). Each problem is printed once.

Exit codes: 0 ok, 1 a check failed, 2 bad input (a build error, a broken FMU).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from ..kernel.errors import DynabrainError

console = Console(highlight=False)
err_console = Console(stderr=True, highlight=False, soft_wrap=True)

fmu_app = typer.Typer(add_completion=False, no_args_is_help=True,
                      help="Write, build and check FMUs (FMI 2.0 / 3.0 co-simulation, in C).")


def _fail(exc: DynabrainError) -> None:
    err_console.print(f"error: {exc}", markup=False)
    raise typer.Exit(2)


@fmu_app.command("new")
def new(name: Annotated[str, typer.Argument(help="the FMU's name (a C identifier)")],
        folder: Annotated[Path, typer.Option("--dir", "-d", help="where to create it")] = Path(".")) -> None:
    """Create a C FMU folder that builds and passes its check as generated."""
    from ..fmu.scaffold import new_fmu

    try:
        path = new_fmu(name, folder)
    except DynabrainError as exc:
        _fail(exc)
    console.print(f"created {path}: edit fmu.yaml and {name}.c, then `dynabrain fmu check {path}`", markup=False)


@fmu_app.command("build")
def build(folder: Annotated[Path, typer.Argument(help="a source folder with fmu.yaml")],
          fmi: Annotated[int | None, typer.Option("--fmi", help="2 or 3 (default: every version listed)")] = None,
          output: Annotated[Path | None, typer.Option("--output", "-o", help="folder for the .fmu files")] = None,
          force: Annotated[bool, typer.Option("--force", help="rebuild even when cached")] = False) -> None:
    """Compile, package and validate the FMU in FOLDER."""
    from ..fmu.build import build_fmu
    from ..fmu.spec import load_spec

    try:
        spec = load_spec(folder)
        versions = spec.fmi if fmi is None else (fmi,)
        for version in versions:
            dest = None if output is None else output / f"{spec.name}-fmi{version}.fmu"
            path = build_fmu(folder, version, dest, force=force)
            console.print(f"FMI {version}.0: {path}", markup=False)
    except DynabrainError as exc:
        _fail(exc)


@fmu_app.command("check")
def check(fmu: Annotated[str, typer.Argument(help="a .fmu file or a source folder (add @fmi3 to pick a version)")],
          ticks: Annotated[int, typer.Option(min=12, help="ticks every run of the check may take at most (the "
                                                          "FMU's default step each; at least 12)")] = 40) -> None:
    """Validate an FMU, run it briefly and check save/restore, replay and fork, in a process of its own
    (an FMU that crashes gets a verdict naming the call and the probe). An FMU that asks to end the
    simulation is checked up to there."""
    from ..fmu.checkproc import check_fmu_apart

    try:
        report, output = check_fmu_apart(fmu, ticks=ticks)
    except DynabrainError as exc:
        _fail(exc)
    for line in output:  # the FMU's log lines, each once (its errors are in the report)
        err_console.print(line, markup=False)
    if report.info is None:
        err_console.print(f"error: {report.problems[0]}", markup=False)
        raise typer.Exit(2)
    info = report.info
    console.print(f"{info.label}: {len(info.inputs)} inputs, {len(info.outputs)} outputs, {len(info.params)} "
                  f"parameters; get/set state: {info.can_get_set}, serialize: {info.can_serialize}", markup=False)
    console.print(str(report), markup=False)
    raise typer.Exit(0 if report.ok else 1)


def register(app: typer.Typer) -> None:
    """Add the ``fmu`` command group to the main CLI."""
    app.add_typer(fmu_app, name="fmu")
