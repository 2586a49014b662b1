"""The bridge's wire format, binary part: one frame layout for state streams, state replies, robot
state, robot commands, shadow comparisons and batch replies (see `PROTOCOL.md`).

A frame is a 40-byte little-endian header and ``count`` float64 values::

    offset  size  field
    0       4     magic  b"DBF1"
    4       2     kind   u16  (STATE 1, ROBOT_STATE 2, ROBOT_CMD 3, SHADOW 4, BATCH 5)
    6       2     flags  u16  (per kind)
    8       8     source u64  (the server instance, or the robot's session number)
    16      8     seq    i64  (tick for STATE; a sequence number otherwise)
    24      8     stamp  i64  (ns: simulated time for STATE; wall-clock time since the epoch otherwise)
    32      4     aux    u32  (view id for STATE; joint count for robot frames; deadline in us for ROBOT_CMD;
                              the length of the JSON description for BATCH)
    36      4     count  u32  number of float64 values that follow
    40      8*count values
    ...     aux   BATCH only: a JSON description of the values (UTF-8), after them

Decoding checks the magic, the kind, the length against ``count`` and the limits, so a malformed frame
is refused with a message saying what is wrong, never half-read.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from .protocol import ProtocolError

MAGIC = b"DBF1"
HEADER = struct.Struct("<4sHHQqqII")
HEADER_SIZE = HEADER.size
MAX_VALUES = 1 << 20
"""At most a million values (8 MiB) in one frame."""

MAX_META = 1 << 24
"""At most 16 MiB of JSON after the values of a BATCH frame."""

STATE, ROBOT_STATE, ROBOT_CMD, SHADOW, BATCH = 1, 2, 3, 4, 5
KINDS = {STATE: "state", ROBOT_STATE: "robot state", ROBOT_CMD: "robot command", SHADOW: "shadow", BATCH: "batch"}

# robot modes (ROBOT_STATE flags)
DISABLED, ENABLED, SAFE_STOP = 0, 1, 2
MODES = {DISABLED: "disabled", ENABLED: "enabled", SAFE_STOP: "safe_stop"}
# robot command operations (ROBOT_CMD flags)
OP_MOVE, OP_STOP, OP_ENABLE = 0, 1, 2
OPS = {OP_MOVE: "move", OP_STOP: "stop", OP_ENABLE: "enable"}

assert HEADER_SIZE == 40


@dataclass(frozen=True)
class Frame:
    """A decoded frame; ``values`` is a read-only float64 array over the received bytes; ``meta`` the
    JSON description that follows the values of a BATCH frame (empty for the other kinds)."""

    kind: int
    flags: int
    source: int
    seq: int
    stamp: int
    aux: int
    values: np.ndarray
    meta: bytes = b""

    def pack(self) -> bytes:
        if self.kind == BATCH:
            return batch(self.values, self.meta, source=self.source, seq=self.seq, stamp=self.stamp)
        return pack(self.kind, self.values, flags=self.flags, source=self.source, seq=self.seq, stamp=self.stamp,
                    aux=self.aux)


def pack(kind: int, values: np.ndarray | list[float] | tuple[float, ...], *, flags: int = 0, source: int = 0,
         seq: int = 0, stamp: int = 0, aux: int = 0) -> bytes:
    """Encode one frame."""
    data = np.ascontiguousarray(values, dtype="<f8").reshape(-1)
    return HEADER.pack(MAGIC, kind, flags, source, seq, stamp, aux, data.size) + data.tobytes()


def pack_header(kind: int, count: int, *, flags: int = 0, source: int = 0, seq: int = 0, stamp: int = 0,
                aux: int = 0) -> bytes:
    """The header alone (the caller appends ``count`` little-endian float64 values)."""
    return HEADER.pack(MAGIC, kind, flags, source, seq, stamp, aux, count)


def batch(values: np.ndarray, meta: bytes, *, source: int = 0, seq: int = 0, stamp: int = 0) -> bytes:
    """A BATCH frame: ``values`` (float64, flattened) then ``meta``, the JSON that describes them."""
    if len(meta) > MAX_META:
        raise ProtocolError(f"batch frame: {len(meta)} bytes of description, over the limit of {MAX_META}")
    data = np.ascontiguousarray(values, dtype="<f8").reshape(-1)
    return HEADER.pack(MAGIC, BATCH, 0, source, seq, stamp, len(meta), data.size) + data.tobytes() + meta


def unpack(payload: bytes | bytearray | memoryview, expect: int | None = None, *, finite: bool = False) -> Frame:
    """Decode a frame; raises `ProtocolError` naming what is wrong. ``expect``: the kind required;
    ``finite``: refuse NaN and infinities (robot frames)."""
    size = len(payload)
    if size < HEADER_SIZE:
        raise ProtocolError(f"frame of {size} bytes is shorter than its {HEADER_SIZE}-byte header")
    magic, kind, flags, source, seq, stamp, aux, count = HEADER.unpack_from(payload, 0)
    if magic != MAGIC:
        raise ProtocolError(f"not a dynabrain frame (magic {magic!r}, expected {MAGIC!r})")
    if kind not in KINDS:
        raise ProtocolError(f"unknown frame kind {kind}")
    if expect is not None and kind != expect:
        raise ProtocolError(f"expected a {KINDS[expect]} frame, got a {KINDS[kind]} frame")
    if count > MAX_VALUES:
        raise ProtocolError(f"frame declares {count} values, over the limit of {MAX_VALUES}")
    extra = aux if kind == BATCH else 0
    if extra > MAX_META:
        raise ProtocolError(f"batch frame declares {extra} bytes of description, over the limit of {MAX_META}")
    want = HEADER_SIZE + 8 * count + extra
    if size != want:
        raise ProtocolError(f"frame declares {count} values" + (f" and {extra} bytes of description" if extra else "")
                            + f" ({want} bytes) but has {size} bytes")
    values = np.frombuffer(payload, dtype="<f8", count=count, offset=HEADER_SIZE)
    if finite and not np.isfinite(values).all():
        raise ProtocolError(f"{KINDS[kind]} frame holds NaN or infinite values")
    meta = bytes(payload[HEADER_SIZE + 8 * count:]) if extra else b""
    return Frame(kind, flags, source, seq, stamp, aux, values, meta)


def state_header(payload: bytes, view: int, count: int, source: int | None) -> tuple[int, int] | None:
    """(seq, stamp) of ``payload`` when it is exactly a STATE frame of ``count`` values of view ``view``
    from server instance ``source`` (any, when None), else None: the checks of `unpack` plus the client's,
    in one step, for the lock-step hot path. None says only "not that": `unpack` tells what is wrong."""
    if len(payload) != HEADER_SIZE + 8 * count or count > MAX_VALUES:
        return None
    magic, kind, _flags, src, seq, stamp, aux, declared = HEADER.unpack_from(payload, 0)
    if magic != MAGIC or kind != STATE or aux != view or declared != count or (source is not None and src != source):
        return None
    return seq, stamp


def values_of(payload: bytes, count: int) -> np.ndarray:
    """The ``count`` values of a frame whose header `state_header` accepted (read-only, over the bytes)."""
    return np.frombuffer(payload, dtype="<f8", count=count, offset=HEADER_SIZE)


def robot_state(q: np.ndarray, qd: np.ndarray, *, mode: int, source: int, seq: int, stamp_ns: int) -> bytes:
    """A ROBOT_STATE frame: measured positions then velocities of ``n`` joints."""
    return pack(ROBOT_STATE, np.concatenate([q, qd]), flags=mode, source=source, seq=seq, stamp=stamp_ns,
                aux=len(q))


def split_robot_state(frame: Frame) -> tuple[np.ndarray, np.ndarray]:
    """(q, qd) of a ROBOT_STATE frame, checked against its joint count."""
    n = frame.aux
    if frame.values.size != 2 * n:
        raise ProtocolError(f"robot state frame for {n} joints carries {frame.values.size} values, expected {2 * n}")
    if frame.flags not in MODES:
        raise ProtocolError(f"robot state frame has unknown mode {frame.flags}")
    return frame.values[:n], frame.values[n:]


def robot_cmd(op: int, targets: np.ndarray | None, *, seq: int, stamp_ns: int, deadline_ns: int,
              source: int = 0) -> bytes:
    """A ROBOT_CMD frame: ``op`` (move, stop, enable), stamped with the wall-clock time the brain issued it."""
    values = np.zeros(0) if targets is None else targets
    return pack(ROBOT_CMD, values, flags=op, source=source, seq=seq, stamp=stamp_ns,
                aux=min(max(deadline_ns // 1000, 0), 0xFFFFFFFF))


def check_robot_cmd(frame: Frame, joints: int) -> None:
    """Refuse a ROBOT_CMD frame whose operation or target count is wrong."""
    if frame.flags not in OPS:
        raise ProtocolError(f"robot command has unknown operation {frame.flags}")
    want = joints if frame.flags == OP_MOVE else 0
    if frame.values.size != want:
        raise ProtocolError(f"robot {OPS[frame.flags]} command carries {frame.values.size} values, expected {want}")
    if frame.aux == 0:
        raise ProtocolError("robot command has no deadline")
