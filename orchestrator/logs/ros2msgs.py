"""ROS 2 messages of a world, written once for the two places that make them: the Zenoh bridge's ROS 2 face
(`dynabrain.bridge.ros2`, ``serve --ros2``) and the logs (``run --log FILE --ros2-schemas``, `logs.sink`).

Messages are encoded in CDR (with its 4-byte encapsulation header) and decoded by ``rosbags`` (its ROS 2
Jazzy type store, which also gives each type's RIHS01 hash and its ``ros2msg`` definition), never by hand:

- ``/clock`` (``rosgraph_msgs/msg/Clock``): the simulated time;
- ``/tf`` (``tf2_msgs/msg/TFMessage``): each body's pose in frame ``world``, child frame the body's name;
- ``joint_states`` (``sensor_msgs/msg/JointState``): every one-degree-of-freedom joint of the core whose
  ``<core>.<joint>.q`` and ``.qd`` are scalar signals: position, velocity, and the force applied (effort)
  when every such joint has a scalar ``.force``.

`Ros2Signals` says which joints and bodies a world's signals give and the signals to read, in the order
`joint_state` and `tf_message` take them. `Codec.msgdef` is the schema text MCAP's ``ros2msg`` encoding
wants (the type's definition, then each type it uses after a line of 80 ``=`` and ``MSG: pkg/Name``), as
rosbag2 writes it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

CLOCK, TF, JOINT_STATE = "rosgraph_msgs/msg/Clock", "tf2_msgs/msg/TFMessage", "sensor_msgs/msg/JointState"
ROS_DISTRO = "jazzy"


class Codec:
    """ROS 2 messages in CDR, by ``rosbags`` (its Jazzy type store): classes, encoding, type hashes and
    definitions."""

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore  # loaded only when ROS 2 messages are made

        self.store = get_typestore(Stores.ROS2_JAZZY)
        self.types = self.store.types
        self._hashes: dict[str, str] = {}

    def hash(self, msgtype: str) -> str:
        if msgtype not in self._hashes:
            self._hashes[msgtype] = self.store.hash_rihs01(msgtype)
        return self._hashes[msgtype]

    def msgdef(self, msgtype: str) -> bytes:
        """The ``ros2msg`` schema text of ``msgtype`` (with its dependencies), as rosbag2 writes it."""
        return self.store.generate_msgdef(msgtype, ros_version=2)[0].encode()

    def encode(self, msg: Any) -> bytes:
        return bytes(self.store.serialize_cdr(msg, msg.__msgtype__))

    def decode(self, data: bytes, msgtype: str) -> Any:
        return self.store.deserialize_cdr(data, msgtype)

    def stamp(self, t_ns: int) -> Any:
        return self.types["builtin_interfaces/msg/Time"](sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)

    # -- the world's messages ------------------------------------------------------------------------------
    def clock(self, stamp: Any) -> Any:
        return self.types[CLOCK](clock=stamp)

    def joint_state(self, stamp: Any, joints: Sequence[str], q: np.ndarray, qd: np.ndarray,
                    effort: np.ndarray) -> Any:
        t = self.types
        return t[JOINT_STATE](header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=""), name=list(joints),
                              position=np.array(q, dtype=np.float64), velocity=np.array(qd, dtype=np.float64),
                              effort=np.array(effort, dtype=np.float64))

    def tf_message(self, stamp: Any, bodies: Sequence[str], pos: np.ndarray, quat_wxyz: np.ndarray) -> Any:
        """Each body's pose (``pos`` (n, 3), ``quat_wxyz`` (n, 4): w first, as dynabrain keeps it) in frame
        ``world``."""
        t = self.types
        header = t["std_msgs/msg/Header"](stamp=stamp, frame_id="world")
        vec, rot = t["geometry_msgs/msg/Vector3"], t["geometry_msgs/msg/Quaternion"]
        transform, stamped = t["geometry_msgs/msg/Transform"], t["geometry_msgs/msg/TransformStamped"]
        return t[TF](transforms=[
            stamped(header=header, child_frame_id=body, transform=transform(
                translation=vec(x=p[0], y=p[1], z=p[2]), rotation=rot(x=w[1], y=w[2], z=w[3], w=w[0])))
            for body, p, w in zip(bodies, np.asarray(pos).tolist(), np.asarray(quat_wxyz).tolist(), strict=True)])


@dataclass(frozen=True)
class Ros2Signals:
    """The joints and bodies a world's signals give ROS 2 messages, and those signals in the order the
    messages take them: every joint's ``q``, every joint's ``qd``, every joint's ``force`` (when
    ``effort``), every body's ``pos``, every body's ``quat``."""

    joints: tuple[str, ...]
    bodies: tuple[str, ...]
    effort: bool
    names: tuple[str, ...]

    @property
    def sizes(self) -> tuple[int, ...]:
        """The values of each group of `names` (q, qd, force, pos, quat)."""
        n, b = len(self.joints), len(self.bodies)
        return (n, n, n if self.effort else 0, 3 * b, 4 * b)

    def split(self, values: np.ndarray) -> tuple[np.ndarray, ...]:
        """``values`` (the signals of `names`, one after the other) as (q, qd, effort, pos (b, 3), quat (b, 4))."""
        q, qd, effort, pos, quat = np.split(values, np.cumsum(self.sizes)[:-1])
        return q, qd, effort, pos.reshape(-1, 3), quat.reshape(-1, 4)


def ros2_signals(core: str | None, joints: Iterable[str], bodies: Iterable[str],
                 slots: Mapping[str, tuple[int, Any, Any]]) -> Ros2Signals:
    """The joints and bodies of core ``core`` (its ``joints()`` and ``bodies()``) that ``slots`` (signal ->
    (offset, shape, unit), `WorldView.signal_slots`) give: see the module docstring."""
    if core is None:
        return Ros2Signals((), (), False, ())

    def shape(name: str) -> Any:
        return tuple(slots[name][1]) if name in slots else None

    js = tuple(j for j in joints if shape(f"{core}.{j}.q") == () and f"{core}.{j}.qd" in slots)
    bs = tuple(b for b in bodies if shape(f"{core}.{b}.pos") == (3,) and shape(f"{core}.{b}.quat") == (4,))
    effort = bool(js) and all(shape(f"{core}.{j}.force") == () for j in js)
    names = ([f"{core}.{j}.q" for j in js] + [f"{core}.{j}.qd" for j in js]
             + ([f"{core}.{j}.force" for j in js] if effort else [])
             + [f"{core}.{b}.pos" for b in bs] + [f"{core}.{b}.quat" for b in bs])
    return Ros2Signals(js, bs, effort, tuple(names))
