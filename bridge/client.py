"""`BrainClient`: a brain's handle on a world served over Zenoh, mirroring the World API.

    with BrainClient("arm", connect="tcp/127.0.0.1:7447") as world:
        world.tick(100)
        world.backtick(50)
        world.set("servo.target", [0.3, 0.5, -0.8])
        v = world.view(["core.joint_q", "cube.pos"])
        frame = world.tick(10, view=v)          # one round trip: ten ticks and the state after them
        print(frame["core.joint_q"], frame.tick)
        futures = world.batch(200, branches=8, params={"servo.kp": [20, 30, 40, 50, 60, 70, 80, 90]},
                              record=["core.joint_q"], keep_states=True)   # 8 futures, the world unchanged
        world.restore(futures.snapshots[3])     # continue from the fourth

Errors tell the situations apart (`errors`): `ConnectError` (no session), `NoWorldError` (nobody
serves that world), `CallTimeoutError` (alive but slow), `WorldRefusedError` and its subclasses (the world
said no, and why). Every call carries the brain's id and the server instance it talks to, so a
restarted server refuses the call (`WorldRestartedError`) instead of running it on a world the brain does
not know.

Every method goes through `BrainClient.call`, which checks the command against the protocol's table of
calls (`protocol.TABLE`: the call's name and its arguments' model, the same check the server makes)
before sending it: a call the server would refuse as a bad request raises `BadRequestError` at once,
and nothing is sent.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import zenoh

from . import frames
from . import protocol as p
from .arguments import finite_list, has_infinity, integer, robot_check, snapshot_id, target_values
from .errors import (
    ERRORS,
    BadRequestError,
    BridgeError,
    CallTimeoutError,
    NoWorldError,
    TickStoppedError,
    WorldRefusedError,
)
from .replies import BatchReply, Snapshot, StateFrame, View
from .zenoh_io import DEFAULT_ENDPOINT, JSON, Settings, open_session, payload_bytes


class BrainClient:
    """A world served over Zenoh. See the module docstring."""

    def __init__(self, world: str, *, connect: str | Sequence[str] = DEFAULT_ENDPOINT,
                 settings: Settings | None = None, brain: str | None = None, timeout: float = 10.0,
                 _parent: BrainClient | None = None):
        self.world = p.check_world_name(world)
        self.timeout = float(timeout)
        self._queriers: dict[str, zenoh.Querier] = {}
        self._payloads: dict[tuple, bytes] = {}
        self._instance: int | None = None
        self._closed = False
        self._subs: list[Any] = []
        self.last_tick = -1
        """The world's tick after the last call."""
        self._motion_pub: zenoh.Publisher | None = None
        self._set_pub: zenoh.Publisher | None = None
        if _parent is not None:  # a fork: the parent's session, brain id and token
            self._session, self.brain, self._owner = _parent._session, _parent.brain, False
            self._alive_key = _parent._alive_key
            self._instance = _parent._instance
            return
        if settings is None:
            settings = Settings(connect=[connect] if isinstance(connect, str) else list(connect))
        self._session, _ = open_session(settings)
        self._owner = True
        self.brain = p.check_world_name(brain) if brain else f"brain-{str(self._session.zid())[:12]}"
        self._alive_key = p.key(self.world, "alive")
        self._token = self._session.liveliness().declare_token(p.key(self.world, "brain", self.brain))

    # -- the call path --------------------------------------------------------------------------------------
    def call(self, name: str, timeout: float | None = None, /, **args: Any) -> Any:
        """Any call by name (``tick``, ``status``, ...) with its arguments; see `PROTOCOL.md`. ``timeout``
        (s, positional) replaces the client's default for this call. A name that is no call, or arguments
        its model refuses, raise `BadRequestError` before anything is sent."""
        if self._closed:
            raise BridgeError(f"this client of world {self.world!r} is closed")
        payload = self._payload(name, args)
        if timeout is None:
            querier = self._queriers.get(name)
            if querier is None:
                querier = self._session.declare_querier(p.call_key(self.world, name), timeout=self.timeout)
                self._queriers[name] = querier
            replies = querier.get(payload=payload, encoding=JSON)
        else:
            replies = self._session.get(p.call_key(self.world, name), payload=payload, encoding=JSON,
                                        timeout=timeout)
        reply = next(iter(replies), None)
        wait = self.timeout if timeout is None else timeout
        if reply is None:
            raise self._no_answer(name, wait)
        return self._decode(name, reply, wait)

    def _payload(self, name: str, args: dict[str, Any]) -> bytes:
        """The command's bytes, checked; those of small repeated calls (a lock-step ``tick``) are kept."""
        if name not in _CACHED_CALLS:
            return self._command(name, args)
        key = (name, self._instance, *args.items())
        try:
            payload = self._payloads.get(key)
        except TypeError:  # unhashable arguments: not a lock-step call
            return self._command(name, args)
        if payload is None:
            if len(self._payloads) > 256:
                self._payloads.clear()
            payload = self._payloads[key] = self._command(name, args)
        return payload

    def _command(self, name: str, args: dict[str, Any]) -> bytes:
        """The command's bytes, validated as the server validates them (`protocol.decode_command`)."""
        payload = p.encode({"v": p.VERSION, "brain": self.brain, "instance": self._instance, "args": args})
        try:
            p.decode_command(name, payload)
        except p.ProtocolError as exc:
            raise BadRequestError(exc.kind, f"{exc} (refused by this client, nothing sent)", name) from None
        return payload

    def _decode(self, name: str, reply: zenoh.Reply, wait: float) -> Any:
        sample = reply.ok
        if sample is None:
            data = payload_bytes(reply.err.payload)
            if data == b"Timeout":  # Zenoh's own error reply when no answer came in time
                raise self._no_answer(name, wait)
            try:
                body = json.loads(data)
                kind, message = str(body["error"]), str(body["message"])
                detail = body.get("detail")
            except (ValueError, KeyError, TypeError, AttributeError):
                raise BridgeError(f"{name}: an error reply that is not the bridge's: {data[:200]!r}") from None
            cls = ERRORS.get(kind, WorldRefusedError)
            error = cls(kind, message, name, detail if isinstance(detail, dict) else None)
            if isinstance(error, TickStoppedError) and error.tick is not None:
                self.last_tick = error.tick
            raise error
        data = sample.payload.to_bytes()
        if data[:4] == frames.MAGIC:  # no JSON reply starts so
            return frames.unpack(data)
        body = json.loads(data)
        if self._instance is None:
            self._instance = int(body["instance"])
        self.last_tick = int(body["tick"])
        return body["result"]

    def _no_answer(self, name: str, timeout: float) -> BridgeError:
        if self.world_alive():
            return CallTimeoutError(f"world {self.world!r} is alive but did not answer {name} within {timeout:g} s "
                                    "(it may still be running the call: pass a longer timeout for long calls; or "
                                    "access control does not let this brain make it)")
        return NoWorldError(f"no world answered {name}: nothing serves {self.world!r} on this Zenoh network "
                            f"(no token at {self._alive_key}); is `dynabrain serve` running, with this name?")

    def world_alive(self, timeout: float = 1.0) -> bool:
        """True when the world's liveliness token is present."""
        replies = self._session.liveliness().get(self._alive_key, timeout=timeout)
        return any(r.ok is not None for r in replies)

    def reattach(self) -> None:
        """Accept the world as it is now (after `WorldRestartedError`): the next call learns the new instance."""
        self._instance = None

    @property
    def instance(self) -> int | None:
        return self._instance

    # -- the World API --------------------------------------------------------------------------------------
    def tick(self, n: int = 1, *, view: View | None = None, timeout: float | None = None) -> Any:
        """Advance ``n`` steps; returns the new tick, or the view's `StateFrame` after the steps."""
        if view is None:
            self.call("tick", timeout, n=n)
            return self.last_tick
        if timeout is None:
            return self._state_call("tick", view, n=n, view=view.id)
        return self._frame(self.call("tick", timeout, n=n, view=view.id), view)

    def backtick(self, n: int = 1) -> int:
        """Go back ``n`` ticks, exactly; returns the tick."""
        self.call("backtick", n=n)
        return self.last_tick

    def start(self, realtime: bool | float = False, *, until: float | None = None) -> dict[str, Any]:
        return self.call("start", realtime=realtime, until=until)

    def stop(self) -> dict[str, Any]:
        """End the world's loop, and the tick running on it (its caller gets `TickStoppedError`);
        ``stopped`` in the reply says how far that tick got, or is None."""
        return self.call("stop")

    def make(self, objects: Sequence[str] | str, others: str = "frozen") -> list[str]:
        """Simulate only ``objects``; ``others``: ``frozen`` (static obstacles) or ``absent`` (out of the
        simulation). Returns the selection."""
        extra = {} if others == "frozen" else {"others": others}
        return self.call("make", objects=[objects] if isinstance(objects, str) else list(objects), **extra)

    def make_joint(self, a: str, b: str, name: str | None = None, *, kind: str = "weld",
                   axis: Sequence[float | str] | None = None, anchor: Sequence[float | str] | None = None) -> str:
        """Join two bodies as they stand: ``weld``, ``hinge`` (about ``axis`` through ``anchor``), ``slider``
        (along ``axis``) or ``ball`` (about ``anchor``); world frame. Returns the joint's name."""
        extra = {k: list(v) for k, v in (("axis", axis), ("anchor", anchor)) if v is not None}
        return self.call("make_joint", a=a, b=b, name=name, **({"kind": kind} if kind != "weld" else {}), **extra)

    def add_body(self, name: str, shape: str, **fields: Any) -> dict[str, Any]:
        """Add a body to the running world (`World.add_body`'s fields: ``size``, ``pos``, ``quat``, ``mass``,
        ``color``, ``friction``, ``restitution``, ``mesh`` (``{vertices, faces}``), ``scale``, ``joint``),
        numbers in SI or strings with units. Returns ``{body, signals}``."""
        return self.call("add_body", name=name, shape=shape, **{k: p.plain(v) for k, v in fields.items()})

    def remove_body(self, name: str) -> dict[str, Any]:
        return self.call("remove_body", name=name)

    def set_material(self, body: str, **coefficients: float | None) -> dict[str, Any]:
        """A body's own ``friction`` and/or ``restitution`` (None: the core's again); returns both, now."""
        return self.call("set_material", body=body, **coefficients)

    def remove_joint(self, name: str) -> None:
        self.call("remove_joint", name=name)

    def no_collision(self, objects: Sequence[str]) -> None:
        self.call("no_collision", objects=list(objects))

    def place(self, body: str, pos: Sequence[float], quat: Sequence[float] | None = None) -> None:
        self.call("place", body=body, pos=[float(x) for x in pos],
                  quat=None if quat is None else [float(x) for x in quat])

    def set(self, name: str, value: Any) -> None:
        """Set a run-time parameter or an unconnected input. NaN goes as null (it means "unset" in an input
        that starts NaN); an infinity is refused here, nothing sent."""
        value = p.plain(value)
        if has_infinity(value):
            raise BadRequestError("bad_request", f"{name}: an infinite value cannot be set; nothing sent", "set")
        self.call("set", name=name, value=value)

    def get(self, name: str) -> Any:
        value = self.call("get", name=name)
        if isinstance(value, list):
            with contextlib.suppress(TypeError, ValueError):
                return np.asarray([np.nan if v is None else v for v in value] if value and value[0] is None
                                  else value, dtype=np.float64)
        return np.nan if value is None else value

    def add_module(self, spec: dict[str, Any] | None = None, **fields: Any) -> dict[str, Any]:
        """Add a module written as in a scenario: ``add_module(name="k", python="pkg.mod:Class",
        params={...}, connect=[[src, dst]])``."""
        return self.call("add_module", module={**(spec or {}), **fields})

    def remove_module(self, name: str) -> list[str]:
        return self.call("remove_module", name=name)

    def connect(self, src: str, dst: str, *, delay: bool = False) -> None:
        self.call("connect", src=src, dst=dst, delay=delay)

    def disconnect(self, dst: str) -> None:
        self.call("disconnect", dst=dst)

    def snapshot(self) -> Snapshot:
        r = self.call("snapshot")
        return Snapshot(int(r["snapshot"]), int(r["tick"]))

    def restore(self, snapshot: Snapshot | int) -> None:
        self.call("restore", snapshot=snapshot.id if isinstance(snapshot, Snapshot) else int(snapshot))

    def drop_snapshot(self, snapshot: Snapshot | int) -> None:
        self.call("drop_snapshot", snapshot=snapshot.id if isinstance(snapshot, Snapshot) else int(snapshot))

    def fork(self, name: str | None = None) -> BrainClient:
        """An independent copy of the world, served beside it and owned by this brain; ``close()`` it."""
        r = self.call("fork", name=name)
        return BrainClient(r["world"], timeout=self.timeout, _parent=self)

    def status(self) -> dict[str, Any]:
        return self.call("status")

    def batch(self, ticks: int, *, branches: int | None = None,
              starts: Snapshot | int | Sequence[Snapshot | int] | None = None,
              inputs: Mapping[str, Any] | None = None, params: Mapping[str, Any] | None = None,
              record: Sequence[str] = (), keep_states: bool = False, timeout: float | None = None) -> BatchReply:
        """``branches`` futures of the world, ``ticks`` ticks each, in one call; the world is not changed.
        As `dynabrain.orchestrator.brain.Batch.run`: ``starts`` None (the world now), a snapshot, or one per
        branch; ``inputs`` port -> values ``(ticks, *port)`` or ``(branches, ticks, *port)``; ``params``
        run-time parameter -> a value, or one per branch; ``record`` the signals returned. With
        ``keep_states`` each branch's final state becomes a snapshot (`restore` continues from it). The
        server's backend runs it; pass a ``timeout`` (s) long enough for the work."""
        if isinstance(starts, Sequence):
            starts = [snapshot_id(s) for s in starts]
        elif starts is not None:
            starts = snapshot_id(starts)
        frame = self.call("batch", timeout, ticks=integer(ticks, "ticks"),
                          branches=None if branches is None else integer(branches, "branches"), starts=starts,
                          inputs={str(n): finite_list(v, str(n)) for n, v in (inputs or {}).items()},
                          params={str(n): p.plain(v) for n, v in (params or {}).items()},
                          record=[record] if isinstance(record, str) else list(record), keep_states=keep_states)
        if not isinstance(frame, frames.Frame) or frame.kind != frames.BATCH:
            raise BridgeError(f"batch: the server did not answer with a batch frame ({type(frame).__name__})")
        if self._instance is not None and frame.source != self._instance:
            raise BridgeError("batch frame from another server instance")
        self.last_tick = frame.seq
        return BatchReply.from_frame(frame)

    # -- views and streams ----------------------------------------------------------------------------------
    def view(self, signals: Sequence[str] | str) -> View:
        """Register signals (names or patterns) to read as one binary frame (`read`, `tick(view=)`)."""
        return View.from_reply(self.call("view", signals=[signals] if isinstance(signals, str) else list(signals)))

    def read(self, view: View) -> StateFrame:
        return self._state_call("read", view, view=view.id)

    def drop_view(self, view: View) -> None:
        self.call("drop_view", view=view.id)

    def _state_call(self, name: str, view: View, /, **args: Any) -> StateFrame:
        """`call` then `_frame`, for calls a lock-step brain makes each step (``tick`` with a view, ``read``):
        the same checks in fewer steps. A reply that is not the expected frame (an error, a JSON reply, a
        frame that fails a check) goes the general way, which raises what it says."""
        if self._closed:
            raise BridgeError(f"this client of world {self.world!r} is closed")
        payload = self._payload(name, args)
        querier = self._queriers.get(name)
        if querier is None:
            querier = self._queriers[name] = self._session.declare_querier(p.call_key(self.world, name),
                                                                           timeout=self.timeout)
        reply = next(iter(querier.get(payload=payload, encoding=JSON)), None)
        if reply is None:
            raise self._no_answer(name, self.timeout)
        sample = reply.ok
        if sample is not None:
            data = sample.payload.to_bytes()
            head = frames.state_header(data, view.id, view.size, self._instance)
            if head is not None:
                self.last_tick = head[0]
                return StateFrame(head[0], head[1], np.frombuffer(data, "<f8", view.size, frames.HEADER_SIZE), view)
        return self._frame(self._decode(name, reply, self.timeout), view)

    def _frame(self, frame: frames.Frame, view: View) -> StateFrame:
        if frame.kind != frames.STATE:
            raise BridgeError(f"expected a state frame, got a {frames.KINDS[frame.kind]} frame")
        if frame.aux != view.id or frame.values.size != view.size:
            raise BridgeError(f"frame of view {frame.aux} with {frame.values.size} values does not match view "
                              f"{view.id} ({view.size} values)")
        if self._instance is not None and frame.source != self._instance:
            raise BridgeError("state frame from another server instance")
        self.last_tick = frame.seq
        return StateFrame(frame.seq, frame.stamp, frame.values, view)

    def subscribe_state(self, callback: Callable[[StateFrame], None]) -> Any:
        """Call ``callback`` with each published state frame (layout from `status`)."""
        stream = self.status().get("stream")
        if stream is None:
            raise BridgeError(f"world {self.world!r} publishes no state stream")
        view = View.from_reply(stream)

        def on_sample(sample: zenoh.Sample) -> None:
            frame = frames.unpack(payload_bytes(sample.payload), frames.STATE)
            if frame.values.size == view.size:
                callback(StateFrame(frame.seq, frame.stamp, frame.values, view))

        return self._subscribe(p.key(self.world, "state"), on_sample)

    def subscribe_events(self, callback: Callable[[dict[str, Any]], None]) -> Any:
        """The world's events as dicts (``tick``, ``kind``, ``detail``, ``source``); an edit's is its typed
        record again by ``dynabrain.orchestrator.kernel.edits.edit_of(event["kind"], event["detail"])``."""
        return self._subscribe(p.key(self.world, "events"),
                               lambda s: callback(json.loads(payload_bytes(s.payload))))

    def subscribe_shadow(self, robot: str, callback: Callable[[frames.Frame], None]) -> Any:
        """SHADOW frames of a robot: ``values[:n]`` predicted, ``values[n:]`` measured (``n = frame.aux``)."""
        return self._subscribe(p.robot_key(self.world, robot, "shadow"),
                               lambda s: callback(frames.unpack(payload_bytes(s.payload), frames.SHADOW)))

    def _subscribe(self, key: str, handler: Callable[[zenoh.Sample], None]) -> Any:
        sub = self._session.declare_subscriber(key, handler)
        self._subs.append(sub)
        return sub

    # -- holds, inputs, robots ------------------------------------------------------------------------------
    def acquire(self, lease: float = 30.0) -> dict[str, Any]:
        """Hold the world: other brains get read-only calls until `release` (or ``lease`` s of silence)."""
        return self.call("acquire", lease=lease)

    def release(self) -> dict[str, Any]:
        return self.call("release")

    @contextlib.contextmanager
    def hold(self, lease: float = 30.0) -> Iterator[BrainClient]:
        self.acquire(lease)
        try:
            yield self
        finally:
            self.release()

    def set_inputs(self, values: dict[str, Any]) -> None:
        """Publish input values (no reply): the world applies them at its next step boundary."""
        if self._set_pub is None:
            self._set_pub = self._session.declare_publisher(p.key(self.world, "in", "set"), encoding=JSON,
                                                            express=True)
        self._set_pub.put(p.encode({"v": p.VERSION, "brain": self.brain, "values": p.plain(values)}))

    def motion(self, robot: str, targets: Sequence[float] | dict[str, float], route: str = "sim") -> dict[str, Any]:
        """Servo targets to the simulation, the robot or both (``route``), with a reply saying what was done."""
        return self.call("motion", robot=robot, targets=target_values(targets), route=route, sent_ns=time.time_ns())

    def send_motion(self, robot: str, targets: Sequence[float] | dict[str, float], route: str = "sim") -> None:
        """Publish a motion command (no reply): for control loops; errors arrive as events."""
        if self._motion_pub is None:
            self._motion_pub = self._session.declare_publisher(p.key(self.world, "in", "motion"), encoding=JSON,
                                                               priority=zenoh.Priority.REAL_TIME, express=True)
        self._motion_pub.put(p.encode({"v": p.VERSION, "brain": self.brain, "robot": robot,
                                       "targets": target_values(targets), "route": route, "sent_ns": time.time_ns()}))

    def robot_enable(self, robot: str) -> dict[str, Any]:
        """Enable the robot: it then takes moves and programs; unless one reaches it within the enable
        window (``enable_window_ms`` of the reply: the link's deadline) it safe-stops."""
        return self.call("robot_enable", robot=robot)

    def robot_stop(self, robot: str) -> dict[str, Any]:
        return self.call("robot_stop", robot=robot)

    def robot_status(self, robot: str) -> dict[str, Any]:
        """The link's state: ``alive`` (``lost_tick``), ``mode`` (``mode_tick``, ``reason``), ``counts``,
        ``program`` (the last one the servo began, and the robot's word on it), ``last_state`` (measured)."""
        return self.call("robot_status", robot=robot)

    def robot_wait(self, robot: str, timeout: float = 60.0, poll_s: float = 0.02) -> dict[str, Any]:
        """Wait until the robot has played to its end the last program the rig's servo began (a brain's
        ``set("<servo>.sequence", [...])`` reaches the simulation and the robot), and return `robot_status`:
        ``last_state`` says where the robot ended. `RobotLostError` when the robot goes away meanwhile (naming
        the world's tick when the link lost it); `RobotStoppedError` when the program was not sent, or the
        robot ignored, refused or stopped it; `CallTimeoutError` after ``timeout`` s (a looping program never
        ends)."""
        end = time.monotonic() + timeout
        while True:
            status = self.robot_status(robot)
            robot_check(robot, status)
            played = (status.get("program") or {}).get("robot")
            if played is not None and played.get("state") == "done":
                return status
            if time.monotonic() > end:
                raise CallTimeoutError(f"robot {robot!r}: its program is not done after {timeout:g} s (the robot's "
                                       f"word: {played})")
            time.sleep(poll_s)

    # -- closing --------------------------------------------------------------------------------------------
    def close(self) -> None:
        """A fork: close it on the server. The main client: undeclare and close the session."""
        if self._closed:
            return
        if not self._owner:
            with contextlib.suppress(BridgeError):
                self.call("close")
        self._closed = True
        for ent in [*self._subs, *self._queriers.values()]:
            with contextlib.suppress(Exception):
                ent.undeclare()
        if self._owner:
            for pub in (self._motion_pub, self._set_pub, self._token):
                if pub is not None:
                    with contextlib.suppress(Exception):
                        pub.undeclare()
            with contextlib.suppress(zenoh.ZError):  # a peer frozen mid-close: the session is gone for us anyway
                self._session.close()

    def __enter__(self) -> BrainClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_CACHED_CALLS = frozenset({"tick", "read", "backtick", "status"})
