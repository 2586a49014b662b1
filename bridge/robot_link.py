"""The bridge's end of a real robot (or the emulator), under ``dynabrain/<world>/robot/<name>/``.

- ``state`` (robot -> bridge): ROBOT_STATE frames, the measured joint positions and velocities;
- ``cmd`` (bridge -> robot): ROBOT_CMD frames (move, stop, enable), each stamped with the wall-clock time
  the brain issued it and carrying the deadline;
- ``shadow`` (bridge -> anyone): SHADOW frames, the simulation's prediction against the measurement;
- ``alive``: the robot's liveliness token; ``info``: its queryable description (joints, rate).

Watchdog: a motion command whose age (now minus the brain's stamp) is over the deadline is not
forwarded, and the robot refuses it too; the robot stops by itself when commands stop coming for a
deadline. Liveliness: losing the robot is reported and refuses motion to it; losing the brain that
drives it sends the robot a stop. Shadow mode: while the world runs in real time, every measured state
is compared with the simulation's joint positions at the same wall-clock time (interpolated from the
last ticks), and both are published side by side.

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
from .streams import EventSink
from .zenoh_io import FRAME

RING = 2048
"""Ticks of prediction kept for shadow comparisons (4 s at a 2 ms step)."""


class RobotLink:
    """One robot rig's link: forwarding with a watchdog, liveliness, shadow comparisons."""

    def __init__(self, session: zenoh.Session, world: str, rig: Rig, service: WorldService, events: EventSink, *,
                 deadline_ns: int, max_skew_ns: int = 1_000_000_000):
        self.rig, self.name, self.joints = rig, rig.robot, rig.joints
        self.deadline_ns, self.max_skew_ns = int(deadline_ns), int(max_skew_ns)
        self._events = events
        self._session, self._world = session, world
        self._lock = threading.Lock()
        self.alive = False
        self.mismatch: str | None = None
        self.driver: str | None = None
        self.mode: str | None = None
        self.reason: str | None = None
        """The robot's own word on its last mode change (``status`` publications)."""
        self.seq = 0
        self.counts = {"forwarded": 0, "dropped": 0, "states": 0, "bad_states": 0, "shadow": 0}
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
        key = lambda *parts: p.robot_key(world, rig.robot, *parts)  # noqa: E731
        self._cmd = session.declare_publisher(key("cmd"), encoding=FRAME, priority=zenoh.Priority.REAL_TIME,
                                              express=True)
        self._shadow = session.declare_publisher(key("shadow"), encoding=FRAME)
        self._state_sub = session.declare_subscriber(key("state"), self._on_state)
        self._status_sub = session.declare_subscriber(key("status"), self._on_status)
        self._alive_sub = session.liveliness().declare_subscriber(key("alive"), self._on_alive, history=True)

    # -- commands -------------------------------------------------------------------------------------------
    def forward(self, targets: np.ndarray, brain: str | None, sent_ns: int | None, seq: int | None) -> dict[str, Any]:
        """Send a move to the robot unless it is older than the deadline (an expected outcome: the result
        says it was dropped). Refuses when the robot is not there."""
        self._require_alive()
        now = time.time_ns()
        stamp = now if sent_ns is None else int(sent_ns)
        age = now - stamp
        if age < -self.max_skew_ns:
            raise DynabrainError(f"robot {self.name!r}: command stamped {-age / 1e6:.0f} ms in the future; "
                                 "are the clocks of the brain and the bridge synchronised?")
        if age > self.deadline_ns:
            with self._lock:
                self.counts["dropped"] += 1
                dropped = self.counts["dropped"]
            if dropped == 1 or dropped % 100 == 0:
                self._events.emit("command_dropped", robot=self.name, brain=brain, age_ms=age / 1e6,
                                  deadline_ms=self.deadline_ns / 1e6, dropped=dropped)
            return {"forwarded": False, "reason": f"{age / 1e6:.1f} ms old, over the {self.deadline_ns / 1e6:g} ms "
                                                  "deadline"}
        with self._lock:
            self.seq = max(self.seq + 1, seq or 0)
            self.driver = brain
            self.counts["forwarded"] += 1
            frame = frames.robot_cmd(frames.OP_MOVE, targets, seq=self.seq, stamp_ns=stamp,
                                     deadline_ns=self.deadline_ns)
        self._cmd.put(frame)
        return {"forwarded": True, "seq": self.seq, "age_ms": age / 1e6}

    def enable(self, brain: str | None) -> dict[str, Any]:
        self._require_alive()
        self._send(frames.OP_ENABLE)
        self.driver = brain
        self._events.emit("robot_enable", robot=self.name, brain=brain)
        return {"sent": "enable"}

    def stop(self, reason: str) -> None:
        """Tell the robot to stop where it stands (sent even if its token is gone: it may still hear)."""
        self._send(frames.OP_STOP)
        self._events.emit("robot_stop", robot=self.name, reason=reason)

    def _send(self, op: int) -> None:
        with self._lock:
            self.seq += 1
            frame = frames.robot_cmd(op, None, seq=self.seq, stamp_ns=time.time_ns(), deadline_ns=self.deadline_ns)
        self._cmd.put(frame)

    def brain_gone(self, brain: str) -> None:
        if self.driver is not None and brain == self.driver:
            self.driver = None
            self.stop(f"brain {brain!r} that drove it is gone")

    def _require_alive(self) -> None:
        if not self.alive:
            raise DynabrainError(f"robot {self.name!r} is not connected (no liveliness token at "
                                 f"{p.robot_key(self._world, self.name, 'alive')})")
        if self.mismatch:
            raise DynabrainError(f"robot {self.name!r} refused: {self.mismatch}")

    # -- liveliness -----------------------------------------------------------------------------------------
    def _on_alive(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self.alive, self.mismatch = True, None
            self._events.emit("robot_joined", robot=self.name)
            threading.Thread(target=self._check_info, daemon=True, name=f"robot-info-{self.name}").start()
        else:
            self.alive = False
            self._events.emit("robot_lost", robot=self.name, last_seq=self.counts["states"])

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
        """Record the simulation's joint positions with the wall-clock time (a StateStream tick hook)."""
        q = self._service.values(self._view)
        with self._lock:
            self._ring_t[self._ring_at] = time.time_ns()
            self._ring_q[self._ring_at] = q
            self._ring_at = (self._ring_at + 1) % RING
            self._ring_len = min(self._ring_len + 1, RING)

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
        if mode != self.mode:
            self.mode = mode
            self._events.emit("robot_mode", robot=self.name, mode=mode)
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
        except (ValueError, TypeError, KeyError):
            self.counts["bad_states"] += 1
            return
        self.reason = reason
        self._events.emit("robot_status", robot=self.name, mode=mode, reason=reason)

    def status(self) -> dict[str, Any]:
        with self._lock:
            k = self.counts["shadow"]
            rms = np.sqrt(self._err_sq / k).tolist() if k else None
            return {"robot": self.name, "alive": self.alive, "refused": self.mismatch, "mode": self.mode,
                    "reason": self.reason,
                    "driver": self.driver, "joints": list(self.joints), "deadline_ms": self.deadline_ns / 1e6,
                    "counts": dict(self.counts), "last_state": self.last_state,
                    "shadow": {"samples": k, "rms": rms, "max": self._err_max.tolist() if k else None}}

    def close(self) -> None:
        for ent in (self._alive_sub, self._status_sub, self._state_sub, self._shadow, self._cmd):
            try:
                ent.undeclare()
            except Exception:  # the session is closing anyway
                continue
