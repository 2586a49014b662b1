"""The ``dynabrain`` command line. Exit codes: 0 ok, 1 an expectation failed or a run failed,
2 bad input (a scenario that does not validate). A run that ends early because a module asked to end
the simulation (an FMU's terminate request) ended normally: 0 when its expectations hold (one it did
not reach fails, so 1), never 1 for the request itself.

Options before the command: ``--version``; ``-v`` / ``--verbose`` (dynabrain's log messages from INFO
on, ``-vv`` from DEBUG; by default warnings and errors), ``-q`` / ``--quiet`` (errors only, and no
progress bar); ``--install-completion`` / ``--show-completion`` (shell completion).
"""

from __future__ import annotations

import logging
import sys
import tempfile
import time
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from ..kernel.errors import DynabrainError, ScenarioError
from ..kernel.extras import hint
from ..kernel.units import format_duration
from ..scenario.model import Scenario, load_scenario
from ..scenario.runner import RunResult, run_scenario
from .common import console, err_console, fail_scenario
from .examples import resolve_scenario
from .log import VIEW_PORT, ViewOpt, ViewPortOpt, view_after_run

_log = logging.getLogger("dynabrain.cli")
app = typer.Typer(no_args_is_help=True, help="dynabrain: a co-simulation orchestrator a robot brain embeds.")
_quiet = False
"""``-q`` before the command: no progress bar either."""


AllowPythonOpt = Annotated[list[str] | None, typer.Option(
    "--allow-python", help="a package whose module classes the scenario may name, besides dynabrain's own, the "
                           "registered ones and the scenario folder's modules (repeatable)")]


def _load(path: Path, allow_python: list[str] | None) -> Scenario:
    """The scenario at ``path`` with the packages the user allowed, or exit 2 with its problems."""
    try:
        return load_scenario(path, allow_python or ())
    except ScenarioError as exc:
        fail_scenario(exc)
        raise  # not reached: fail_scenario exits


def _version(value: bool) -> None:
    if value:
        try:
            version = importlib_metadata.version("dynabrain")
        except importlib_metadata.PackageNotFoundError:
            version = "unknown (not installed)"
        console.print(f"dynabrain {version}", markup=False)
        raise typer.Exit()


@app.callback()
def _options(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                          help="print the version and exit"),
             verbose: int = typer.Option(0, "--verbose", "-v", count=True,
                                         help="more messages: -v info, -vv debug"),
             quiet: bool = typer.Option(False, "--quiet", "-q", help="errors only, and no progress bar")) -> None:
    """dynabrain: a co-simulation orchestrator a robot brain embeds."""
    global _quiet
    _quiet = quiet
    level = logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
    root = logging.getLogger("dynabrain")
    root.setLevel(level)
    if not any(getattr(h, "_dynabrain_cli", False) for h in root.handlers):
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
        handler._dynabrain_cli = True  # type: ignore[attr-defined]
        root.addHandler(handler)


