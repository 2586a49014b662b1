"""A robot emulator: a separate process that behaves like a real robot on the bridge's robot link.

It runs its own simulation of the robot (a World from a scenario, stepped in real time), publishes the
measured joint state with noise and latency, and takes commands the way a robot controller should:

- it starts *disabled* (holding its pose) and follows move commands and plays motion programs only once
  *enabled* (a program on its own clock, `robot_player`); what it ignores or refuses it counts and says
  on ``status``;
- it refuses a command older than the command's deadline (the brain's stamp against its clock);
- it stops by itself (*safe stop*: hold where it stands) when no move or program arrives within the
  enable window after an enable, when streamed moves stop coming for their deadline, when the world's
  liveliness token goes away, or on a stop command; an enable is needed to go on. A program is a whole
  command: while it plays, and after it (holding its last pose), no stream of moves is expected.

A rig on a servo's ``q_ref`` (the robot modules' `Servo`, whose program the moves add to) holds its
pose by keeping its inputs as they are and freezing its program; a rig on a ``target`` (`PDServo`)
holds the measured position.

``dynabrain robot-emulator bridge/arm.yaml --world arm --connect tcp/127.0.0.1:7447``
Noise comes from its own seeded generator.
"""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.world import World

from . import frames
from . import protocol as p
from .calls import find_rig
from .robot_player import ProgramPlayer
from .robot_program import OP_PROGRAM, Program, read_program
from .zenoh_io import FRAME, JSON, Settings, open_session, payload_bytes

_log = logging.getLogger("dynabrain.robot")


@dataclass
class EmulatorOptions:
    world: str
    """Key-space name of the world this robot belongs to."""
    robot: str = "arm"
    servo: str = "servo"
    """The servo module of the emulator's own world that its joints follow (a `PDServo`, or the robot
    modules' `Servo`: its ``target`` or ``q_ref`` input)."""
    rate_hz: float = 250.0
    """Control and measurement rate."""
    noise: float = 0.0
    """Standard deviation of the position noise (rad or m); velocities get ten times as much."""
    latency_s: float = 0.0
    """Delay between measuring and publishing a state."""
    cmd_latency_s: float = 0.0
    """Delay before a received command takes effect (a slow bus between bridge and controller)."""
    seed: int = 0
    sets: dict[str, Any] = field(default_factory=dict)
    """Parameter or input values for the emulator's own world (a model mismatch for shadow tests)."""


