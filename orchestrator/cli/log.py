"""Run outputs (``--log``, ``log:``, ``--live``) and the log commands (``replay``, ``plot``, ``log recover``).

Exit codes: 0 ok; 1 ``replay --verify`` found a divergence; 2 bad input (a missing, truncated or
foreign file, an unknown signal, a recorded scenario that no longer loads).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console

from ..kernel.errors import DynabrainError, ScenarioError

err = Console(stderr=True, highlight=False, soft_wrap=True)
out = Console(highlight=False, soft_wrap=True)
LIVE_PORT_ENV = "DYNABRAIN_LIVE_PORT"
"""Environment variable with the live view's port (default 8765; 0 for any free port)."""


class RunOutputs:
    """What a run writes besides its summary; `finish` is called with the run's result."""

    def __init__(self, logger: Any = None, live: Any = None, console: Console | None = None):
        self.logger, self.live, self.console = logger, live, console or err

    def finish(self, result: Any) -> None:
        """Record the expectation results, close the log (errors surface here, not at world.close)."""
        if self.logger is not None:
            self.logger.log_result(result)
            self.logger.close()
            stats = self.logger.stats
            self.console.print(f"log: {self.logger.path} ({os.path.getsize(self.logger.path) / 1024:.1f} KiB, "
                               f"{stats['messages']} messages, {stats['chunks']} chunks)", markup=False)
        if self.live is not None and sys.stdin.isatty():
            self.console.print(f"live view: the run is over; still serving {self.live.url}; press Enter to stop",
                               markup=False)
            with suppress(EOFError, KeyboardInterrupt):
                input()


def attach_run_outputs(world: Any, scenario: Any, *, log: Path | None, live: bool, console: Console,
                       live_rate_hz: float = 0.0) -> RunOutputs:
    """Attach the MCAP logger (``--log FILE``, else the scenario's ``log: {mcap: FILE}``, resolved against
    the scenario's folder) and the live view (``--live``; ``live_rate_hz``: ticks sent per simulated
    second, 0 for every tick) a run asks for."""
    from ..logs.logger import McapLogger

    cfg = scenario.model.log
    path = os.fspath(log) if log is not None else None
    if path is None and cfg.mcap:
        path = cfg.mcap if os.path.isabs(cfg.mcap) else os.path.join(scenario.dir, cfg.mcap)
    logger = None
    if path is not None:
        folder = os.path.dirname(os.path.abspath(path))
        try:
            os.makedirs(folder, exist_ok=True)
        except OSError as exc:
            raise DynabrainError(f"cannot create the folder of the log {path}: {exc.strerror}") from None
        # a scenario run never backticks (a failed tick discards nothing): no window needed
        logger = McapLogger(path, decimate=cfg.decimate, window=0).attach(world, scenario)
        console.print(f"recording to {path}", markup=False)
    view = None
    if live:
        from ..logs.live import DEFAULT_PORT, LiveView

        port = os.environ.get(LIVE_PORT_ENV, str(DEFAULT_PORT))
        if not port.isdigit():
            raise DynabrainError(f"{LIVE_PORT_ENV}={port!r} is not a port number")
        every = max(1, round(1e9 / (live_rate_hz * world.dt_ns))) if live_rate_hz > 0 else 1
        view = LiveView(port=int(port), every=every).attach(world)
        rate = f"{1e9 / (every * world.dt_ns):g} Hz of simulated time" + (" (every tick)" if every == 1 else "")
        console.print(f"live view: {view.url} (Foxglove: Open connection > Foxglove WebSocket), {rate}",
                      markup=False)
    return RunOutputs(logger, view, console)


# -- commands -------------------------------------------------------------------------------------------
def replay(log: Annotated[Path, typer.Argument(help="an MCAP log")],
           verify: Annotated[bool, typer.Option("--verify", help="re-simulate and compare every tick")] = False,
           publish: Annotated[bool, typer.Option("--publish", help="re-publish over Zenoh")] = False,
           speed: Annotated[float, typer.Option(help="--publish speed factor (1 = real time)")] = 1.0,
           listen: Annotated[list[str] | None, typer.Option(help="--publish: Zenoh endpoint to listen on "
                                                            "(default tcp/127.0.0.1:7447)")] = None,
           connect: Annotated[list[str] | None, typer.Option(help="--publish: Zenoh endpoint to connect to")] = None,
           events: Annotated[int, typer.Option(help="how many events to list")] = 40) -> None:
    """Summarize a log (duration, channels, events); --verify re-simulates it and compares bit for bit."""
    from ..logs.read import read_index
    from ..logs.replay import summarize

    with _bad_input():
        for line in summarize(read_index(log), max_events=events):
            out.print(line, markup=False)
        if publish:
            from dynabrain.bridge import publish_recording

            if listen or connect:
                from dynabrain.bridge.zenoh_io import Settings

                settings = Settings(listen=listen or [], connect=connect or [])
                publish_recording(os.fspath(log), speed=speed, settings=settings)
            else:
                publish_recording(os.fspath(log), speed=speed)
        if verify:
            _verify(log)


