"""A log shown in Rerun (``dynabrain view LOG``): the run's scene, its signals, events and imagined futures.

`record_log` reads a log once and writes a Rerun recording (``.rrd``) of it, on one timeline ``sim_time``
(simulated seconds):

- ``world/<body>``: each body of the run's ``/scene`` (``foxglove.SceneUpdate``) as Rerun primitives in the
  body's frame (cubes -> ``Boxes3D``, spheres and ellipsoids -> ``Ellipsoids3D``, cylinders (and a capsule's
  middle) -> ``Cylinders3D``, triangle lists -> ``Mesh3D``), moved by the body's ``/tf`` pose
  (``Transform3D``) at every tick of the run (what rollbacks discarded is left out, `LogIndex.final`). A
  robot's links are bodies like any other. Geoms that belong to no body are drawn in ``world/world``.
- ``signals/<module>/<port>``: each bus signal of at most `MAX_COMPONENTS` components as a time series
  (``Scalars``), one series per component.
- ``events`` and ``expectations/<label>``: the events as text at their time (``TextLog``), a failed
  expectation at level WARN.
- ``imagined/<name>/<branch>/...``: each imagined future (``/imagined/<name>/<branch>/{scene,tf,bus}``) as
  entities of its own, drawn beside what happened (translucent, as the log draws them) from the tick it
  starts at to its last, then cleared.

`rerun_live.RerunLive` streams a running world the same way (``serve --view``). `serve_rrd` shows a recording
in Rerun's web viewer: the ``rerun`` program that rerun-sdk installs, serving
the viewer and the recording on loopback only (``--bind 127.0.0.1``).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..kernel.errors import DynabrainError
from ..kernel.extras import hint
from .read import LogIndex, iter_bus, read_index
from .scan import Message, scan
from .scene import INFINITE_PLANE
from .schema import IMAGINED, TOPIC_BUS, TOPIC_SCENE, TOPIC_TF, BusCodec

TIMELINE = "sim_time"
MAX_COMPONENTS = 16
"""Signals with more components than this (images, long state vectors) are not drawn as time series."""
WORLD = "world"


def require_rerun() -> Any:
    """The ``rerun`` module, or an error naming the package to install."""
    try:
        import rerun
    except ModuleNotFoundError as exc:
        raise hint(exc) or DynabrainError(f"the Rerun viewer cannot be imported: {exc}") from None
    return rerun


@dataclass
class _Poses:
    """A frame's poses over time, gathered before they are sent as columns."""

    times_s: list[float] = field(default_factory=list)
    translations: list[tuple[float, float, float]] = field(default_factory=list)
    quaternions_xyzw: list[tuple[float, float, float, float]] = field(default_factory=list)


@dataclass
class ViewReport:
    """What a recording holds: counted for the CLI's line and for the tests."""

    bodies: int = 0
    poses: int = 0
    signals: int = 0
    events: int = 0
    imagined: list[str] = field(default_factory=list)


def record_log(path: str | os.PathLike[str], out: str | os.PathLike[str]) -> ViewReport:
    """Write the Rerun recording of log ``path`` to ``out`` (see the module docstring)."""
    rr = require_rerun()
    index = read_index(path)
    dt_s = (index.info.dt_ns if index.info else 1) / 1e9
    name = index.info.scenario_name if index.info and index.info.scenario_name else os.path.basename(index.path)
    rec = rr.RecordingStream("dynabrain")
    rec.send_recording_name(name)
    rec.save(os.fspath(out), default_blueprint=blueprint())
    report = ViewReport()
    rec.log(WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log("imagined", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    poses = _read_messages(rr, rec, index, dt_s, report)
    for frame, got in poses.items():
        rec.send_columns(frame, indexes=[rr.TimeColumn(TIMELINE, duration=np.asarray(got.times_s))],
                         columns=rr.Transform3D.columns(translation=np.asarray(got.translations),
                                                        quaternion=np.asarray(got.quaternions_xyzw)))
        report.poses += len(got.times_s)
    _signals(rr, rec, index, dt_s, report)
    _events(rr, rec, index, report)
    rec.flush()
    rec.disconnect()
    return report


def blueprint() -> Any:
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="scene", origin="/", contents=[f"/{WORLD}/**", f"{IMAGINED}/**"]),
            rrb.Vertical(rrb.TimeSeriesView(name="signals", origin="/signals"),
                         rrb.TextLogView(name="events", origin="/", contents=["/events/**", "/expectations/**"])),
            column_shares=[3, 2]),
        collapse_panels=True)


