"""What the logger hands its sink, and what travels through the pipe to and from the child writer.

One named type per message, used on both sides (`logs.logger`, `logs.sink`); a field name replaces
a position in a tuple. They are `NamedTuple`s: a message is still a tuple (pickled as a class reference
and its fields, unpacked into a `LogSink` method's arguments as it is), so naming them costs nothing
on the hot path.

They live here, not in `logs.sink`: the child runs ``python -m dynabrain.orchestrator.logs.sink``, where
that module is ``__main__``, and a class defined there would be a different class in each process.

Parent to child: `Open` (first, once), then any of `Metadata`, `Layout`, `Event`, `ImaginedRows` and
`Rows`, in the order the logger made them, then `Finish` or `Abort`. Child to parent: `Ready` (or `Failed`) after
`Open`, `Done` after each `Rows`, `Failed` when a write fails, `Finished` after `Finish`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

if TYPE_CHECKING:
    import numpy as np

Scene = tuple[int, bytes]
"""A scene drawing and the row (of its block) whose tick it belongs to."""


# -- the logger's calls (LogSink methods of the same names and arguments) -------------------------------------
class Metadata(NamedTuple):
    """An MCAP metadata record."""

    name: str
    values: Mapping[str, str]


class Layout(NamedTuple):
    """A bus layout: ``key`` names its codec (made again from the channel ``meta``); ``cols`` are the
    bus columns of each body's pose, ``missing`` the bodies whose poses the bus lacks (sent in ``extra``);
    ``joints``: for a log with ROS 2 messages, the joints of ``/joint_states`` and their bus columns (rows
    q, qd and, when the joints have a force, effort)."""

    key: int
    meta: Mapping[str, str]
    cols: np.ndarray
    missing: list[str]
    joints: tuple[tuple[str, ...], np.ndarray] | None = None


class Event(NamedTuple):
    """One ``/events`` message: at simulated time ``time_ns``, its ``kind`` (the ``foxglove.Log`` name),
    ``level`` (`schema.event_level`) and ``text`` (the event as JSON)."""

    time_ns: int
    kind: str
    level: int
    text: str
    epoch: int


class ImaginedRows(NamedTuple):
    """A branch the brain imagined (`kernel.observers.Imagined`), for ``/imagined/<name>/<branch>/...``:
    ``values`` are its rows (ticks, size), the values after ticks ``start_tick + 1`` on, laid out as
    ``slots`` say ((signal, shape, unit), one after the other); ``bodies`` and ``cols``: each body
    whose pose the rows hold, and its 7 columns (x y z qw qx qy qz); ``scene``: a ``SceneUpdate``
    drawing those bodies in their imagined frames (empty: none)."""

    name: str
    branch: int
    start_tick: int
    epoch: int
    slots: list[tuple[str, tuple[int, ...], str]]
    values: np.ndarray
    bodies: list[str]
    cols: np.ndarray
    scene: bytes


Call = Metadata | Layout | Event | ImaginedRows
"""A writer call the logger makes (`ThreadSink.call`, `ProcessSink.call`)."""


# -- the logger's rows -------------------------------------------------------------------------------------
class Span(NamedTuple):
    """Rows ``[lo, hi)`` of a block of the logger's, to write to ``/bus`` (``discarded``: to
    ``/discarded/bus``)."""

    block: Any
    lo: int
    hi: int
    discarded: bool


class Release(NamedTuple):
    """A block whose rows are all handed over: back to its pool once everything before it is written."""

    block: Any


# -- the pipe, parent to child ----------------------------------------------------------------------------
class Open(NamedTuple):
    """Open the log (the `LogSink` arguments)."""

    path: str
    writer_args: dict[str, Any]
    dt_ns: int
    decimate: int
    bodies: list[str] | None
    descriptors: dict[str, bytes]
    ros2: bool = False


class Shared(NamedTuple):
    """A float64 array in shared memory, by the path of its file and its shape."""

    path: str
    shape: tuple[int, ...]


class RowsPart(NamedTuple):
    """Rows ``[lo, hi)`` of a block in shared memory: ticks ``first + lo`` on, of one layout (``key``),
    epoch and fate; ``extra``: the poses the bus lacks, in a second array; ``scenes``: by row from ``lo``."""

    key: int
    rows: Shared
    extra: Shared | None
    lo: int
    hi: int
    first: int
    epoch: int
    discarded: bool
    scenes: Sequence[Scene]


class Rows(NamedTuple):
    """Parts of blocks to encode and write, in order; the child answers `Done`."""

    parts: list[RowsPart]


class Finish(NamedTuple):
    """Write the summary and footer; the child answers `Finished` (or `Failed`) and ends."""


class Abort(NamedTuple):
    """Close the file as it is and end."""


# -- the pipe, child to parent ----------------------------------------------------------------------------
class Ready(NamedTuple):
    """The log is open."""


class Done(NamedTuple):
    """The child has written this many `Rows` messages (their blocks can take rows again)."""

    batches: int


class Failed(NamedTuple):
    """Opening, writing or finishing failed; the parent raises ``reason`` at its next call."""

    reason: str


class Finished(NamedTuple):
    """The file is complete: what was written and the writer's CPU time (`logs.sink.NOTHING_WRITTEN`)."""

    stats: dict[str, float]