def _verify(log: Path) -> None:
    from ..logs.verify import verify

    result = verify(log)
    rate = f"{result.ticks} ticks re-simulated, {result.rows} rows compared in {result.wall_s:.2f} s " \
           f"({result.ticks_per_s:,.0f} ticks/s)"
    if result.ok:
        out.print(f"[green]verify: identical[/] up to tick {result.last_tick}: {rate}")
        return
    d = result.divergence
    out.print(f"[red]verify: DIVERGES[/] at tick {d.tick} (epoch {d.epoch}): {d.message}", soft_wrap=True)
    if d.signal is not None:
        out.print(f"  {d.signal}: recorded {d.recorded!r}", markup=False)
        out.print(f"  {' ' * len(d.signal)}  replayed {d.replayed!r}", markup=False)
    out.print(rate, markup=False)
    raise typer.Exit(1)


def plot(log: Annotated[Path, typer.Argument(help="an MCAP log")],
         signals: Annotated[list[str], typer.Argument(help="signals (core.aa.pos, aa.pos, aa.pos[2])")],
         output: Annotated[Path | None, typer.Option("--out", "-o", help="PNG file (default: LOG.png)")] = None
         ) -> None:
    """Plot signals of a log against simulated time (a PNG), with its events marked."""
    from ..logs.plot import plot as make_plot

    with _bad_input():
        path = make_plot(log, signals, output)
    out.print(f"wrote {path}", markup=False)


def recover(log: Annotated[Path, typer.Argument(help="a log left by a killed run")],
            output: Annotated[Path | None, typer.Option("--out", "-o",
                                                        help="where to write (default: LOG.recovered.mcap)")] = None
            ) -> None:
    """Write a valid MCAP with every complete chunk of a log cut short (a killed run)."""
    from ..logs.recover import recover as do_recover

    with _bad_input():
        path, report = do_recover(log, output)
    if report.complete:
        out.print(f"{log} was complete; nothing was lost", markup=False)
    elif len(report.damaged) > 1 or (report.damaged and report.damaged[0].end < os.path.getsize(log)):
        out.print(f"{log} is damaged in {len(report.damaged)} place(s) ({report.problem}): skipped "
                  f"{report.lost_bytes} bytes, kept every intact chunk after them", markup=False)
    else:
        out.print(f"{log} stops early ({report.problem}): lost its last {report.lost_bytes} bytes", markup=False)
    ticks = ""
    if report.ticks:
        span = report.ticks[1] - report.ticks[0] + 1
        gaps = f", {span - report.run_ticks} missing in gaps" if report.run_ticks and report.run_ticks < span else ""
        ticks = f", {report.run_ticks or span} run ticks from {report.ticks[0]} to {report.ticks[1]}{gaps}"
    out.print(f"wrote {path}: {report.chunks} chunks, {report.messages} messages{ticks}"
              + (f"; {report.moved} discarded messages moved to /discarded/..." if report.moved else ""), markup=False)


@contextmanager
def _bad_input() -> Iterator[None]:
    """Print a DynabrainError (a scenario's problems one a line) and exit with code 2."""
    try:
        yield
    except ScenarioError as exc:
        err.print(f"[bold red]the recorded scenario no longer loads: {len(exc.problems)} problem(s):[/]")
        for problem in exc.problems:
            err.print(f"  {problem}", markup=False)
        raise typer.Exit(2) from None
    except DynabrainError as exc:
        err.print(f"error: {exc}", markup=False)
        raise typer.Exit(2) from None


def register(app: typer.Typer) -> None:
    """Add ``replay``, ``plot`` and ``log recover`` to the main CLI."""
    app.command()(replay)
    app.command()(plot)
    group = typer.Typer(no_args_is_help=True, help="Work on log files.")
    group.command()(recover)
    app.add_typer(group, name="log")