def _read_messages(rr: Any, rec: Any, index: LogIndex, dt_s: float, report: ViewReport) -> dict[str, _Poses]:
    """The scenes (logged as they come) and the poses (gathered, per entity path) of the run and of each
    imagined future; the run's only where they are the run (not discarded by a rollback)."""
    from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    final_tf = index.final(TOPIC_TF)
    poses: dict[str, _Poses] = {}
    scenes: list[tuple[float, str, Any]] = []
    imagined_ends: dict[str, float] = {}
    for pos, msg in enumerate(_messages(index), start=1):
        topic = index.channels[msg.channel_id].topic
        prefix = _imagined_prefix(topic)
        t_s = msg.publish_time / 1e9 if index.info else msg.log_time / 1e9
        if topic == TOPIC_SCENE or (prefix and topic == prefix + TOPIC_SCENE):
            scenes.append((t_s, prefix, SceneUpdate.FromString(msg.data)))
        elif (topic == TOPIC_TF and pos in final_tf) or (prefix and topic == prefix + TOPIC_TF):
            for tf in FrameTransforms.FromString(msg.data).transforms:
                got = poses.setdefault(entity_path(tf.child_frame_id, prefix), _Poses())
                got.times_s.append(t_s)
                got.translations.append((tf.translation.x, tf.translation.y, tf.translation.z))
                got.quaternions_xyzw.append((tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w))
            if prefix:
                imagined_ends[prefix] = max(imagined_ends.get(prefix, 0.0), t_s)
        elif prefix and topic == prefix + TOPIC_BUS:
            imagined_ends[prefix] = max(imagined_ends.get(prefix, 0.0), t_s)
    plane_m = _plane_side(poses)
    for t_s, prefix, update in scenes:
        rec.set_time(TIMELINE, duration=t_s)
        for entity in update.entities:
            report.bodies += draw_entity(rr, rec, entity_path(entity.id, prefix), entity, plane_m)
    for prefix, end_s in imagined_ends.items():  # a future is shown from its start to its last tick
        rec.set_time(TIMELINE, duration=end_s + dt_s)
        rec.log(prefix.strip("/"), rr.Clear(recursive=True))
        report.imagined.append(prefix.strip("/"))
    return poses


def _plane_side(poses: dict[str, _Poses]) -> float:
    """The side (m) of the square that draws an infinite plane here: twice the bodies' first positions'
    reach from the origin, plus a metre, at most `scene.INFINITE_PLANE` (which the live view draws; in
    Rerun, whose camera frames everything, it would shrink the bodies to specks)."""
    first = [got.translations[0] for got in poses.values() if got.translations]
    reach = float(np.abs(np.asarray(first)[:, :2]).max()) if first else 1.0
    return min(2 * reach + 1.0, INFINITE_PLANE)


def _messages(index: LogIndex) -> Iterator[Message]:
    for rec in scan(index.path):
        if isinstance(rec, Message) and rec.channel_id in index.channels:
            yield rec


def _imagined_prefix(topic: str) -> str:
    """``/imagined/push/0/tf`` -> ``/imagined/push/0``; '' for the run's topics."""
    if not topic.startswith(IMAGINED + "/"):
        return ""
    head, _, _last = topic.rpartition("/")
    return head if head.count("/") == 3 else ""


def entity_path(frame: str, prefix: str) -> str:
    """The entity path of a frame: ``world/<body>``, or for an imagined frame (``imagined/push/0/cart``) that
    frame itself."""
    import rerun as rr

    if prefix and frame.startswith(prefix.strip("/") + "/"):
        head, body = frame[:len(prefix) - 1], frame[len(prefix):]
        return head + "/" + rr.escape_entity_path_part(body)
    return f"{WORLD}/{rr.escape_entity_path_part(frame)}"


