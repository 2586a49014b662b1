"""ROS 2 over Zenoh: a served world's robot as ROS 2 topics that nodes running on ``rmw_zenoh`` see and drive.

`Ros2Bridge` speaks rmw_zenoh's wire format on the served world's Zenoh session:

- **data**: a topic's samples go on ``<domain_id>/<fully qualified name without the leading slash>/<DDS type
  name>/<type hash>`` (``0/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_a13e...``), the payload the
  message in CDR with its 4-byte encapsulation header, each sample with the attachment rmw_zenoh's subscribers
  require: a sequence number (int64), the source time (int64 ns since the epoch) and the publisher's GID
  (16 bytes), written by Zenoh's own serializer;
- **graph**: liveliness tokens under ``@ros2_lv/<domain_id>/<zenoh id>/<node id>/<entity id>/<kind>/<enclave>/
  <namespace>/<node>[/<topic>/<type>/<hash>/<qos>]`` announce the node (``NN``), its publishers (``MP``) and
  its subscriptions (``MS``), names with ``/`` written ``%``, so ``ros2 node list``, ``ros2 topic list``,
  ``ros2 topic info`` and ``ros2 topic echo`` find them.

The format is rmw_zenoh_cpp 0.2.10's (ROS 2 Jazzy: ``liveliness_utils.cpp``, ``attachment_helpers.cpp``,
``type_support_common.cpp``, ``qos.cpp`` of its ``release/jazzy`` branch), unchanged up to 0.12.0 (Rolling),
which only appends an optional field for buffer types. Messages are encoded and decoded by ``rosbags``
(its Jazzy type store, which also gives each type's RIHS01 hash), through `logs.ros2msgs`, which the logs share
(``run --log FILE --ros2-schemas``): the messages, and which joints and bodies a world's signals give.

The node ``/dynabrain_<world>`` publishes, every ``1 / rate_hz`` of simulated time as the world ticks:

- ``/clock`` (``rosgraph_msgs/msg/Clock``): the simulated time (a node with ``use_sim_time`` follows it; a
  backtick makes it jump back, which ROS 2 nodes see as a jump back in time);
- ``/tf`` (``tf2_msgs/msg/TFMessage``): each body's pose in frame ``world``, child frame the body's name;
- ``<ns>/joint_states`` (``sensor_msgs/msg/JointState``): every one-degree-of-freedom joint of the core:
  position, velocity, and the force applied (effort);

and for each robot rig ``R`` (``dynabrain serve --robot R=SERVO``) it subscribes to

- ``<ns>/R/joint_commands`` (``std_msgs/msg/Float64MultiArray``): one target per joint of the rig, in its
  order, set at the next step boundary;
- ``<ns>/R/joint_trajectory`` (``trajectory_msgs/msg/JointTrajectory``): joints by name, points reached at
  their ``time_from_start`` of simulated time from the tick the message is taken, targets interpolated
  linearly from the current ones each tick; an empty ``points`` list stops the trajectory.

Commands go the bridge's way (`BridgeServer.motion`, route ``sim``) under the id ``ros2``: refused while a
brain holds the world (an ``input_refused`` event), and a message with a wrong field (joint names, lengths,
non-finite values, bytes that are not CDR of the type) is dropped with an ``input_error`` event that names
the topic and the field; the world is unchanged.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh
import zenoh.ext

from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.observers import WorldView
from dynabrain.orchestrator.logs.ros2msgs import CLOCK, JOINT_STATE, ROS_DISTRO, TF, Codec, Ros2Signals, ros2_signals

from .calls import Rig, WorldService
from .streams import EventSink

_log = logging.getLogger("dynabrain.bridge.ros2")

RMW_ZENOH_VERSION = "0.2.10"
"""The rmw_zenoh_cpp release whose key expressions, tokens and attachment this module writes (ROS 2 Jazzy)."""
ADMIN_SPACE = "@ros2_lv"
RMW_ZENOH_DEFAULT_DEPTH = 42
"""rmw_zenoh's default history depth: a QoS equal to its default is written as an empty field."""
BRAIN_ID = "ros2"
"""The id ROS 2 commands go under in the bridge (holds, events)."""
MAX_COMMAND_BYTES = 1 << 20
MULTI_ARRAY, TRAJECTORY = "std_msgs/msg/Float64MultiArray", "trajectory_msgs/msg/JointTrajectory"
_NOT_NAME = re.compile(r"[^A-Za-z0-9_]")

