"""Run outputs (``--log``, ``log:``, ``--live``, ``--view``) and the log commands (``replay``, ``plot``, ``view``,
``log recover``).

Exit codes: 0 ok; 1 ``replay --verify`` found a divergence; 2 bad input (a missing, truncated or
foreign file, an unknown signal, a recorded scenario that no longer loads).
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

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
        """Record the expectation results, close the log (errors surface here, not at world.close); send the
        results to the live view (a client that connects later gets them too)."""
        if self.live is not None:
            self.live.log_result(result)
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
                       live_rate_hz: float = 0.0, live_port: int | None = None,
                       ros2_schemas: bool = False) -> RunOutputs:
    """Attach the MCAP logger (``--log FILE``, else the scenario's ``log: {mcap: FILE}``, resolved against
    the scenario's folder; ``ros2_schemas`` or the scenario's ``log: {ros2_schemas: true}``: also ROS 2
    messages) and the live view (``--live``; ``live_rate_hz``: ticks sent per simulated second, 0 for every
    tick; ``live_port``: ``--live-port``) a run asks for."""
    from ..logs.logger import McapLogger

    cfg = scenario.model.log
    path = os.fspath(log) if log is not None else None
    if path is None and cfg.mcap:
        path = cfg.mcap if os.path.isabs(cfg.mcap) else os.path.join(scenario.dir, cfg.mcap)
    view = None
    if live:  # first: a port in use stops the run before anything is recorded
        view = live_options(live_port, live_rate_hz, world.dt_ns).start(world, scenario)
        console.print(f"live view: {view.url} (Foxglove: Open connection > Foxglove WebSocket), "
                      f"{live_rate(view.every, world.dt_ns)}", markup=False)
    logger = None
    if path is not None:
        folder = os.path.dirname(os.path.abspath(path))
        try:
            os.makedirs(folder, exist_ok=True)
        except OSError as exc:
            raise DynabrainError(f"cannot create the folder of the log {path}: {exc.strerror}") from None
        # a scenario run never backticks (a failed tick discards nothing): no window needed
        ros2 = ros2_schemas or cfg.ros2_schemas
        logger = McapLogger(path, decimate=cfg.decimate, window=0, ros2=ros2).attach(world, scenario)
        console.print(f"recording to {path}" + (" (with ROS 2 messages)" if ros2 else ""), markup=False)
    return RunOutputs(logger, view, console)


def live_options(port: int | None, rate_hz: float = 0.0, dt_ns: int = 1) -> Any:
    """The live view's `LiveOptions`: the port of ``--live-port``, else of ``DYNABRAIN_LIVE_PORT``, else 8765
    (then a port in use means another free one); ``rate_hz``: ticks sent per simulated second (0: all)."""
    from ..logs.live import DEFAULT_PORT, LiveOptions

    option: str | None = "--live-port"
    if port is None:
        text = os.environ.get(LIVE_PORT_ENV)
        option = LIVE_PORT_ENV if text is not None else None
        if text is not None and not text.isdigit():
            raise DynabrainError(f"{LIVE_PORT_ENV}={text!r} is not a port number")
        port = int(text) if text is not None else DEFAULT_PORT
    if not 0 <= port <= 65535:
        raise DynabrainError(f"{option} {port} is not a port number (0 to 65535; 0: any free port)")
    every = max(1, round(1e9 / (rate_hz * dt_ns))) if rate_hz > 0 else 1
    return LiveOptions(port=port, port_option=option, every=every)


def live_rate(every: int, dt_ns: int) -> str:
    return f"{1e9 / (every * dt_ns):g} Hz of simulated time" + (" (every tick)" if every == 1 else "")


LivePortOpt = Annotated[int | None, typer.Option(
    "--live-port", help=f"--live: the WebSocket port (default ${LIVE_PORT_ENV}, else 8765, else any free one; "
                        "0: any free port); a port asked for and in use is an error")]


VIEW_PORT = 9090
"""The Rerun web viewer's default port (Rerun's own default)."""
ViewOpt = Annotated[bool, typer.Option(
    "--view", help="show the log in Rerun's web viewer (served on loopback; rerun-sdk, the [view] extra)")]
ViewPortOpt = Annotated[int, typer.Option(
    "--view-port", help="--view: the web viewer's port (0: any free one); in use: another free one")]


def show_in_rerun(log: Path | str, *, save: Path | None = None, port: int = VIEW_PORT, serve: bool = True) -> None:
    """``dynabrain view``: the log's Rerun recording (``save``, else a temporary file), served in Rerun's web
    viewer on loopback until Enter (on a terminal) or Ctrl-C; errors as `DynabrainError`."""
    import tempfile

    from ..logs.rerun_view import record_log, require_rerun

    require_rerun()
    if not 0 <= port <= 65535:
        raise DynabrainError(f"--view-port {port} is not a port number (0 to 65535; 0: any free port)")
    with tempfile.TemporaryDirectory(prefix="dynabrain-view-") as tmp:
        rrd = Path(save) if save is not None else Path(tmp) / (Path(log).stem + ".rrd")
        report = record_log(log, rrd)
        futures = f", {len(report.imagined)} imagined futures" if report.imagined else ""
        out.print(f"rerun: {rrd if save is not None else 'recording'}: {report.bodies} bodies drawn, {report.poses} "
                  f"poses, {report.signals} signals, {report.events} events{futures}", markup=False)
        if serve:
            _serve_rerun(rrd, port)


def view_after_run(log: str, port: int, *, temporary: bool) -> None:
    """``run --view``: the run's log shown in Rerun; a temporary log (no ``--log``) is removed after."""
    try:
        with _bad_input():
            show_in_rerun(log, port=port)
    finally:
        if temporary:
            import shutil

            shutil.rmtree(os.path.dirname(log), ignore_errors=True)