def draw_entity(rr: Any, rec: Any, path: str, entity: Any, plane_m: float) -> int:
    """One ``foxglove.SceneEntity``'s primitives under ``path`` (in its frame), an infinite plane's slab
    ``plane_m`` square; 1 if it drew anything."""
    drawn = 0
    if entity.cubes:
        rec.log(path + "/boxes", rr.Boxes3D(
            centers=[_xyz(c.pose.position) for c in entity.cubes],
            sizes=[_slab(_xyz(c.size), plane_m) for c in entity.cubes],
            quaternions=[_xyzw(c.pose.orientation) for c in entity.cubes],
            colors=[_rgba(c.color) for c in entity.cubes], fill_mode="solid"))
        drawn = 1
    if entity.spheres:
        rec.log(path + "/spheres", rr.Ellipsoids3D(
            centers=[_xyz(s.pose.position) for s in entity.spheres],
            half_sizes=[np.multiply(_xyz(s.size), 0.5) for s in entity.spheres],
            quaternions=[_xyzw(s.pose.orientation) for s in entity.spheres],
            colors=[_rgba(s.color) for s in entity.spheres], fill_mode="solid"))
        drawn = 1
    if entity.cylinders:
        rec.log(path + "/cylinders", rr.Cylinders3D(
            centers=[_xyz(c.pose.position) for c in entity.cylinders],
            radii=[c.size.x / 2 for c in entity.cylinders], lengths=[c.size.z for c in entity.cylinders],
            quaternions=[_xyzw(c.pose.orientation) for c in entity.cylinders],
            colors=[_rgba(c.color) for c in entity.cylinders], fill_mode="solid"))
        drawn = 1
    for k, tri in enumerate(entity.triangles):
        rec.log(f"{path}/mesh{k}", rr.Transform3D(translation=_xyz(tri.pose.position),
                                                   quaternion=_xyzw(tri.pose.orientation)))
        points = np.array([_xyz(p) for p in tri.points], dtype=np.float32).reshape(-1, 3)
        rec.log(f"{path}/mesh{k}", rr.Mesh3D(vertex_positions=points,
                                             triangle_indices=np.asarray(tri.indices, dtype=np.uint32).reshape(-1, 3),
                                             albedo_factor=_rgba(tri.color)))
        drawn = 1
    return drawn


def _slab(size: tuple[float, float, float], plane_m: float) -> tuple[float, float, float]:
    infinite = size[0] == size[1] == INFINITE_PLANE
    return (plane_m, plane_m, size[2]) if infinite else size


def _xyz(v: Any) -> tuple[float, float, float]:
    return (v.x, v.y, v.z)


def _xyzw(q: Any) -> tuple[float, float, float, float]:
    return (q.x, q.y, q.z, q.w) if (q.x, q.y, q.z, q.w) != (0.0, 0.0, 0.0, 0.0) else (0.0, 0.0, 0.0, 1.0)


def _rgba(c: Any) -> tuple[int, int, int, int]:
    return tuple(round(255 * min(max(x, 0.0), 1.0)) for x in (c.r, c.g, c.b, c.a))  # type: ignore[return-value]