@app.command()
def run(scenario: Path = typer.Argument(..., help="scenario YAML file, or the name of a shipped one (two_cubes)"),
        realtime: bool | None = typer.Option(None, "--realtime/--no-realtime",
                                             help="pace the run at real time (default: with --live, or as the "
                                                  "scenario says)"),
        duration: str | None = typer.Option(None, help="override world.duration (e.g. 2s)"),
        log: Path | None = typer.Option(None, "--log", help="record the run to an MCAP file"),
        live: bool = typer.Option(False, "--live", help="serve the run to Foxglove over WebSocket (loopback); "
                                                        "paces it at real time unless --no-realtime"),
        live_rate: float = typer.Option(0.0, "--live-rate", min=0.0,
                                        help="--live: ticks sent per simulated second (0: every tick)"),
        live_port: int | None = typer.Option(None, "--live-port", help="--live: the WebSocket port (default "
                                             "$DYNABRAIN_LIVE_PORT, else 8765, else any free one; 0: any free "
                                             "port); a port asked for and in use is an error"),
        ros2_schemas: bool = typer.Option(False, "--ros2-schemas", help="--log: also write /joint_states, /clock "
                                          "and /tf as ROS 2 messages (CDR, ros2msg schemas) for rosbag2 tools"),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bar"),
        allow_python: AllowPythonOpt = None, view: ViewOpt = False, view_port: ViewPortOpt = VIEW_PORT) -> None:
    """Run a scenario to its end and check its expectations."""
    scenario = resolve_scenario(scenario)
    if not scenario.exists() and scenario.parent == Path("."):
        err_console.print(f"no file {scenario} here, and no shipped scenario of that name (`dynabrain examples` "
                          "lists them)", markup=False)
    t0 = time.perf_counter()
    sc = _load(scenario, allow_python)
    if duration is not None:
        sc.duration_ns = _duration_option(duration)
    try:
        world = sc.build()
    except ScenarioError as exc:
        fail_scenario(exc)
    _log.info("%s: built in %.3f s", scenario, time.perf_counter() - t0)
    _log.debug("world %s: step %s, schedule %s, %d signals, history %s", world.name,
               format_duration(world.dt_ns), " -> ".join(world.schedule_order()), len(world.signals),
               world.history.describe())
    from .log import attach_run_outputs

    temporary = view and log is None and not sc.model.log.mcap  # --view shows a log: a temporary one unless asked
    if temporary:
        log = Path(tempfile.mkdtemp(prefix="dynabrain-view-")) / f"{sc.model.name}.mcap"
    try:
        outputs = attach_run_outputs(world, sc, log=log, live=live, console=err_console, live_rate_hz=live_rate,
                                     live_port=live_port, ros2_schemas=ros2_schemas)
        with Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.fields[t]}"),
                      TimeRemainingColumn(), console=console, transient=True, disable=quiet or _quiet) as bar:
            task = bar.add_task(sc.model.name, total=sc.duration_ns // world.dt_ns, t="")

            def progress(done: int, total: int) -> None:
                bar.update(task, completed=done, t=f"t={done * world.dt_ns / 1e9:.3f}s")

            if realtime is None:  # a live view is watched: at real time, unless told otherwise
                realtime = True if live else None
            result = run_scenario(sc, world, progress=progress, realtime=realtime)
        history = world.history.describe()
        outputs.finish(result)
    finally:
        core = world.core
        world.close()  # also on Ctrl-C: observers (the log) are closed and stay readable
    _summary(result, history, quiet=_quiet)
    _engine_notes(core)
    if view:
        view_after_run(outputs.logger.path, view_port, temporary=temporary)
    raise typer.Exit(0 if result.ok else 1)


def _engine_notes(core: Any) -> None:
    """What the engine said that the run did not show (MuJoCo: how many of its warnings were repeats)."""
    line = core.engine_notes() if core is not None else None
    if line and not _quiet:
        err_console.print(line, markup=False)


def _summary(result: RunResult, history: str, *, quiet: bool = False) -> None:
    """The run's summary and its checks; ``quiet`` (``dynabrain -q``): only what went wrong, and the verdict."""
    _log.debug("%s: %d expectations, %d ticks in %.3f s", result.scenario, len(result.expectations), result.ticks,
               result.wall_time)
    if not quiet:
        console.print(f"[bold]{result.scenario}[/]: simulated {result.sim_time:.3f} s ({result.ticks} ticks) in "
                      f"{result.wall_time:.3f} s wall, real-time factor {result.realtime_factor:.1f}")
        console.print(f"history: {history}", markup=False)
    if result.error:
        console.print(f"[bold red]run stopped:[/] {escape(result.error)}")
    if result.ended:
        console.print(f"[bold]run ended:[/] {escape(result.ended)}")
    shown = [e for e in result.expectations if not (quiet and e.passed)]
    if shown:
        table = Table(show_header=True, header_style="bold")
        table.add_column("check")
        table.add_column("when")
        table.add_column("result")
        for exp in shown:
            when = f"t={exp.start * result.dt_ns / 1e9:g}s"
            if exp.end != exp.start:
                when += f"..{exp.end * result.dt_ns / 1e9:g}s"
            status = "[green]pass[/]" if exp.passed else f"[red]FAIL[/] {exp.detail}"
            table.add_row(exp.label, when, status)
        console.print(table)
    verdict = "[green]all checks passed[/]" if result.ok else "[red]failed[/]"
    console.print(verdict)


def _duration_option(text: str) -> int:
    """``--duration`` in nanoseconds, or exit 2 naming what is wrong with it."""
    from ..kernel.units import NS_PER_S, parse_duration_ns
    from ..scenario.limits import MAX_DURATION_S

    try:
        ns = parse_duration_ns(text)
        if not 0 < ns <= MAX_DURATION_S * NS_PER_S:
            raise DynabrainError(f"a duration is above 0 and at most {MAX_DURATION_S:g} s")
    except DynabrainError as exc:
        err_console.print(f"--duration {text}: {exc}", markup=False)
        raise typer.Exit(2) from None
    return ns


@app.command()
def check(scenario: Path = typer.Argument(..., help="scenario YAML file"),
          allow_python: AllowPythonOpt = None) -> None:
    """Validate a scenario (every problem at once) and show what it builds; a module class outside
    dynabrain's own, the registered ones and the scenario folder is refused unimported (--allow-python)."""
    sc = _load(scenario, allow_python)
    try:
        world = sc.build()
    except ScenarioError as exc:
        fail_scenario(exc)
    try:
        console.print(f"[bold]{sc.model.name}[/]: valid")
        console.print(f"step {format_duration(world.dt_ns)}, duration {format_duration(sc.duration_ns)}, "
                      f"core {world.core.ENGINE if world.core else 'none'}")
        table = Table("module", "class", "period", "inputs", "outputs", header_style="bold")
        for step in world.structure.plan:
            rec = step.record
            table.add_row(rec.name, type(rec.module).__name__, format_duration(rec.period_ns),
                          str(len(rec.inputs)), str(len(rec.outputs)))
        console.print(table)
        console.print(f"schedule: {' -> '.join(world.schedule_order())}")
        for conn in world.connections:
            console.print(f"  {conn}", markup=False)
        if world.core is not None:
            console.print(f"objects: {len(world.core.objects())}, selected: {len(world.core.selection)}")
        console.print(f"expectations: {len(sc.expectations)}; events: {len(sc.model.events)}")
    finally:
        world.close()


def _register_plugins() -> None:
    """Command groups that live in their own files (FMU authoring, logs, the Zenoh bridge)."""
    from . import examples, fmu, log, serve, ssp

    fmu.register(app)
    log.register(app)
    serve.register(app)
    examples.register(app)
    ssp.register(app, run)


_register_plugins()


def command() -> Any:
    """The ``dynabrain`` command as click runs it, its help without type placeholders: a flag (``--help``
    too) shows no ``<bool>``, a repeatable option or argument ``<text>`` (one value each, not
    ``<list[str]>``), and an argument its name in capitals (``{LOG}``: required, not ``{log}``)."""
    cmd = typer.main.get_command(app)
    todo = [cmd]
    while todo:
        current = todo.pop()
        todo += list(getattr(current, "commands", {}).values())
        current.get_help_option = _plain_help_option(current.get_help_option)
        for param in current.params:  # (typer's own click: told apart by kind, not class)
            if param.param_type_name == "option" and getattr(param, "is_flag", False):
                param.metavar = ""
            elif param.param_type_name == "option" and param.multiple and param.metavar is None:
                param.metavar = "<text>"
            elif param.param_type_name == "argument" and param.name:
                param.metavar = param.metavar or param.name.upper()
                if param.nargs != 1:
                    param.display_type_rich = lambda ctx: "<text>"
    return cmd


def _plain_help_option(make: Any) -> Any:
    def help_option(ctx: Any) -> Any:
        option = make(ctx)
        if option is not None:
            option.metavar = ""
        return option

    return help_option


def main() -> None:
    try:
        command()(prog_name="dynabrain")
    except ModuleNotFoundError as exc:  # a part of dynabrain that is not installed: name its extra
        missing = hint(exc)
        if missing is None:
            raise
        err_console.print(f"error: {missing}", markup=False)
        raise SystemExit(2) from None
    except DynabrainError as exc:
        err_console.print(f"error: {exc}", markup=False)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
