"""`BridgeServer`: a World exposed over Zenoh in the key space ``dynabrain/<world>/...`` (`PROTOCOL.md`).

- every brain call is a query on ``call/<name>``, validated (`protocol`), run one at a time, and answered
  with a reply or an error reply; the server goes on whatever the payload;
- state frames and events are published (`streams`); brain inputs arrive by subscription (``in/set``,
  ``in/motion``) and are applied at the next step boundary;
- ``alive`` is the world's liveliness token; brains declare ``brain/<id>``; a brain that holds the world
  (``acquire``) keeps others to read-only calls until it releases, its lease ends, or its token goes;
- forks are served as worlds of their own, owned by the brain that made them;
- ``batch`` runs N futures of a served world on one `Batch` per world, kept between calls (`batching`);
- robot rigs link real robots (`robot_link`).

Calls are serialised by one lock. A short call runs at once on the Zenoh thread that delivered it; a
long one (many ticks, or a call `protocol.TABLE` marks ``slow``: a new module, a fork) or one arriving
while another runs goes to a worker thread in arrival order, so Zenoh's threads are never blocked for
long. Read-only calls and ``stop`` that arrive while another call runs do not wait behind the queue: a
long ``tick`` runs in slices (`calls.SLICE_S`) and answers them between two slices (a ``stop`` ends it
there, error ``stopped`` with the ticks done), and the worker answers them before its next queued call.
Each call is answered by the ``do_<call>`` method the table names: this server's (``server`` calls:
holds, forks, the loop, robots, its status) or its `WorldService`'s (the world's calls).
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import zenoh

from dynabrain.orchestrator.kernel.errors import DynabrainError, ModuleError, RollbackError, WorldClosedError
from dynabrain.orchestrator.kernel.world import World

from . import protocol as p
from .batching import BatchSettings
from .calls import DEFAULT_ALLOW_PYTHON, StoppedTickError, WorldService
from .holds import BusyError, Hold
from .loop import Loop
from .robot_link import RobotLink
from .streams import EventSink, StateStream
from .zenoh_io import FRAME, JSON, Settings, open_session, payload_bytes

if TYPE_CHECKING:
    from dynabrain.orchestrator.logs.live import LiveOptions, LiveView

    from .ros2 import Ros2Bridge, Ros2Options

_log = logging.getLogger("dynabrain.bridge")
MAX_FORKS = 16
URGENT = p.READ_ONLY | {"stop"}
"""Calls answered between two slices of a long tick, and before the queued calls."""
_STEP_CALLS = frozenset({"tick", "read"})
"""Calls `WorldService.step_frame` may answer (a one-step tick with a view, a read)."""


class _RestartedError(DynabrainError):
    pass


@dataclass
class ServeOptions:
    """What `dynabrain serve` exposes, and how."""

    name: str | None = None
    """Key-space name (``dynabrain/<name>/...``); default: the world's name."""
    stream: Sequence[str] | None = None
    """Signals (names or patterns) of the state stream; default: the core's body poses and joint states."""
    decimate: int = 1
    """Publish a state frame every ``decimate`` ticks (0: no state stream)."""
    robots: dict[str, str] = field(default_factory=dict)
    """Robot rigs: robot name -> the PDServo module whose targets its motion commands set."""
    deadline_ns: int = 100_000_000
    """A motion command older than this is not forwarded to the robot; the robot stops when none arrives."""
    allow_python: Sequence[str] = DEFAULT_ALLOW_PYTHON
    base_dir: str | None = None
    inline_ticks: int = 100
    """A ``tick`` of at most this many steps runs on the Zenoh thread that delivered it."""
    batch: BatchSettings = field(default_factory=BatchSettings)
    """How ``batch`` calls run on the served world (its forks run theirs with the ``serial`` backend)."""
    trial_params: bool = True
    """Try a brain's run-time parameter change on a fork first, one tick, and refuse one that makes it fail."""
    tokenless_lease_s: float = p.TOKENLESS_LEASE_S
    """Most seconds of silence a hold lasts while its brain has no liveliness token."""
    ros2: Ros2Options | None = None
    """Also show the world to ROS 2 nodes on rmw_zenoh (`ros2`): joint states, /tf, /clock, joint commands."""
    live: LiveOptions | None = None
    """Also serve the world to Foxglove (`logs.live`): its /bus, /tf, /scene and events as brains drive it."""


