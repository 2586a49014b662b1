"""The bridge's end of a real robot (or the emulator), under ``dynabrain/<world>/robot/<name>/``.

- ``state`` (robot -> bridge): ROBOT_STATE frames, the measured joint positions and velocities;
- ``cmd`` (bridge -> robot): ROBOT_CMD frames (move, stop, enable, program), each stamped with the
  wall-clock time the brain issued it and carrying the deadline;
- ``shadow`` (bridge -> anyone): SHADOW frames, the simulation's prediction against the measurement;
- ``alive``: the robot's liveliness token; ``info``: its queryable description (joints, rate).

Programs: when the rig's servo begins a new motion program (a brain set its ``sequence``), the link
sends the robot the program's timed steps (`robot_program`), which the robot plays on its own clock.

Watchdog: a motion command whose age (now minus the brain's stamp) is over the deadline is not
forwarded, and the robot refuses it too; the robot stops by itself when streamed moves stop coming for
a deadline, or when no move or program comes within the *enable window* after an enable (the same
length). A move or program the robot would ignore (it is disabled or safe-stopped, by its last word)
is not sent: it is reported as ignored, never as forwarded. Liveliness: losing the robot is reported
(with the world's tick) and refuses motion to it; losing the brain that drives it sends the robot a
stop. Shadow mode: while the world runs in real time, every measured state is compared with the
simulation's joint positions at the same wall-clock time (interpolated from the last ticks), and both
are published side by side.

Clocks: ages compare the brain's and this host's wall clocks, so hosts must be synchronised (NTP, PTP)
to well under the deadline; a command stamped more than ``max_skew`` in the future is refused.
"""

from __future__ import annotations

import json
import threading
import time
from typing import Any

import numpy as np
import zenoh

from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.observers import WorldView

from . import frames
from . import protocol as p
from .calls import Rig, WorldService
from .robot_program import Program, program_cmd
from .streams import EventSink
from .zenoh_io import FRAME

RING = 2048
"""Ticks of prediction kept for shadow comparisons (4 s at a 2 ms step)."""
ANSWER_NS = 1_000_000_000
"""How long the link waits for the robot's answer to an enable (on ``status``) before it goes by the
robot's last word again; a robot that answers ends the wait at once."""




