"""``dynabrain serve``: expose a World over Zenoh; ``dynabrain robot-emulator``: a robot on the bridge's
robot link, emulated in a process of its own. See ``bridge/PROTOCOL.md``."""

from __future__ import annotations

import logging
import os
import signal
import threading
from pathlib import Path
from typing import Annotated

import typer

from ..kernel.errors import DynabrainError, ScenarioError
from ..kernel.units import parse_duration_ns
from .common import fail_scenario, load_or_exit
from .log import VIEW_PORT, LivePortOpt, ViewPortOpt, live_options, start_rerun_live
from .log import live_rate as live_rate_text

ListenOpt = Annotated[list[str] | None, typer.Option(
    "--listen", help="endpoint to listen on (repeatable); port 0 picks a free port (default: tcp/127.0.0.1:7447)")]
ConnectOpt = Annotated[list[str] | None, typer.Option(
    "--connect", help="endpoint to connect to: another peer or a router (repeatable)")]
ConfigOpt = Annotated[Path | None, typer.Option(
    "--zenoh-config", help="Zenoh JSON5 config (router, TLS, user/password, access control); "
                           "see bridge/zenoh-secure.json5")]
ModeOpt = Annotated[str | None, typer.Option(
    "--mode", help="Zenoh mode: peer (default) or client (through a router given by --connect)")]
LeaseOpt = Annotated[str | None, typer.Option(
    "--lease", help="how long a silent peer counts as alive (e.g. 2s; Zenoh's default is 10s)")]


def register(app: typer.Typer) -> None:
    """Add ``serve`` and ``robot-emulator`` to the main CLI."""
    app.command("serve")(serve)
    app.command("robot-emulator")(robot_emulator)


def _settings(listen: list[str] | None, connect: list[str] | None, config: Path | None, lease: str | None,
              mode: str | None, default_listen: list[str]):
    from dynabrain.bridge.zenoh_io import Settings

    if mode not in (None, "peer", "client"):
        raise DynabrainError(f"--mode is peer or client, got {mode!r}")
    if listen is None and config is None and mode != "client":
        listen = default_listen
    return Settings(listen=listen or [], connect=connect or [], config_file=str(config) if config else None,
                    lease_ms=None if lease is None else parse_duration_ns(lease) // 1_000_000, mode=mode)


def _build(scenario: Path):
    sc = load_or_exit(scenario)
    try:
        return sc, sc.build()
    except ScenarioError as exc:
        fail_scenario(exc)


def _robots(items: list[str] | None) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in items or []:
        name, sep, servo = item.partition("=")
        if not sep or not name or not servo:
            raise DynabrainError(f"--robot takes NAME=SERVO_MODULE (e.g. arm=servo), got {item!r}")
        out[name] = servo
    return out


def _positive_seconds(value: str, option: str) -> float:
    seconds = parse_duration_ns(value) / 1e9
    if seconds <= 0:
        raise DynabrainError(f"{option} must be a positive duration (e.g. 2s), got {value!r}")
    return seconds


def _ros2_options(rate_hz: float):
    from dynabrain.bridge.ros2 import Ros2Options

    domain = os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
    if not domain.isdigit():
        raise DynabrainError(f"ROS_DOMAIN_ID must be a whole number >= 0, got {domain!r}")
    if not rate_hz > 0:
        raise DynabrainError(f"--ros2-rate must be a positive number of Hz, got {rate_hz!r}")
    return Ros2Options(domain_id=int(domain), rate_hz=rate_hz)


def _wait_for_signal(stop: threading.Event) -> None:
    def handler(signum, frame) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)
    while not stop.wait(0.5):
        pass