@dataclass
class _Ticking:
    """The ``tick`` running now: on which world, for which brain, how far; who asked it to stop."""

    served: _Served
    brain: str | None
    asked: int
    done: int = 0
    stop_by: str | None = None

    def describe(self) -> dict[str, Any]:
        return {"world": self.served.name, "call": "tick", "brain": self.brain, "ticks_done": self.done,
                "ticks_asked": self.asked}


@dataclass
class _Served:
    name: str
    service: WorldService
    queryables: list[Any] = field(default_factory=list)
    owner: str | None = None
    closed: bool = False

    def undeclare(self) -> None:
        for queryable in self.queryables:
            with contextlib.suppress(Exception):
                queryable.undeclare()
        self.queryables = []


class BridgeServer:
    """Serves one World (and its forks) over one Zenoh session. ``open()`` then ``close()``."""

    def __init__(self, world: World, settings: Settings | None = None, options: ServeOptions | None = None):
        self.world = world
        self.settings = settings or Settings(listen=["tcp/127.0.0.1:7447"])
        self.options = options or ServeOptions()
        self.name = p.check_world_name(self.options.name or world.name)
        self.instance = int.from_bytes(os.urandom(6), "little")  # < 2**53: exact in any JSON reader
        self.endpoints: list[str] = []
        self.session: zenoh.Session | None = None
        self.brains: set[str] = set()
        self.links: dict[str, RobotLink] = {}
        self._served: dict[str, _Served] = {}
        self._call_lock = threading.Lock()
        self._jobs: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._urgent: deque[tuple] = deque()
        self._ticking: _Ticking | None = None
        self._worker: threading.Thread | None = None
        self._entities: list[Any] = []
        self._fork_count = 0
        self._handlers = p.handlers(self, server=True)
        self.ros2: Ros2Bridge | None = None
        self.live: LiveView | None = None

    # -- lifecycle ------------------------------------------------------------------------------------------
    def open(self) -> list[str]:
        """Open the session and declare everything; returns the endpoints clients connect to. The live view
        (``options.live``) starts first: a port in use raises before anything is declared."""
        if self.options.live is not None:
            self.live = self.options.live.start(self.world)
        try:
            self.session, self.endpoints = open_session(self.settings)
        except BaseException:
            self._close_live()
            raise
        try:
            self._declare()
        except BaseException:
            self.close()
            raise
        return self.endpoints

    def _declare(self) -> None:
        s, name, opts = self.session, self.name, self.options
        self.events = EventSink(s, name)
        self.events.tick_of = lambda: self.world.tick_count
        self.hold = Hold(name, self.events.emit, tokenless_lease=opts.tokenless_lease_s)
        service = WorldService(self.world, instance=self.instance, allow_python=opts.allow_python,
                               base_dir=opts.base_dir, stream=self._stream_signals() if opts.decimate else (),
                               batch=opts.batch, trial_params=opts.trial_params)
        service.on_input_error = lambda msg: self.events.emit("input_error", message=msg)
        self.main = self._serve(name, service)
        self.stream = StateStream(s, name, service, self.events, max(opts.decimate, 1))
        self.world.observe(self.stream)
        self.loop = Loop(service, lambda reason, error: self.events.emit("loop_end", reason=reason, error=error))
        for robot, servo in opts.robots.items():
            rig = service.add_rig(robot, servo)
            link = RobotLink(s, name, rig, service, self.events, deadline_ns=opts.deadline_ns)
            self.links[robot] = link
            self.stream.tick_hooks.append(link.on_tick)
        if opts.ros2 is not None:
            from .ros2 import BRAIN_ID, Ros2Bridge  # rosbags is loaded only when ROS 2 is asked for

            self.ros2 = Ros2Bridge(s, name, service, self.events, opts.ros2,
                                   drive=lambda robot, targets: self._drive(BRAIN_ID, robot, targets))
            self.stream.tick_hooks.append(self.ros2.on_tick)
        live = s.liveliness()
        self._entities += [
            live.declare_subscriber(p.key(name, "brain", "*"), self._on_brain, history=True),
            s.declare_subscriber(p.key(name, "in", "set"), self._on_set_input),
            s.declare_subscriber(p.key(name, "in", "motion"), self._on_motion_input),
        ]
        self._worker = threading.Thread(target=self._work, daemon=True, name=f"dynabrain-serve-calls-{name}")
        self._worker.start()
        self._entities.append(live.declare_token(p.key(name, "alive")))

    def _stream_signals(self) -> list[str]:
        if self.options.stream is not None:
            return list(self.options.stream)
        signals = set(self.world.signals)
        core = self.world.core.name if self.world.core is not None else ""
        wanted = [f"{core}.{b}" for b in ("body_pos", "body_quat", "joint_q", "joint_qd")]
        return [s for s in wanted if s in signals]

    def _serve(self, name: str, service: WorldService, owner: str | None = None) -> _Served:
        """One complete queryable on ``call/*`` answers every call (and ``unknown_call`` for the rest).
        One queryable per call would let access control hide calls by their declarations, but a second
        queryable matching a query (a catch-all for unknown names) doubles the cost of every call in
        Zenoh, so access control filters the queries themselves (see zenoh-secure.json5)."""
        served = _Served(name, service, owner=owner)
        service.between_slices = lambda done, asked: self._between_slices(served, done, asked)
        served.queryables.append(self.session.declare_queryable(
            p.key(name, "call", "*"), lambda query: self._on_query(served, query), complete=True))
        self._served[name] = served
        return served

    def close(self) -> None:
        """Stop the loop, tell robots to stop, undeclare everything, close forks and the session. The
        served World itself stays open (its owner closes it)."""
        self._close_live()
        if self.session is None:
            return
        with contextlib.suppress(Exception):
            self.loop.stop()
        for link in self.links.values():
            with contextlib.suppress(Exception):
                link.stop("the bridge is closing")
            link.close()
        self._jobs.put(None)
        if self._worker is not None:
            self._worker.join(timeout=10)
        with self._call_lock:
            for served in list(self._served.values()):
                served.undeclare()
                served.service.close()  # the batch's workers
                if served is not getattr(self, "main", None):
                    served.service.world.close()
            self._served.clear()
        if self.ros2 is not None:
            self.ros2.close()
        if getattr(self, "stream", None) is not None:
            with contextlib.suppress(ValueError):
                self.world.unobserve(self.stream)
            self.stream.close()
        for ent in reversed(self._entities):
            with contextlib.suppress(Exception):
                ent.undeclare()
        with contextlib.suppress(Exception):
            self.events.close()
        session, self.session = self.session, None
        session.close()

    def _close_live(self) -> None:
        live, self.live = self.live, None
        if live is not None:
            with contextlib.suppress(ValueError):
                self.world.unobserve(live)
            live.close()

    def __enter__(self) -> BridgeServer:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- queries --------------------------------------------------------------------------------------------
    def _on_query(self, served: _Served, query: zenoh.Query) -> None:
        key = query.key_expr
        call = str(key).rsplit("/", 1)[-1]
        try:
            env, args = p.decode_command(call, payload_bytes(query.payload))
        except p.ProtocolError as exc:
            self._reply_error(query, exc.kind, str(exc), call)
            return
        except Exception as exc:  # a payload Zenoh itself could not hand over
            self._reply_error(query, "bad_request", f"{type(exc).__name__}: {exc}", call)
            return
        job = (served, call, env, args, query, key)
        quick = call not in p.SLOW and not (call == "tick" and args.n > self.options.inline_ticks)
        if quick and self._jobs.empty() and self._call_lock.acquire(blocking=False):
            try:
                self._run(job)
            finally:
                self._call_lock.release()
            return
        if call in URGENT:  # answered between two slices of a long tick, or by the worker before its queue
            self._urgent.append(job)
            self._jobs.put(self._run_urgent)
            return
        self._jobs.put(lambda: self._run(job))

    def _run_urgent(self) -> None:
        """Answer the read-only calls and stops waiting (the caller holds the call lock)."""
        while True:
            try:
                job = self._urgent.popleft()
            except IndexError:
                return
            self._run(job)

    def _between_slices(self, served: _Served, done: int, asked: int) -> str | None:
        """Between two slices of a long tick on ``served`` (the call lock held, the world lock free):
        answer the urgent calls; the brain that stopped the tick, or None."""
        ticking = self._ticking
        if ticking is not None:
            ticking.done = done
        self._run_urgent()
        return ticking.stop_by if ticking is not None else None

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                with self._call_lock:
                    self._run_urgent()  # read-only calls and stops go before the queue
                    job()
            except Exception:  # a bug in a job: log it, keep serving
                _log.exception("bridge job failed")

    def _enqueue(self, task: Callable[[], None]) -> None:
        self._jobs.put(task)

    def _run(self, job: tuple) -> None:
        served, call, env, args, query, key = job
        try:
            result = self._execute(served, call, env, args)
            if result.__class__ is bytes:
                query.reply(key, result, encoding=FRAME)
            else:
                body = {"tick": served.service.world.tick_count, "instance": self.instance, "result": result}
                query.reply(key, p.encode(body), encoding=JSON)
        except Exception as exc:
            kind, message = _classify(exc)
            if kind == "internal":
                _log.exception("call %s failed unexpectedly", call)
            self._reply_error(query, kind, message, call, getattr(exc, "detail", None))  # drops the query
            return
        try:
            query.drop()  # the final answer: the brain stops waiting now
        except Exception as exc:  # the brain is gone
            _log.debug("dropping the query of %s: %s", call, exc)

    def _reply_error(self, query: zenoh.Query, kind: str, message: str, call: str | None,
                     detail: dict[str, Any] | None = None) -> None:
        body = {"error": kind, "message": message, "call": call, "instance": self.instance}
        if detail is not None:
            body["detail"] = detail
        try:
            query.reply_err(p.encode(body), encoding=JSON)
        except Exception as exc:  # the brain is gone; nothing to answer
            _log.debug("error reply to %s not sent: %s", call, exc)
        with contextlib.suppress(Exception):
            query.drop()

    def _execute(self, served: _Served, call: str, env: p.Envelope, args: Any) -> Any:
        if env.instance is not None and env.instance != self.instance:
            raise _RestartedError(f"the server restarted: this is instance {self.instance}, the brain expected "
                                  f"{env.instance}; the world's state is new (call reattach() to go on with it)")
        if served.closed:
            raise WorldClosedError(f"world {served.name!r} is closed")
        brain = env.brain
        if served.owner is not None and brain != served.owner:
            raise BusyError(f"world {served.name!r} is a fork owned by brain {served.owner!r}")
        hold = self.hold if served is self.main else None
        if call in _STEP_CALLS and (hold is None or not hold.held):
            # the lock-step hot path: one tick (no slices, so no `_Ticking` anyone could see) and a frame;
            # no hold to check or renew. None: not that simple, the general way below runs it.
            frame = served.service.step_frame(args)
            if frame is not None:
                return frame
        if hold is not None:
            hold.check(call, brain)
            hold.enter(brain)
        handler = self._handlers.get(call)  # a server call; otherwise the world's
        ticking = call == "tick"
        outer = self._ticking
        if ticking:
            self._ticking = _Ticking(served, brain, args.n)
        try:
            return handler(served, env, args) if handler is not None else served.service.call(call, args)
        finally:
            if ticking:
                self._ticking = outer
            if hold is not None:
                hold.leave(brain)

    # -- holds ----------------------------------------------------------------------------------------------
    def do_acquire(self, served: _Served, env: p.Envelope, args: p.AcquireArgs) -> dict[str, Any]:
        self._require_main(served, "acquire")
        return self.hold.acquire(env.brain, args.lease, has_token=env.brain in self.brains)

    def do_release(self, served: _Served, env: p.Envelope, args: p.NoArgs) -> dict[str, Any]:
        self._require_main(served, "release")
        return self.hold.release(env.brain)

    def _require_main(self, served: _Served, call: str) -> None:
        if served is not self.main:
            raise DynabrainError(f"{call} is for the served world {self.name!r}, not for fork {served.name!r}")

    # -- brains ---------------------------------------------------------------------------------------------
    def _on_brain(self, sample: zenoh.Sample) -> None:
        brain = str(sample.key_expr).rsplit("/", 1)[-1]
        if sample.kind == zenoh.SampleKind.PUT:
            self.brains.add(brain)
            self.hold.token_seen(brain)
            self.events.emit("brain_joined", brain=brain)
            return
        self.brains.discard(brain)
        self.events.emit("brain_left", brain=brain)
        for link in self.links.values():
            link.brain_gone(brain)  # at once: a robot must not wait behind a long call
        self._enqueue(lambda: self._forget_brain(brain))

    def _forget_brain(self, brain: str) -> None:
        self.hold.forget(brain)
        for served in [s for s in self._served.values() if s.owner == brain]:
            self._close_fork(served, reason=f"brain {brain!r} is gone")

    # -- forks ----------------------------------------------------------------------------------------------
    def do_fork(self, served: _Served, env: p.Envelope, args: p.ForkArgs) -> dict[str, Any]:
        if len(self._served) - 1 >= MAX_FORKS:
            raise DynabrainError(f"too many forks ({MAX_FORKS}); close some first")
        self._fork_count += 1
        name = p.check_world_name(args.name or f"{self.name}-fork{self._fork_count}")
        if name in self._served:
            raise DynabrainError(f"a world named {name!r} is already served here")
        world = served.service.world.fork(name)
        svc = WorldService(world, instance=self.instance, allow_python=self.options.allow_python,
                           base_dir=self.options.base_dir, trial_params=self.options.trial_params,
                           batch=BatchSettings("serial", max_ticks=self.options.batch.max_ticks))
        svc.rigs = dict(served.service.rigs)
        self._serve(name, svc, owner=env.brain)
        self.events.emit("fork", world=name, brain=env.brain, tick=world.tick_count)
        return {"world": name, "tick": world.tick_count}

    def do_close(self, served: _Served, env: p.Envelope, args: p.NoArgs) -> None:
        if served is self.main:
            raise DynabrainError(f"close is for forks; the served world {self.name!r} closes with its server")
        self._close_fork(served, reason=f"closed by {env.brain!r}")

    def _close_fork(self, served: _Served, reason: str) -> None:
        served.closed = True
        served.undeclare()
        served.service.close()
        served.service.world.close()
        self._served.pop(served.name, None)
        self.events.emit("fork_closed", world=served.name, reason=reason)

    # -- loop -----------------------------------------------------------------------------------------------
    def do_start(self, served: _Served, env: p.Envelope, args: p.StartArgs) -> dict[str, Any]:
        self._require_main(served, "start")
        return self.loop.start(args.realtime, args.until)

    def do_stop(self, served: _Served, env: p.Envelope, args: p.NoArgs) -> dict[str, Any]:
        """End the loop (the served world's) and the tick running on ``served``, if any: that tick stops
        before its next slice and answers ``stopped``."""
        out = self.loop.stop() if served is self.main else {"running": False, "error": None}
        ticking = self._ticking
        if ticking is not None and ticking.served is served and ticking.stop_by is None:
            ticking.stop_by = env.brain or "(no id)"
            out["stopped"] = {"brain": ticking.brain, "ticks_done": ticking.done, "ticks_asked": ticking.asked}
        else:
            out["stopped"] = None
        return out

    # -- robots ---------------------------------------------------------------------------------------------
    def do_motion(self, served: _Served, env: p.Envelope, args: p.MotionArgs) -> dict[str, Any]:
        return self.motion(served, args, env.brain)

    def motion(self, served: _Served, args: p.MotionArgs, brain: str | None) -> dict[str, Any]:
        svc = served.service
        rig = svc.rig(args.robot)
        out: dict[str, Any] = {}
        inputs = svc.motion_inputs(rig, args.targets)  # checks joints and values for both routes
        vector = None
        if args.route != "sim":
            if served is not self.main:
                raise DynabrainError(f"fork {served.name!r} has no robot; route motion to 'sim'")
            vector = _full_targets(rig.joints, args.targets, args.robot)
        if args.route != "robot":
            svc.submit(inputs)
            out["sim"] = "applied at the next step"
        if vector is not None:
            out["robot"] = self.links[args.robot].forward(vector, brain, args.sent_ns, args.seq)
        return out

    def _robot(self, robot: str):
        link = self.links.get(robot)
        if link is None:
            self.main.service.rig(robot)  # raises naming the robots there are
            raise DynabrainError(f"no robot {robot!r}")
        return link

    def do_robot_enable(self, served: _Served, env: p.Envelope, args: p.RobotRef) -> dict[str, Any]:
        self._require_main(served, "robot_enable")
        return self._robot(args.robot).enable(env.brain)

    def do_robot_stop(self, served: _Served, env: p.Envelope, args: p.RobotRef) -> dict[str, Any]:
        self._require_main(served, "robot_stop")
        self._robot(args.robot).stop(f"asked by brain {env.brain!r}")
        return {"sent": "stop"}

    def do_robot_status(self, served: _Served, env: p.Envelope, args: p.RobotRef) -> dict[str, Any]:
        self._require_main(served, "robot_status")
        return self._robot(args.robot).status()

    # -- inputs ---------------------------------------------------------------------------------------------
    def _input_allowed(self, brain: str | None, what: str) -> bool:
        holder = self.hold.holder()
        if holder is not None and holder != brain:
            self.events.emit("input_refused", input=what, brain=brain, holder=holder)
            return False
        return True

    def _on_set_input(self, sample: zenoh.Sample) -> None:
        try:
            msg = p.decode_input(p.SetInput, payload_bytes(sample.payload), "in/set")
        except p.ProtocolError as exc:
            self.events.emit("input_error", message=str(exc))
            return
        if self._input_allowed(msg.brain, "set"):
            self.main.service.submit(dict(msg.values))

    def _drive(self, brain: str, robot: str, targets: list[float] | dict[str, float]) -> bool:
        """Targets from another middleware (ROS 2) for a rig, routed to the simulation as a motion input;
        False when a hold refused them (an ``input_refused`` event)."""
        if not self._input_allowed(brain, "motion"):
            return False
        self.motion(self.main, p.MotionArgs(robot=robot, targets=targets, route="sim"), brain)
        return True

    def _on_motion_input(self, sample: zenoh.Sample) -> None:
        try:
            msg = p.decode_input(p.MotionInput, payload_bytes(sample.payload), "in/motion")
            if self._input_allowed(msg.brain, "motion"):
                self.motion(self.main, msg, msg.brain)
        except DynabrainError as exc:
            self.events.emit("input_error", message=f"in/motion: {exc}")

    # -- status ---------------------------------------------------------------------------------------------
    def do_status(self, served: _Served, env: p.Envelope, args: p.NoArgs) -> dict[str, Any]:
        out = served.service.status()
        holder = self.hold.holder()
        out["server"] = {
            "world": self.name, "instance": self.instance, "endpoints": self.endpoints,
            "brains": sorted(self.brains), "holder": holder, "owner": served.owner,
            "forks": [s.name for s in self._served.values() if s is not self.main],
            "loop": {"running": self.loop.running, "realtime": self.loop.realtime, "error": self.loop.error},
            "stream_frames": self.stream.frames_sent, "input_errors": served.service.input_errors[-5:],
            "running": self._ticking.describe() if self._ticking is not None else None,
        }
        if self.ros2 is not None and served is self.main:
            out["server"]["ros2"] = self.ros2.describe()
        return out


def _full_targets(joints: tuple[str, ...], targets: list | dict, robot: str) -> np.ndarray:
    if isinstance(targets, dict):
        missing = [j for j in joints if j not in targets]
        if missing:
            raise DynabrainError(f"a motion to robot {robot!r} sets every joint; missing {', '.join(missing)}")
        return np.array([float(targets[j]) for j in joints])
    return np.array([float(v) for v in targets])


def _classify(exc: Exception) -> tuple[str, str]:
    """The error kind of the reply, and its message."""
    if isinstance(exc, p.ProtocolError):
        return exc.kind, str(exc)
    for cls, kind in ((BusyError, "busy"), (_RestartedError, "restarted"), (StoppedTickError, "stopped"),
                      (ModuleError, "module_error"),
                      (RollbackError, "rollback"), (WorldClosedError, "closed"), (DynabrainError, "refused")):
        if isinstance(exc, cls):
            return kind, str(exc)
    if isinstance(exc, (ValueError, TypeError, KeyError, IndexError)):
        return "refused", f"{type(exc).__name__}: {exc}"
    return "internal", f"{type(exc).__name__}: {exc} (a bug in the bridge; the server goes on)"