class RobotLink:
    """One robot rig's link: forwarding with a watchdog, programs, liveliness, shadow comparisons."""

    def __init__(self, session: zenoh.Session, world: str, rig: Rig, service: WorldService, events: EventSink, *,
                 deadline_ns: int, max_skew_ns: int = 1_000_000_000):
        self.rig, self.name, self.joints = rig, rig.robot, rig.joints
        self.deadline_ns, self.max_skew_ns = int(deadline_ns), int(max_skew_ns)
        self.enable_window_ns = self.deadline_ns
        """After an enable, the robot safe-stops unless a move or a program reaches it within this time
        (the enable frame carries it as its deadline)."""
        self._events = events
        self._session, self._world = session, world
        self._sim = service.world
        self._lock = threading.Lock()
        self.alive = False
        self.lost_tick: int | None = None
        """The world's tick when the robot's liveliness token went away (None while it is there)."""
        self.mismatch: str | None = None
        self.driver: str | None = None
        self.mode: str | None = None
        """The robot's mode by its latest word (a state frame or a status publication, whichever is newer)."""
        self.reason: str | None = None
        """The robot's own word on its last mode change (``status`` publications)."""
        self.mode_tick: int | None = None
        """The world's tick when the link learnt of the robot's last mode change."""
        self._mode_ns = 0  # the robot's stamp of the word `mode` comes from
        self._answer_ns = 0  # the stamp of its last status publication
        self._enable_ns: int | None = None  # when this link last sent an enable
        self.robot_word: dict[str, Any] = {}
        """The robot's counts and program from its last status publication."""
        self.program: dict[str, Any] | None = None
        """The last program the servo began, and what became of it on the link."""
        self.seq = 0
        self.counts = {"forwarded": 0, "dropped": 0, "ignored": 0, "programs": 0, "states": 0, "bad_states": 0,
                       "shadow": 0}
        self.last_state: dict[str, Any] | None = None
        n = len(self.joints)
        self._err_sq, self._err_max = np.zeros(n), np.zeros(n)
        self._ring_t = np.zeros(RING, dtype=np.int64)
        self._ring_q = np.zeros((RING, n))
        self._ring_len = 0
        self._ring_at = 0
        core = service.world.core
        names = [f"{core.name}.{j}.q" if core is not None else f"{rig.servo}.{j}.q" for j in self.joints]
        self._view = service.internal_view(names)
        self._service = service
        self._servo: Any = None
        self._plays = False
        self._bus: Any = None  # the world's bus when the servo was looked up: a new one means a new structure
        self._seen: Any = None  # the servo's program when last looked at: only a new one goes to the robot
        self._watch_servo()
        key = lambda *parts: p.robot_key(world, rig.robot, *parts)  # noqa: E731
        self._cmd = session.declare_publisher(key("cmd"), encoding=FRAME, priority=zenoh.Priority.REAL_TIME,
                                              express=True)
        self._shadow = session.declare_publisher(key("shadow"), encoding=FRAME)
        self._state_sub = session.declare_subscriber(key("state"), self._on_state)
        self._status_sub = session.declare_subscriber(key("status"), self._on_status)
        self._alive_sub = session.liveliness().declare_subscriber(key("alive"), self._on_alive, history=True)

    # -- commands -------------------------------------------------------------------------------------------
    def forward(self, targets: np.ndarray, brain: str | None, sent_ns: int | None, seq: int | None) -> dict[str, Any]:
        """Send a move to the robot unless it is older than the deadline or the robot would ignore it (expected
        outcomes: the result says it was dropped or ignored). Refuses when the robot is not there."""
        self._require_alive()
        now = time.time_ns()
        stamp = now if sent_ns is None else int(sent_ns)
        age = now - stamp
        if age < -self.max_skew_ns:
            raise DynabrainError(f"robot {self.name!r}: command stamped {-age / 1e6:.0f} ms in the future; "
                                 "are the clocks of the brain and the bridge synchronised?")
        if age > self.deadline_ns:
            if (count := self._count("dropped")) == 1 or count % 100 == 0:
                self._events.emit("command_dropped", robot=self.name, brain=brain, age_ms=age / 1e6,
                                  deadline_ms=self.deadline_ns / 1e6, dropped=count)
            return {"forwarded": False, "reason": f"{age / 1e6:.1f} ms old, over the {self.deadline_ns / 1e6:g} ms "
                                                  "deadline"}
        why = self.ignores()
        if why is not None:
            if (count := self._count("ignored")) == 1 or count % 100 == 0:
                self._events.emit("command_ignored", robot=self.name, brain=brain, reason=why,
                                  ignored=count)
            return {"forwarded": False, "ignored": True, "reason": why}
        with self._lock:
            self.seq = max(self.seq + 1, seq or 0)
            self.driver = brain
            self.counts["forwarded"] += 1
            frame = frames.robot_cmd(frames.OP_MOVE, targets, seq=self.seq, stamp_ns=stamp,
                                     deadline_ns=self.deadline_ns)
        self._cmd.put(frame)
        return {"forwarded": True, "seq": self.seq, "age_ms": age / 1e6}

    def _count(self, what: str) -> int:
        with self._lock:
            self.counts[what] += 1
            return self.counts[what]

    def ignores(self) -> str | None:
        """Why the robot would ignore a move or a program now (it is disabled or safe-stopped by its latest
        word, and no enable of ours is still unanswered), or None."""
        with self._lock:
            mode, reason, enable_ns, answer_ns = self.mode, self.reason, self._enable_ns, self._answer_ns
        if mode in (None, "enabled"):
            return None
        if enable_ns is not None and answer_ns < enable_ns and time.time_ns() - enable_ns < ANSWER_NS:
            return None  # our enable is on its way and the robot has not answered it yet
        return (f"robot {self.name!r} is {mode.replace('_', ' ')}"
                + (f" ({reason})" if reason else "") + ": it ignores moves and programs until robot_enable")

    def enable(self, brain: str | None) -> dict[str, Any]:
        self._require_alive()
        with self._lock:
            self._enable_ns = time.time_ns()
        self._send(frames.OP_ENABLE, self.enable_window_ns)
        self.driver = brain
        self._events.emit("robot_enable", robot=self.name, brain=brain)
        return {"sent": "enable", "enable_window_ms": self.enable_window_ns / 1e6}

    def stop(self, reason: str) -> None:
        """Tell the robot to stop where it stands (sent even if its token is gone: it may still hear)."""
        self._send(frames.OP_STOP, self.deadline_ns)
        self._events.emit("robot_stop", robot=self.name, reason=reason)

    def _send(self, op: int, deadline_ns: int) -> None:
        with self._lock:
            self.seq += 1
            frame = frames.robot_cmd(op, None, seq=self.seq, stamp_ns=time.time_ns(), deadline_ns=deadline_ns)
        self._cmd.put(frame)

    def brain_gone(self, brain: str) -> None:
        if self.driver is not None and brain == self.driver:
            self.driver = None
            self.stop(f"brain {brain!r} that drove it is gone")

    def _require_alive(self) -> None:
        if not self.alive:
            raise DynabrainError(self._absent())
        if self.mismatch:
            raise DynabrainError(f"robot {self.name!r} refused: {self.mismatch}")

    def _absent(self) -> str:
        token = p.robot_key(self._world, self.name, "alive")
        if self.lost_tick is None:
            return f"robot {self.name!r} is not connected (no liveliness token at {token})"
        return (f"robot {self.name!r} is not connected: lost at tick {self.lost_tick} (its liveliness token {token} "
                f"went away; the world is at tick {self._sim.tick_count})")

    # -- programs -------------------------------------------------------------------------------------------
    def _watch_servo(self) -> None:
        """Look up the rig's servo (again when it was replaced): does it play motion programs?"""
        servo = self._sim.modules.get(self.rig.servo)
        if servo is not self._servo:
            self._servo = servo
            self._plays = isinstance(getattr(type(servo), "program", None), property)
            self._seen = servo.program if self._plays else None  # the program it has now is not news

    def _check_program(self, tick: int) -> None:
        """Send the robot the servo's program when the servo began a new one in the tick just done (a program
        a rollback brought back is not sent again: the robot cannot go back in time)."""
        servo = self._servo
        motion = servo.program
        if motion is self._seen:
            return
        self._seen = motion
        if servo.program_start_ns >= self._sim.time_ns - self._sim.dt_ns:
            self.send_program(Program.of_motion(motion), tick)

    def send_program(self, program: Program, tick: int) -> dict[str, Any]:
        """Send ``program`` to the robot, unless it is absent or would ignore it; the record of what was done
        (also `status`'s ``program`` and a ``robot_program`` event)."""
        record: dict[str, Any] = {**program.describe(), "tick": tick, "seq": None, "forwarded": False,
                                  "ignored": False, "reason": None}
        if program.poses.shape[1] != len(self.joints):
            record["reason"] = f"{program.poses.shape[1]} joints, the rig has {len(self.joints)}"
        elif not self.alive or self.mismatch:
            record["reason"] = self._absent() if not self.alive else f"robot {self.name!r} refused: {self.mismatch}"
        elif (why := self.ignores()) is not None:
            record["ignored"], record["reason"] = True, why
            self._count("ignored")
        else:
            with self._lock:
                self.seq += 1
                self.counts["programs"] += 1
                frame = program_cmd(program, seq=self.seq, stamp_ns=time.time_ns(), deadline_ns=self.deadline_ns)
                record["seq"], record["forwarded"] = self.seq, True
            self._cmd.put(frame)
        self.program = record
        self._events.emit("robot_program", robot=self.name, **record)
        return record

    # -- liveliness -----------------------------------------------------------------------------------------
    def _on_alive(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self.alive, self.mismatch, self.lost_tick = True, None, None
            with self._lock:
                self._enable_ns = None
            self._events.emit("robot_joined", robot=self.name)
            threading.Thread(target=self._check_info, daemon=True, name=f"robot-info-{self.name}").start()
        else:
            self.lost_tick = self._sim.tick_count
            self.alive = False
            self._events.emit("robot_lost", robot=self.name, last_seq=self.counts["states"], lost_tick=self.lost_tick)

    def _check_info(self) -> None:
        """Ask the robot its joints; a robot whose joints differ from the rig's is refused."""
        try:
            replies = self._session.get(p.robot_key(self._world, self.name, "info"), timeout=2.0)
            info = next((json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None), None)
        except Exception as exc:
            info, error = None, str(exc)
        else:
            error = "no answer from its info queryable"
        if info is None:
            self.mismatch = f"cannot read its description ({error})"
        elif list(info.get("joints", [])) != list(self.joints):
            self.mismatch = f"its joints {info.get('joints')} are not the rig's {list(self.joints)}"
        if self.mismatch:
            self._events.emit("robot_refused", robot=self.name, reason=self.mismatch)

    # -- measurements and shadow ----------------------------------------------------------------------------
    def on_tick(self, view: WorldView) -> None:
        """Record the simulation's joint positions with the wall-clock time, and send the robot a program
        the servo began (a StateStream tick hook)."""
        q = self._service.values(self._view)
        with self._lock:
            self._ring_t[self._ring_at] = time.time_ns()
            self._ring_q[self._ring_at] = q
            self._ring_at = (self._ring_at + 1) % RING
            self._ring_len = min(self._ring_len + 1, RING)
        bus = view.bus()
        if bus is not self._bus:  # the structure changed (or the first tick): look the servo up again
            self._bus = bus
            self._watch_servo()
        if self._plays:
            self._check_program(view.tick)

    def _predicted(self, stamp: int) -> np.ndarray | None:
        with self._lock:
            n = self._ring_len
            if n < 2:
                return None
            order = (np.arange(self._ring_at - n, self._ring_at)) % RING
            t, q = self._ring_t[order], self._ring_q[order]
        if not t[0] <= stamp <= t[-1] + 20_000_000:  # no prediction for that time (20 ms of slack at the end)
            return None
        i = int(np.searchsorted(t, stamp))
        if i >= n:
            return q[-1].copy()
        if i == 0:
            return q[0].copy()
        w = (stamp - t[i - 1]) / max(t[i] - t[i - 1], 1)
        return q[i - 1] + w * (q[i] - q[i - 1])

    def _set_mode(self, mode: str, stamp: int) -> None:
        """The robot's mode by a word stamped ``stamp``; an older word than the one we have is not news."""
        with self._lock:
            if stamp < self._mode_ns:
                return
            self._mode_ns = stamp
            changed, self.mode = mode != self.mode, mode
            if changed:
                self.mode_tick = self._sim.tick_count
        if changed:
            self._events.emit("robot_mode", robot=self.name, mode=mode)

    def _on_state(self, sample: zenoh.Sample) -> None:
        try:
            frame = frames.unpack(sample.payload.to_bytes(), frames.ROBOT_STATE, finite=True)
            q, qd = frames.split_robot_state(frame)
            if q.size != len(self.joints):
                raise p.ProtocolError(f"{q.size} joints, the rig has {len(self.joints)}")
        except p.ProtocolError as exc:
            self.counts["bad_states"] += 1
            if self.counts["bad_states"] in (1, 10, 100, 1000):
                self._events.emit("robot_bad_state", robot=self.name, reason=str(exc), count=self.counts["bad_states"])
            return
        mode = frames.MODES[frame.flags]
        self._set_mode(mode, frame.stamp)
        self.counts["states"] += 1
        self.last_state = {"seq": frame.seq, "stamp_ns": frame.stamp, "q": q.tolist(), "qd": qd.tolist(),
                           "mode": mode, "received_ns": time.time_ns()}
        predicted = self._predicted(frame.stamp)
        if predicted is None:
            return
        err = q - predicted
        with self._lock:
            self._err_sq += err * err
            np.maximum(self._err_max, np.abs(err), out=self._err_max)
            self.counts["shadow"] += 1
        self._shadow.put(frames.pack(frames.SHADOW, np.concatenate([predicted, q]), flags=frame.flags,
                                     seq=frame.seq, stamp=frame.stamp, aux=len(q)))

    def _on_status(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        try:
            msg = json.loads(data) if len(data) <= p.MAX_INPUT_BYTES else None
            reason, mode = str(msg["reason"])[:500], str(msg["mode"])[:50]
            stamp = int(msg.get("stamp_ns") or time.time_ns())  # a robot that stamps no status: received now
        except (ValueError, TypeError, KeyError, AttributeError):
            self.counts["bad_states"] += 1
            return
        word = {k: msg[k] for k in ("counts", "program") if isinstance(msg.get(k), dict)}
        with self._lock:
            self.reason, self._answer_ns, self.robot_word = reason, max(self._answer_ns, stamp), word
        if mode in frames.MODES.values():
            self._set_mode(mode, stamp)
        self._events.emit("robot_status", robot=self.name, mode=mode, reason=reason, program=word.get("program"))

    def status(self) -> dict[str, Any]:
        with self._lock:
            k = self.counts["shadow"]
            rms = np.sqrt(self._err_sq / k).tolist() if k else None
            program = None
            if self.program is not None:
                played = self.robot_word.get("program")
                program = {**self.program, "robot": played if played and played.get("seq") == self.program["seq"]
                           and self.program["forwarded"] else None}
            return {"robot": self.name, "alive": self.alive, "lost_tick": self.lost_tick, "refused": self.mismatch,
                    "mode": self.mode, "mode_tick": self.mode_tick, "reason": self.reason, "driver": self.driver,
                    "joints": list(self.joints),
                    "deadline_ms": self.deadline_ns / 1e6, "enable_window_ms": self.enable_window_ns / 1e6,
                    "counts": dict(self.counts), "robot_counts": self.robot_word.get("counts"),
                    "program": program, "last_state": self.last_state,
                    "shadow": {"samples": k, "rms": rms, "max": self._err_max.tolist() if k else None}}

    def close(self) -> None:
        for ent in (self._alive_sub, self._status_sub, self._state_sub, self._shadow, self._cmd):
            try:
                ent.undeclare()
            except Exception:  # the session is closing anyway
                continue