def serve(scenario: Annotated[Path, typer.Argument(help="scenario YAML file")],
          listen: ListenOpt = None, connect: ConnectOpt = None, zenoh_config: ConfigOpt = None,
          name: Annotated[str | None, typer.Option(help="key-space name (dynabrain/<name>/...)")] = None,
          stream: Annotated[list[str] | None, typer.Option(
              "--stream", help="signal or pattern in the state stream (repeatable) (default: body poses, joint states)")
          ] = None,
          decimate: Annotated[int, typer.Option(help="publish state every N ticks (0: none)")] = 1,
          robot: Annotated[list[str] | None, typer.Option(
              "--robot", help="a robot rig NAME=SERVO: motion commands set module SERVO's targets")] = None,
          deadline: Annotated[str, typer.Option(help="age beyond which a robot command is dropped")] = "100ms",
          allow_python: Annotated[list[str] | None, typer.Option(
              "--allow-python", help="module classes brains may add (fnmatch pattern, repeatable) "
                                     "(default: dynabrain.*)")] = None,
          lease: LeaseOpt = None, mode: ModeOpt = None,
          start: Annotated[bool, typer.Option("--start", help="run the world's loop from the start")] = False,
          realtime: Annotated[bool, typer.Option("--realtime", help="with --start: at real time")] = False,
          batch_backend: Annotated[str, typer.Option(
              "--batch-backend", help="how `batch` calls run the world's futures: auto, serial, processes or ray "
                                      "(auto: worker processes when there is more than one core)")] = "auto",
          batch_workers: Annotated[int | None, typer.Option(
              "--batch-workers", help="worker processes (or Ray actors) of `batch` calls (default: every core)")
          ] = None,
          batch_max_ticks: Annotated[int, typer.Option(
              "--batch-max-ticks", help="most branches x ticks in one `batch` call")] = 1_000_000,
          tokenless_lease: Annotated[str, typer.Option(
              "--tokenless-lease", help="most silence a hold lasts while its brain has no liveliness token")] = "10s",
          trial_params: Annotated[bool, typer.Option(
              "--trial-params/--no-trial-params",
              help="try a brain's run-time parameter change on a fork, one tick, and refuse one that makes the tick "
                   "fail")] = True,
          ros2: Annotated[bool, typer.Option(
              "--ros2", help="also speak ROS 2 (rmw_zenoh, Jazzy): /clock, /tf, joint_states, and joint commands to "
                             "each --robot; domain from ROS_DOMAIN_ID")] = False,
          ros2_rate: Annotated[float, typer.Option(
              "--ros2-rate", help="ROS 2 messages per second of simulated time")] = 100.0,
          live: Annotated[bool, typer.Option(
              "--live", help="also serve the world to Foxglove over WebSocket (loopback): /bus, /tf, /scene and "
                             "events as brains drive it")] = False,
          live_port: LivePortOpt = None,
          live_rate: Annotated[float, typer.Option(
              "--live-rate", min=0.0, help="--live: ticks sent per simulated second (0: every tick)")] = 0.0,
          view: Annotated[bool, typer.Option(
              "--view", help="also stream the world to Rerun's web viewer (loopback): bodies, signals, events and "
                             "the futures brains imagine")] = False,
          view_port: ViewPortOpt = VIEW_PORT) -> None:
    """Serve a world over Zenoh to remote brains (and robots) until interrupted; --live also to Foxglove,
    --view to Rerun."""
    from dynabrain.bridge.batching import BatchSettings
    from dynabrain.bridge.calls import DEFAULT_ALLOW_PYTHON
    from dynabrain.bridge.server import BridgeServer, ServeOptions

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    settings = _settings(listen, connect, zenoh_config, lease, mode, ["tcp/127.0.0.1:7447"])
    batch = BatchSettings(batch_backend, batch_workers, batch_max_ticks)
    ros2_options = _ros2_options(ros2_rate) if ros2 else None
    sc, world = _build(scenario)
    live_opts = live_options(live_port, live_rate, world.dt_ns) if live else None
    options = ServeOptions(name=name, stream=stream, decimate=decimate, robots=_robots(robot),
                           deadline_ns=parse_duration_ns(deadline), base_dir=sc.dir,
                           allow_python=DEFAULT_ALLOW_PYTHON if allow_python is None else allow_python, batch=batch,
                           tokenless_lease_s=_positive_seconds(tokenless_lease, "--tokenless-lease"),
                           trial_params=trial_params, ros2=ros2_options, live=live_opts)
    server = BridgeServer(world, settings, options)
    rerun = None
    try:
        endpoints = server.open()
        rerun = start_rerun_live(world, view_port) if view else None
        if server.live is not None:
            print(f"live view: {server.live.url} (Foxglove: Open connection > Foxglove WebSocket), "
                  f"{live_rate_text(server.live.every, world.dt_ns)}", flush=True)
        if start:
            server.loop.start(realtime, None)
        where = " ".join(endpoints) or f"(through {' '.join(settings.connect) or 'the configured router'})"
        print(f"serving world {server.name!r} (dynabrain/{server.name}/**) on {where} instance {server.instance}",
              flush=True)
        if server.ros2 is not None:
            info = server.ros2.describe()
            print(f"ROS 2 node {info['node']} on domain {info['domain_id']} (rmw_zenoh {info['rmw_zenoh']} format)",
                  flush=True)
        _wait_for_signal(threading.Event())
    finally:
        if rerun is not None:
            rerun.close()
        server.close()
        world.close()


def robot_emulator(scenario: Annotated[Path, typer.Argument(help="scenario of the robot's own simulation")],
                   world: Annotated[str, typer.Option(help="key-space name of the world the robot belongs to")],
                   robot: Annotated[str, typer.Option(help="the robot's name")] = "arm",
                   servo: Annotated[str, typer.Option(help="the PDServo module its joints follow")] = "servo",
                   listen: ListenOpt = None, connect: ConnectOpt = None, zenoh_config: ConfigOpt = None,
                   rate: Annotated[float, typer.Option(help="control and measurement rate (Hz)")] = 250.0,
                   noise: Annotated[float, typer.Option(help="position noise (std, rad or m)")] = 0.0,
                   latency: Annotated[str, typer.Option(help="measurement latency (e.g. 5ms)")] = "0s",
                   cmd_latency: Annotated[str, typer.Option(help="command latency (e.g. 20ms)")] = "0s",
                   seed: Annotated[int, typer.Option(help="seed of the noise")] = 0,
                   set_: Annotated[list[str] | None, typer.Option(
                       "--set", help="name=value in the robot's own world (a model mismatch)")] = None,
                   lease: LeaseOpt = None, mode: ModeOpt = None) -> None:
    """Run a robot emulator: its own simulation in real time, with noise and latency, on the robot link."""
    from dynabrain.bridge.robot_emulator import EmulatorOptions, parse_set, run_emulator

    logging.basicConfig(level=logging.INFO, format="%(message)s")  # mode changes, with their reasons
    settings = _settings(listen, connect, zenoh_config, lease, mode, [])
    options = EmulatorOptions(world=world, robot=robot, servo=servo, rate_hz=rate, noise=noise,
                              latency_s=parse_duration_ns(latency) / 1e9,
                              cmd_latency_s=parse_duration_ns(cmd_latency) / 1e9, seed=seed,
                              sets=parse_set(set_ or []))
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    signal.signal(signal.SIGINT, lambda *a: stop.set())

    def ready(endpoints: list[str]) -> None:
        print(f"robot {robot!r} of world {world!r} ready" + (f" on {' '.join(endpoints)}" if endpoints else ""),
              flush=True)

    own_world = _build(scenario)[1]
    try:
        final = run_emulator(own_world, settings, options, stop=stop, ready=ready)
    except DynabrainError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    print(f"robot {robot!r} stopped: {final['mode']} ({final['reason']}); counts {final['counts']}", flush=True)