def _signals(rr: Any, rec: Any, index: LogIndex, dt_s: float, report: ViewReport) -> None:
    """Each small bus signal of the run, and of each imagined future, as time series."""
    final = index.final(TOPIC_BUS)
    series: dict[str, tuple[list[float], list[np.ndarray]]] = {}
    for codec, _epoch, tick, row, pos, _topic in iter_bus(index.path, index):
        if pos not in final:
            continue
        _add_row(series, "signals", codec, tick * dt_s, row)
    futures = {cid: (_imagined_prefix(ch.topic).strip("/"), BusCodec.from_metadata(ch.metadata))
               for cid, ch in index.channels.items()
               if _imagined_prefix(ch.topic) and ch.topic.endswith(TOPIC_BUS) and "layout" in ch.metadata}
    if futures:
        for msg in _messages(index):
            future = futures.get(msg.channel_id)
            if future is not None:
                rows, ticks, _epochs = future[1].decode(np.frombuffer(msg.data, dtype=np.uint8))
                _add_row(series, future[0] + "/signals", future[1], int(ticks[0]) * dt_s, rows[0])
    for path, (times, values) in series.items():
        data = np.asarray(values, dtype=np.float64)
        rec.send_columns(path, indexes=[rr.TimeColumn(TIMELINE, duration=np.asarray(times))],
                         columns=rr.Scalars.columns(scalars=data).partition([data.shape[1]] * len(data))
                         if data.shape[1] > 1 else rr.Scalars.columns(scalars=data[:, 0]))
        report.signals += 1


def signal_path(root: str, name: str) -> str:
    """``signals`` and ``core.cart.pos`` -> ``signals/core/cart/pos``."""
    return root + "/" + "/".join(_escape(p) for p in name.split("."))


def _add_row(series: dict, root: str, codec: BusCodec, t_s: float, row: np.ndarray) -> None:
    for slot in codec.slots:
        if 0 < slot.size <= MAX_COMPONENTS:
            path = signal_path(root, slot.name)
            times, values = series.setdefault(path, ([], []))
            times.append(t_s)
            values.append(row[slot.offset:slot.offset + slot.size])


def _escape(part: str) -> str:
    import rerun as rr

    return rr.escape_entity_path_part(part)


def _events(rr: Any, rec: Any, index: LogIndex, report: ViewReport) -> None:
    """The events at their time; expectation results under ``expectations/<label>`` as well."""
    from .replay import describe

    for ev in index.events:
        kind = str(ev.get("kind", "?"))
        if kind == "layout":
            continue
        rec.set_time(TIMELINE, duration=float(ev.get("time", 0.0)))
        detail = ev.get("detail", {}) if isinstance(ev.get("detail"), dict) else {}
        failed = (kind == "expect" and not detail.get("passed", True)) or kind in ("error", "rollback")
        text = f"{kind} {describe(ev)}"
        rec.log("events", rr.TextLog(text, level="WARN" if failed else "INFO"))
        if kind == "expect":
            rec.log("expectations/" + _escape(str(detail.get("name", "?"))), rr.TextLog(text, level="WARN" if failed
                                                                                         else "INFO"))
        report.events += 1


def serve_rrd(rrd: str | os.PathLike[str] | None, *, web_port: int = 9090, grpc_port: int = 9876
              ) -> subprocess.Popen:
    """Rerun's web viewer for ``rrd`` (None: for what an SDK sends to ``grpc_port``, `rerun_live`), served on
    loopback by the ``rerun`` program (a child process; the caller ends it: no ``preexec_fn`` ties it to this
    process, as that can deadlock a process with threads, the bridge's). Open ``viewer_url(web_port,
    grpc_port)`` in a browser."""
    require_rerun()
    files = [os.fspath(rrd)] if rrd is not None else []
    return subprocess.Popen([rerun_program(), "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port",
                             str(web_port), "--port", str(grpc_port), *files],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                            start_new_session=True)  # a Ctrl-C is ours: the stream is flushed before it ends


def rerun_program() -> str:
    """The ``rerun`` program itself (rerun-sdk's ``rerun_cli`` package holds it; its ``rerun`` script on PATH
    starts it as a child that would outlive the script when that is killed)."""
    try:
        import rerun_cli

        exe = os.path.join(os.path.dirname(rerun_cli.__file__), "rerun")
        if os.access(exe, os.X_OK):
            return exe
    except ImportError:
        pass
    exe = shutil.which("rerun", path=os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", ""))
    if exe is None:
        raise DynabrainError("the rerun program (installed with rerun-sdk) is not found")
    return exe


def viewer_url(web_port: int, grpc_port: int) -> str:
    """The web viewer's address, connected to the recording's gRPC server."""
    return f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc_port}%2Fproxy"