Drive = Callable[[str, "list[float] | dict[str, float]"], bool]
"""Sets a rig's targets the bridge's way: ``drive(robot, targets)``; False when a hold refused it."""


@dataclass(frozen=True)
class Ros2Options:
    """How a served world shows itself to ROS 2."""

    domain_id: int = 0
    """The ROS domain (``ROS_DOMAIN_ID``): the first chunk of every key."""
    rate_hz: float = 100.0
    """Messages per second of simulated time (at most one per tick)."""
    namespace: str = "/"
    """The node's namespace; ``joint_states`` and the rigs' topics are under it (``/clock`` and ``/tf`` not)."""
    node: str | None = None
    """The node's name; default ``dynabrain_<world>``."""


# -- names and keys (rmw_zenoh's format) -------------------------------------------------------------------
def ros_name(name: str) -> str:
    """A ROS name token from a dynabrain name (letters, digits, ``_``; not starting with a digit)."""
    token = _NOT_NAME.sub("_", name) or "_"
    return f"_{token}" if token[0].isdigit() else token


def dds_type(msgtype: str) -> str:
    """``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_`` (rmw_zenoh's type name)."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    """A name inside a liveliness token: ``/`` written ``%`` (so ``/`` alone is ``%``)."""
    return name.replace("/", "%")


def topic_key(domain_id: int, topic: str, msgtype: str, type_hash: str) -> str:
    """The key expression a topic's samples go on."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type(msgtype)}/{type_hash}"


def qos_field(depth: int) -> str:
    """The QoS chunk of a token: reliable, volatile, keep-last ``depth``, no deadline, lifespan or liveliness
    lease; fields equal to rmw_zenoh's default are left empty (``::,10:,:,:,,``)."""
    return f"::,{'' if depth == RMW_ZENOH_DEFAULT_DEPTH else depth}:,:,:,,"


def node_token(domain_id: int, zid: str, node_id: int, namespace: str, node: str) -> str:
    return f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{node_id}/NN/%/{mangle(namespace)}/{node}"


def endpoint_token(domain_id: int, zid: str, node_id: int, entity_id: int, kind: str, namespace: str, node: str,
                   topic: str, msgtype: str, type_hash: str, depth: int) -> str:
    """A publisher's (``MP``) or subscription's (``MS``) token."""
    return (f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{entity_id}/{kind}/%/{mangle(namespace)}/{node}/"
            f"{mangle(topic)}/{dds_type(msgtype)}/{type_hash}/{qos_field(depth)}")


def attachment(seq: int, source_ns: int, gid: bytes) -> zenoh.ZBytes:
    """rmw_zenoh's sample attachment: sequence number, source time (ns), publisher GID (16 bytes)."""
    return zenoh.ext.z_serialize((zenoh.ext.Int64(seq), zenoh.ext.Int64(source_ns), gid))


def read_attachment(data: zenoh.ZBytes) -> tuple[int, int, bytes]:
    seq, source_ns, gid = zenoh.ext.z_deserialize(tuple[zenoh.ext.Int64, zenoh.ext.Int64, bytes], data)
    return int(seq), int(source_ns), bytes(gid)


# -- the graph's entities ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Endpoint:
    """One publisher or subscription of the node."""

    topic: str
    """Fully qualified: ``/arm/joint_commands``."""
    msgtype: str
    depth: int = 10


class _Publisher:
    def __init__(self, session: zenoh.Session, key: str, token: str):
        self.key, self.token_key = key, token
        self.gid = hashlib.blake2b(token.encode(), digest_size=16).digest()
        self._pub = session.declare_publisher(key, reliability=zenoh.Reliability.RELIABLE)
        self._token = session.liveliness().declare_token(token)
        self.seq = 0

    def put(self, payload: bytes) -> None:
        self.seq += 1
        self._pub.put(payload, attachment=attachment(self.seq, time.time_ns(), self.gid))

    def close(self) -> None:
        for ent in (self._token, self._pub):
            with contextlib.suppress(Exception):
                ent.undeclare()