def start_rerun_live(world: Any, port: int) -> Any:
    """``serve --view``: the world streamed to Rerun's web viewer (`logs.rerun_live.RerunLive`), its address
    printed; the caller closes it."""
    from ..logs.rerun_live import RerunLive

    live = RerunLive(web_port=_port_or_free(port), grpc_port=_port_or_free(0)).attach(world)
    print(f"rerun: open {live.url}", flush=True)
    return live


def _serve_rerun(rrd: Path, port: int) -> None:
    import socket
    import time

    from ..logs.rerun_view import serve_rrd, viewer_url

    web, grpc = _port_or_free(port), _port_or_free(0)
    proc = serve_rrd(rrd, web_port=web, grpc_port=grpc)
    try:
        end = time.monotonic() + 20
        while socket.socket().connect_ex(("127.0.0.1", web)) != 0:
            if proc.poll() is not None or time.monotonic() > end:
                why = proc.stderr.read().decode(errors="replace")[-400:] if proc.poll() is not None else "no answer"
                raise DynabrainError(f"the rerun web viewer did not start: {why.strip()}")
            time.sleep(0.1)
        out.print(f"rerun: open {viewer_url(web, grpc)}", markup=False)
        if sys.stdin.isatty():
            out.print("press Enter to stop", markup=False)
            with suppress(EOFError, KeyboardInterrupt):
                input()
        else:
            import signal

            def interrupt(_sig: int, _frame: Any) -> None:
                raise KeyboardInterrupt

            previous = signal.signal(signal.SIGTERM, interrupt)  # a SIGTERM ends it as Ctrl-C does: cleaned up
            try:
                with suppress(KeyboardInterrupt):
                    proc.wait()
            finally:
                signal.signal(signal.SIGTERM, previous)
    finally:
        proc.kill()
        proc.wait()


def _port_or_free(port: int) -> int:
    """``port`` when it is free on loopback, else (or for 0) a free one."""
    import socket

    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# -- commands -------------------------------------------------------------------------------------------
def view(log: Annotated[Path, typer.Argument(help="an MCAP log")],
         save: Annotated[Path | None, typer.Option("--save", help="keep the Rerun recording (.rrd) there")] = None,
         port: ViewPortOpt = VIEW_PORT,
         serve: Annotated[bool, typer.Option("--serve/--no-serve", help="serve the web viewer (--no-serve: only "
                                                                        "write --save)")] = True) -> None:
    """Show a log in Rerun's web viewer (loopback): the bodies at their poses, the signals, the events and
    expectation results, and each imagined future beside what happened."""
    if not serve and save is None:
        err.print("error: --no-serve writes only the recording: name it with --save", markup=False)
        raise typer.Exit(2)
    with _bad_input():
        show_in_rerun(log, save=save, port=port, serve=serve)