class RobotEmulator:
    """See the module docstring. ``open()``, ``run(stop_event)``, ``close()``."""

    def __init__(self, world: World, settings: Settings, options: EmulatorOptions):
        self.world, self.settings, self.opts = world, settings, options
        p.check_world_name(options.world)
        p.check_world_name(options.robot)
        self.rig = find_rig(world, options.robot, options.servo)
        self.joints = self.rig.joints
        core = world.core.name if world.core is not None else options.servo
        self._q_names = [f"{core}.{j}.q" for j in self.joints]
        self._qd_names = [f"{core}.{j}.qd" for j in self.joints]
        self._rng = np.random.default_rng(options.seed)
        self._source = int.from_bytes(np.random.default_rng(options.seed + 1).bytes(6), "little")
        self.mode, self.reason = frames.DISABLED, "starting"
        self._status_ns = time.time_ns()  # when `mode` and `reason` last changed (the status's stamp)
        self.counts = {"moves": 0, "programs": 0, "stale": 0, "ignored": 0, "bad": 0, "states": 0}
        self._commands: collections.deque[tuple[int, bytes]] = collections.deque(maxlen=1024)
        self._outbox: collections.deque[tuple[int, bytes]] = collections.deque()
        self._world_present = False
        self._world_lost = False
        self._deadline_ns = 0
        self._last_cmd = 0
        self._watch: str | None = None
        """What the watchdog waits for: ``enable`` (a first move or program within the enable window),
        ``move`` (fresh moves within their deadline), or nothing (disabled, stopped, or a program)."""
        self._offsets = self.rig.port == "q_ref"
        self._seq = 0
        self.session: zenoh.Session | None = None
        for name, value in options.sets.items():
            world.set(name, value)
        self.player = ProgramPlayer(world, self.rig)
        self.target = np.array(world.get(self.rig.signal), dtype=np.float64) if self._offsets else self._measure()[0]

    # -- Zenoh -----------------------------------------------------------------------------------------------
    def open(self) -> list[str]:
        self.session, endpoints = open_session(self.settings)
        s, o = self.session, self.opts
        key = lambda *parts: p.robot_key(o.world, o.robot, *parts)  # noqa: E731
        self._state = s.declare_publisher(key("state"), encoding=FRAME, priority=zenoh.Priority.REAL_TIME)
        self._status = s.declare_publisher(key("status"), encoding=JSON)
        self._entities = [
            s.declare_subscriber(key("cmd"), self._on_cmd),
            s.declare_queryable(key("info"), self._on_info),
            s.liveliness().declare_subscriber(p.key(o.world, "alive"), self._on_world, history=True),
            s.liveliness().declare_token(key("alive")),
        ]
        return endpoints

    def _on_cmd(self, sample: zenoh.Sample) -> None:
        self._commands.append((time.monotonic_ns(), payload_bytes(sample.payload)))

    def _on_world(self, sample: zenoh.Sample) -> None:
        present = sample.kind == zenoh.SampleKind.PUT
        self._world_present = present
        if not present:
            self._world_lost = True

    def _on_info(self, query: zenoh.Query) -> None:
        with contextlib.suppress(Exception):
            query.reply(query.key_expr, p.encode(self.describe()), encoding=JSON)

    def describe(self) -> dict[str, Any]:
        return {"robot": self.opts.robot, "joints": list(self.joints), "rate_hz": self.opts.rate_hz,
                "mode": frames.MODES[self.mode], "reason": self.reason, "stamp_ns": self._status_ns,
                "counts": dict(self.counts), "program": self.player.word}

    # -- the control loop -----------------------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        """Run in real time until ``stop`` is set."""
        period = int(1e9 / self.opts.rate_hz)
        w = self.world
        t0, tick0 = time.monotonic_ns(), w.tick_count
        next_at = t0
        while not stop.is_set():
            now = time.monotonic_ns()
            self._take_commands(now, time.time_ns())
            self._watchdogs(now)
            self._play()
            w.set(self.rig.signal, self.target)
            due = min(tick0 + (now - t0) // w.dt_ns - w.tick_count, 50)
            if due > 0:
                w.tick(due)
            self._publish_state(now)
            next_at += period
            delay = next_at - time.monotonic_ns()
            if delay < -50 * period:  # far behind (a stall): restart the pacing from now
                next_at = time.monotonic_ns()
            elif delay > 0:
                stop.wait(delay / 1e9)

    def _measure(self) -> tuple[np.ndarray, np.ndarray]:
        q = np.array([self.world.get(n) for n in self._q_names])
        qd = np.array([self.world.get(n) for n in self._qd_names])
        return q, qd

    def _publish_state(self, now: int) -> None:
        q, qd = self._measure()
        noise = self.opts.noise
        if noise > 0:
            q = q + self._rng.normal(0.0, noise, q.size)
            qd = qd + self._rng.normal(0.0, 10 * noise, qd.size)
        self._seq += 1
        frame = frames.robot_state(q, qd, mode=self.mode, source=self._source, seq=self._seq, stamp_ns=time.time_ns())
        self._outbox.append((now + int(self.opts.latency_s * 1e9), frame))
        while self._outbox and self._outbox[0][0] <= now:
            self._state.put(self._outbox.popleft()[1])
            self.counts["states"] += 1

    def _take_commands(self, now: int, wall: int) -> None:
        delay = int(self.opts.cmd_latency_s * 1e9)
        while self._commands and self._commands[0][0] + delay <= now:
            _, payload = self._commands.popleft()
            try:
                frame = frames.unpack(payload, frames.ROBOT_CMD, finite=True)
                if frame.flags == OP_PROGRAM:
                    program = read_program(frame, len(self.joints))
                else:
                    frames.check_robot_cmd(frame, len(self.joints))
                    program = None
            except p.ProtocolError as exc:
                self.counts["bad"] += 1
                _log.warning("robot %s: command refused: %s", self.opts.robot, exc)
                continue
            self._apply(frame, program, now, wall)

    def _apply(self, frame: frames.Frame, program: Program | None, now: int, wall: int) -> None:
        deadline = frame.aux * 1000
        if frame.flags == frames.OP_STOP:
            self._safe_stop("stop command")
            return
        age = wall - frame.stamp
        if age > deadline:
            self.counts["stale"] += 1
            why = f"{age / 1e6:.0f} ms old, over its {deadline / 1e6:g} ms deadline"
            if frame.flags == frames.OP_ENABLE:  # answered, so the link knows the robot is still not enabled
                self._set_mode(self.mode, f"enable refused: {why}")
            elif program is not None:
                self.player.refuse(program, frame.seq, "refused", why)
                self._publish_status()
            return
        if frame.flags == frames.OP_ENABLE:
            self._enable(deadline, now)
        elif self.mode != frames.ENABLED:
            self.counts["ignored"] += 1
            if program is not None:
                self.player.refuse(program, frame.seq, "ignored", f"the robot is {frames.MODES[self.mode]}")
            self._publish_status()
        elif program is not None:
            self.counts["programs"] += 1
            self.player.start(program, frame.seq, self.target)
            self._watch = None  # a whole command: no stream of moves to watch
            self._publish_status()
        else:
            if self.player.playing and not self.player.by_servo:
                self.player.end("replaced", "a move came")
            self.target = np.array(frame.values)
            self._deadline_ns, self._last_cmd, self._watch = deadline, now, "move"
            self.counts["moves"] += 1

    def _enable(self, window_ns: int, now: int) -> None:
        """Enabled: hold the pose until a move or a program comes, within ``window_ns`` (the enable window)."""
        if not self._offsets and not self.player.playing:
            self.target = self._measure()[0]
        self._deadline_ns, self._last_cmd, self._watch = window_ns, now, "enable"
        self._world_lost = False
        self._set_mode(frames.ENABLED, "enabled")

    def _play(self) -> None:
        """Targets from a program played here; say when a program is done."""
        target = self.player.target()
        if target is not None:
            self.target = target
        if self.player.done():
            self._publish_status()

    def _watchdogs(self, now: int) -> None:
        if self.mode != frames.ENABLED:
            return
        quiet = now - self._last_cmd
        if self._world_lost or not self._world_present:
            self._safe_stop(f"world {self.opts.world!r} lost (its liveliness token is gone)")
        elif self._watch == "enable" and quiet > self._deadline_ns:
            self._safe_stop(f"no move or program within the enable window ({self._deadline_ns / 1e6:g} ms after "
                            "robot_enable)")
        elif self._watch == "move" and quiet > self._deadline_ns:
            self._safe_stop(f"no fresh command for {quiet / 1e6:.0f} ms (deadline {self._deadline_ns / 1e6:g} ms)")

    def _safe_stop(self, reason: str) -> None:
        """Hold the joints where they stand (a servo that plays programs: where its program stands), and say
        why."""
        if self.player.playing:
            self.player.end("stopped", reason)
        if not self._offsets:
            self.target = self._measure()[0]
        self._watch = None
        self._set_mode(frames.SAFE_STOP, reason)

    def _set_mode(self, mode: int, reason: str) -> None:
        changed = mode != self.mode or reason != self.reason
        self.mode, self.reason = mode, reason
        if changed:
            self._status_ns = time.time_ns()
            self._publish_status()
            _log.info("robot %s: %s (%s)", self.opts.robot, frames.MODES[mode], reason)

    def _publish_status(self) -> None:
        """Say the robot's mode, counts and program on ``status`` (on each change of them)."""
        if self.session is not None:
            with contextlib.suppress(Exception):
                self._status.put(p.encode(self.describe()))

    def close(self) -> None:
        if self.session is None:
            return
        for ent in [*reversed(self._entities), self._status, self._state]:
            with contextlib.suppress(Exception):
                ent.undeclare()
        session, self.session = self.session, None
        session.close()


def run_emulator(world: World, settings: Settings, options: EmulatorOptions, *,
                 stop: threading.Event | None = None, ready: Any = None) -> dict[str, Any]:
    """Run an emulator on ``world`` (its own simulation, closed at the end) until ``stop``; returns its
    final description."""
    emu = RobotEmulator(world, settings, options)
    try:
        endpoints = emu.open()
        if ready is not None:
            ready(endpoints)
        emu.run(stop or threading.Event())
        return emu.describe()
    finally:
        emu.close()
        world.close()


def parse_set(items: list[str]) -> dict[str, Any]:
    """``name=value`` pairs, values as JSON where they parse (``servo.kp=40``, ``core.gravity=[0,0,-9]``)."""
    out: dict[str, Any] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise DynabrainError(f"--set takes name=value, got {item!r}")
        try:
            out[name] = json.loads(text)
        except ValueError:
            out[name] = text
    return out