# -- what the world shows ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Layout:
    """The joints and bodies published, and the bridge's view of their signals."""

    signals: Ros2Signals
    view: int | None
    bus: object

    @property
    def joints(self) -> tuple[str, ...]:
        return self.signals.joints

    @property
    def bodies(self) -> tuple[str, ...]:
        return self.signals.bodies


def _layout(service: WorldService, view: WorldView) -> _Layout:
    core = service.world.core
    signals = ros2_signals(core.name if core is not None else None, core.joints() if core is not None else (),
                           core.bodies() if core is not None else (), view.signal_slots())
    vid = service.internal_view(list(signals.names)) if signals.names else None
    return _Layout(signals, vid, view.bus().base)


@dataclass
class _Trajectory:
    """A JointTrajectory being followed: ``times_ns[k]`` (from its start) and ``targets[k]`` per joint; row 0
    is filled with the current targets when it starts."""

    rig: Rig
    joints: tuple[str, ...]
    times_ns: np.ndarray
    targets: np.ndarray
    start_ns: int | None = None


@dataclass
class Ros2Counts:
    published: int = 0
    commands: int = 0
    trajectories: int = 0
    refused: int = 0
    errors: int = 0


class _CommandError(DynabrainError):
    """A ROS 2 command with a bad field (reported as an ``input_error`` event)."""