def replay(log: Annotated[Path, typer.Argument(help="an MCAP log")],
           verify: Annotated[bool, typer.Option("--verify", help="re-simulate and compare every tick")] = False,
           publish: Annotated[bool, typer.Option("--publish", help="re-publish over Zenoh")] = False,
           speed: Annotated[float, typer.Option(help="--publish speed factor (1 = real time)")] = 1.0,
           listen: Annotated[list[str] | None, typer.Option(help="--publish: Zenoh endpoint to listen on "
                                                            "(default tcp/127.0.0.1:7447)")] = None,
           connect: Annotated[list[str] | None, typer.Option(help="--publish: Zenoh endpoint to connect to")] = None,
           live: Annotated[bool, typer.Option(
               "--live", help="play the log to Foxglove over WebSocket (loopback), at --speed, once a client "
                              "subscribes; with --publish both at once")] = False,
           live_port: LivePortOpt = None,
           view_: ViewOpt = False,
           view_port: ViewPortOpt = VIEW_PORT,
           events: Annotated[int, typer.Option(help="how many events to list")] = 40,
           allow_python: Annotated[list[str] | None, typer.Option(
               "--allow-python", help="--verify: a package whose module classes the log may name, besides "
                                      "dynabrain's own, the registered ones and the scenario folder's (repeatable)")
           ] = None,
           allow_version_mismatch: Annotated[bool, typer.Option(
               "--allow-version-mismatch", help="--verify: verify a log written by another major or minor "
                                                "version of dynabrain or MuJoCo")] = False) -> None:
    """Summarize a log (duration, channels, events); --verify re-simulates it and compares bit for bit;
    --publish plays it over Zenoh, --live to Foxglove."""
    from ..logs.read import read_index
    from ..logs.replay import summarize

    with _bad_input():
        for line in summarize(read_index(log), max_events=events):
            out.print(line, markup=False)
        view = _live_replay(log, live_port, speed) if live else None
        try:
            if view is not None and not publish:
                _play(view)
            elif publish:
                thread = _play_beside(view)
                _publish(log, speed, listen, connect)
                if thread is not None:
                    thread.join()
            if view is not None and sys.stdin.isatty():
                out.print(f"live view: the log is over; still serving {view.url}; press Enter to stop", markup=False)
                with suppress(EOFError, KeyboardInterrupt):
                    input()
        finally:
            if view is not None:
                view.close()
        if view_:
            show_in_rerun(log, port=view_port)
        if verify:
            _verify(log, tuple(allow_python or ()), allow_version_mismatch)


def _live_replay(log: Path, port: int | None, speed: float) -> Any:
    from ..logs.replay import LogView

    options = live_options(port)
    view = LogView(log, port=options.port, port_option=options.port_option, speed=speed).start()
    out.print(f"live view: {view.url} (Foxglove: Open connection > Foxglove WebSocket); plays once a client "
              "subscribes", markup=False)
    return view


def _play(view: Any) -> None:
    result = view.play()
    out.print(f"live view: played {result.messages} messages in {result.wall_s:.3f} s", markup=False)


def _play_beside(view: Any) -> Any:
    """The live view's replay on a thread of its own (beside the Zenoh one)."""
    if view is None:
        return None
    import threading

    thread = threading.Thread(target=_play, args=(view,), daemon=True, name="dynabrain-replay-live")
    thread.start()
    return thread


def _publish(log: Path, speed: float, listen: list[str] | None, connect: list[str] | None) -> None:
    from dynabrain.bridge import publish_recording

    if listen or connect:
        from dynabrain.bridge.zenoh_io import Settings

        publish_recording(os.fspath(log), speed=speed, settings=Settings(listen=listen or [], connect=connect or []))
    else:
        publish_recording(os.fspath(log), speed=speed)


def _verify(log: Path, allow_python: tuple[str, ...] = (), allow_version_mismatch: bool = False) -> None:
    from ..logs.verify import verify

    quiet = logging.getLogger("dynabrain").getEffectiveLevel() >= logging.ERROR  # (dynabrain -q)
    with Progress(TextColumn("verify"), BarColumn(), MofNCompleteColumn(), TextColumn("rows"), TimeRemainingColumn(),
                  console=err, transient=True, disable=quiet) as bar:
        task = bar.add_task("verify", total=None)
        result = verify(log, allow_python=allow_python, allow_version_mismatch=allow_version_mismatch,
                        progress=lambda done, total: bar.update(task, completed=done, total=total))
    out.print(f"verify: {result.versions}", markup=False)
    for first, last in result.gaps:
        out.print(f"verify: gap: the recording lacks ticks {first}..{last} (lost chunks); stepped through, not "
                  "compared", markup=False)
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
         output: Annotated[Path | None, typer.Option("--out", "-o", help="PNG file (default: LOG.png)")] = None,
         events: Annotated[str | None, typer.Option(
             "--events", help="event kinds to mark, comma-separated (set,make_joint); none for none (default: all "
                              "but the log's bookkeeping)")] = None,
         imagined: Annotated[bool, typer.Option(
             "--imagined", help="overlay the log's imagined futures of the same signals (dashed)")] = False,
         expectations: Annotated[bool, typer.Option(
             "--expectations/--no-expectations", help="a strip with the run's expectation results")] = True,
         split: Annotated[bool, typer.Option(
             "--split", help="a panel per component (x, y, z each its own; also when their scales differ)")] = False
         ) -> None:
    """Plot signals of a log against simulated time (a PNG): events marked (repeated edits as a band), the
    expectation results, the imagined futures with --imagined."""
    from ..logs.plot import PlotOptions
    from ..logs.plot import plot as make_plot

    kinds = None if events is None else tuple(k.strip() for k in events.split(",") if k.strip() and k != "none")
    with _bad_input():
        path = make_plot(log, signals, output, PlotOptions(kinds, imagined, expectations, split))
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
    """Add ``replay``, ``plot``, ``view`` and ``log recover`` to the main CLI."""
    app.command()(replay)
    app.command()(plot)
    app.command()(view)
    group = typer.Typer(no_args_is_help=True, help="Work on log files.")
    group.command()(recover)
    app.add_typer(group, name="log")