class Ros2Bridge:
    """The ROS 2 face of one served world on its Zenoh session. `on_tick` is a `StateStream` tick hook."""

    def __init__(self, session: zenoh.Session, world: str, service: WorldService, events: EventSink,
                 options: Ros2Options, drive: Drive):
        if options.rate_hz <= 0 or not np.isfinite(options.rate_hz):
            raise DynabrainError(f"ROS 2 rate must be a positive number of Hz, got {options.rate_hz!r}")
        if options.domain_id < 0:
            raise DynabrainError(f"ROS 2 domain id must be >= 0, got {options.domain_id}")
        self.options, self._service, self._events, self._drive = options, service, events, drive
        self.codec = Codec()
        self.counts = Ros2Counts()
        self.node = options.node or f"dynabrain_{ros_name(world)}"
        self.namespace = "/" + "/".join(ros_name(t) for t in options.namespace.split("/") if t)
        self.zid = str(session.info.zid())
        self._session = session
        self._lock = threading.Lock()
        self._pending: dict[str, _Trajectory | None] = {}
        self._active: dict[str, _Trajectory] = {}
        wv = WorldView(service.world)
        self._every = max(1, round(1e9 / (options.rate_hz * service.world.dt_ns)))
        self._rigs: dict[str, Rig] = dict(service.rigs)
        with service.world.lock():
            self._layout = _layout(service, wv)
            self._target_views = {r: service.internal_view([rig.signal]) for r, rig in self._rigs.items()}
        self._entity = 0
        self._entities: list[Any] = []
        try:
            self._declare()
        except BaseException:
            self.close()
            raise

    def _declare(self) -> None:
        """The node's token first, then each publisher and subscription with its token (rmw_zenoh's order)."""
        o = self.options
        self._entities.append(self._session.liveliness().declare_token(
            node_token(o.domain_id, self.zid, 0, self.namespace, self.node)))
        self._clock = self._publisher(Endpoint("/clock", CLOCK, depth=1))
        self._tf = self._publisher(Endpoint("/tf", TF, depth=100))
        self._joints = self._publisher(Endpoint(self._topic("joint_states"), JOINT_STATE))
        for robot in self._rigs:
            self._subscribe(Endpoint(self._topic(ros_name(robot), "joint_commands"), MULTI_ARRAY),
                            lambda data, topic, r=robot: self._on_array(r, topic, data))
            self._subscribe(Endpoint(self._topic(ros_name(robot), "joint_trajectory"), TRAJECTORY),
                            lambda data, topic, r=robot: self._on_trajectory(r, topic, data))

    # -- declarations ---------------------------------------------------------------------------------------
    def _topic(self, *parts: str) -> str:
        return "/".join((self.namespace.rstrip("/"), *parts))

    def _next_id(self) -> int:
        self._entity += 1
        return self._entity

    def _token(self, kind: str, ep: Endpoint) -> str:
        o = self.options
        return endpoint_token(o.domain_id, self.zid, 0, self._next_id(), kind, self.namespace, self.node, ep.topic,
                              ep.msgtype, self.codec.hash(ep.msgtype), ep.depth)

    def _publisher(self, ep: Endpoint) -> _Publisher:
        pub = _Publisher(self._session, topic_key(self.options.domain_id, ep.topic, ep.msgtype,
                                                  self.codec.hash(ep.msgtype)), self._token("MP", ep))
        self._entities.append(pub)
        return pub

    def _subscribe(self, ep: Endpoint, handler: Callable[[bytes, str], None]) -> None:
        """Any type hash is taken (``*``): the CDR of these types is the same in every distribution."""
        key = topic_key(self.options.domain_id, ep.topic, ep.msgtype, "*")

        def on_sample(sample: zenoh.Sample) -> None:
            handler(sample.payload.to_bytes(), ep.topic)

        self._entities.append(self._session.declare_subscriber(key, on_sample))
        self._entities.append(self._session.liveliness().declare_token(self._token("MS", ep)))

    def describe(self) -> dict[str, Any]:
        """The node, its topics and counts (for ``status``)."""
        o = self.options
        return {"node": f"{self.namespace.rstrip('/')}/{self.node}", "domain_id": o.domain_id, "rmw_zenoh":
                RMW_ZENOH_VERSION, "distro": ROS_DISTRO, "every_ticks": self._every,
                "publishes": [self._clock.key, self._tf.key, self._joints.key],
                "joints": list(self._layout.joints), "bodies": list(self._layout.bodies),
                "counts": vars(self.counts).copy()}

    def close(self) -> None:
        for ent in reversed(self._entities):
            if isinstance(ent, _Publisher):
                ent.close()
                continue
            with contextlib.suppress(Exception):
                ent.undeclare()
        self._entities = []

    # -- publishing (the stepping thread, under the world lock) ---------------------------------------------
    def on_tick(self, view: WorldView) -> None:
        if self._pending or self._active:
            self._follow()
        if view.tick % self._every == 0:
            try:
                self._publish(view)
            except Exception:  # a bug here must not fail the world's tick
                _log.exception("ROS 2 publication failed")

    def _publish(self, view: WorldView) -> None:
        lay = self._layout
        if view.bus().base is not lay.bus:  # the structure changed: bodies or joints came or went
            if lay.view is not None:
                with contextlib.suppress(DynabrainError):
                    self._service.do_drop_view(_ViewRef(lay.view))  # the bridge's own view (a negative id)
            lay = self._layout = _layout(self._service, view)
        codec = self.codec
        stamp = codec.stamp(self._service.world.time_ns)
        self._clock.put(codec.encode(codec.clock(stamp)))
        if lay.view is not None:
            q, qd, effort, pos, quat = lay.signals.split(self._service.values(lay.view))
            if lay.joints:
                self._joints.put(codec.encode(codec.joint_state(stamp, lay.joints, q, qd, effort)))
            if lay.bodies:
                self._tf.put(codec.encode(codec.tf_message(stamp, lay.bodies, pos, quat)))
        self.counts.published += 1

    # -- commands (Zenoh's threads) -------------------------------------------------------------------------
    def _decode(self, data: bytes, msgtype: str, topic: str) -> Any:
        if len(data) > MAX_COMMAND_BYTES:
            raise _CommandError(f"{len(data)} bytes, more than {MAX_COMMAND_BYTES}")
        try:
            return self.codec.decode(data, msgtype)
        except Exception as exc:  # rosbags raises what its reader meets: struct, index, unicode errors
            raise _CommandError(f"not CDR of {msgtype} ({type(exc).__name__}: {exc})") from None

    def _report(self, topic: str, exc: Exception) -> None:
        self.counts.errors += 1
        self._events.emit("input_error", message=f"ROS 2 {topic}: {exc}", source=BRAIN_ID)

    def _on_array(self, robot: str, topic: str, data: bytes) -> None:
        try:
            msg = self._decode(data, MULTI_ARRAY, topic)
            rig = self._rigs[robot]
            values = np.asarray(msg.data, dtype=np.float64)
            if values.shape != (len(rig.joints),):
                raise _CommandError(f"field data has {values.size} values; robot {robot!r} has "
                                    f"{len(rig.joints)} joints ({', '.join(rig.joints)})")
            _check_finite(values, "data", [f"[{i}] ({j})" for i, j in enumerate(rig.joints)])
            with self._lock:
                self._pending[robot] = None  # a command ends a trajectory
            self._command(robot, values.tolist())
        except DynabrainError as exc:
            self._report(topic, exc)

    def _on_trajectory(self, robot: str, topic: str, data: bytes) -> None:
        try:
            msg = self._decode(data, TRAJECTORY, topic)
            trajectory = _trajectory(self._rigs[robot], msg)
        except DynabrainError as exc:
            self._report(topic, exc)
            return
        with self._lock:
            self._pending[robot] = trajectory
        self.counts.trajectories += trajectory is not None

    def _command(self, robot: str, targets: list[float] | dict[str, float]) -> bool:
        if not self._drive(robot, targets):
            self.counts.refused += 1
            return False
        self.counts.commands += 1
        return True

    # -- trajectories (the stepping thread) -----------------------------------------------------------------
    def _follow(self) -> None:
        with self._lock:
            pending, self._pending = self._pending, {}
        for robot, trajectory in pending.items():
            self._active.pop(robot, None)
            if trajectory is not None:
                current = self._service.values(self._target_views[robot])
                index = [trajectory.rig.joints.index(j) for j in trajectory.joints]
                trajectory.targets[0] = current[index]
                trajectory.start_ns = self._service.world.time_ns
                self._active[robot] = trajectory
        now = self._service.world.time_ns
        for robot, tr in list(self._active.items()):
            t = now - tr.start_ns
            done = t >= tr.times_ns[-1]
            row = tr.targets[-1] if done else [np.interp(t, tr.times_ns, column) for column in tr.targets.T]
            targets = {j: float(v) for j, v in zip(tr.joints, row, strict=True)}
            try:
                ok = self._command(robot, targets)
            except DynabrainError as exc:
                self._report(self._topic(ros_name(robot), "joint_trajectory"), exc)
                ok = False
            if done or not ok:
                del self._active[robot]


@dataclass(frozen=True)
class _ViewRef:
    view: int


def _check_finite(values: np.ndarray, name: str, labels: list[str]) -> None:
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        raise _CommandError(f"field {name}{labels[bad[0]]} is {values[bad[0]]}: targets must be finite")


def _trajectory(rig: Rig, msg: Any) -> _Trajectory | None:
    """A checked JointTrajectory for ``rig`` (None: no points, which stops the one being followed)."""
    names = list(msg.joint_names)
    if not msg.points:
        return None
    if not names:
        raise _CommandError("field joint_names is empty")
    unknown = [j for j in names if j not in rig.joints]
    if unknown:
        raise _CommandError(f"field joint_names: robot {rig.robot!r} has no joint {unknown[0]!r} "
                            f"(its joints: {', '.join(rig.joints)})")
    if len(set(names)) != len(names):
        raise _CommandError(f"field joint_names names a joint twice: {names}")
    times, rows = [0], []
    for k, point in enumerate(msg.points):
        positions = np.asarray(point.positions, dtype=np.float64)
        if positions.shape != (len(names),):
            raise _CommandError(f"field points[{k}].positions has {positions.size} values for {len(names)} "
                                f"joint_names")
        _check_finite(positions, f"points[{k}].positions", [f"[{i}] ({j})" for i, j in enumerate(names)])
        d = point.time_from_start
        t_ns = int(d.sec) * 1_000_000_000 + int(d.nanosec)
        if t_ns < times[-1]:
            raise _CommandError(f"field points[{k}].time_from_start ({t_ns / 1e9:g} s) is before the point "
                                f"before it ({times[-1] / 1e9:g} s)")
        times.append(t_ns)
        rows.append(positions)
    targets = np.vstack([np.zeros(len(names)), *rows])
    return _Trajectory(rig, tuple(names), np.asarray(times, dtype=np.float64), targets)
