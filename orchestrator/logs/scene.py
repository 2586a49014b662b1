"""The scene as Foxglove draws it: one ``SceneEntity`` per body, in the body's own frame.

Each entity is ``frame_locked`` to the frame named after its body, so the ``/tf`` poses move it.
Geoms map to Foxglove primitives: box -> cube; sphere and ellipsoid -> sphere; cylinder -> cylinder;
capsule -> a cylinder and two spheres; plane -> a thin slab (20 m square when infinite); mesh -> a
triangle list. Bodies of objects that are not selected (frozen, `World.make`) are drawn translucent;
so are the bodies of a branch the brain imagined, in that branch's frames (`SceneDrawing.imagined`).

Geoms that belong to no body (a model file's ground, attached to the world) are drawn in an entity
``world`` in the frame ``world``. These, and mesh vertices, come from the core (`PhysicsCore.world_geoms`,
`PhysicsCore.mesh`); a mesh the core does not give is left out of the drawing (the rest is drawn).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.CylinderPrimitive_pb2 import CylinderPrimitive
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.TriangleListPrimitive_pb2 import TriangleListPrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.duration_pb2 import Duration
from google.protobuf.timestamp_pb2 import Timestamp

from .schema import varint

_log = logging.getLogger("dynabrain.mcap")
INFINITE_PLANE = 20.0
"""Side (m) of the slab that draws an infinite plane."""
FROZEN_ALPHA = 0.35
"""Opacity factor of bodies that are not simulated."""
IMAGINED_ALPHA = 0.4
"""Opacity factor of bodies drawn in an imagined branch's frames (`SceneDrawing.imagined`)."""


class SceneDrawing:
    """Encodes ``foxglove.SceneUpdate`` messages of a core's bodies. Each body's entity is serialized
    once per state (simulated or frozen); a message adds the timestamp and joins them."""

    def __init__(self, core: Any):
        self.core = core
        self.bodies = [b for b in core.bodies() if core.body_info(b).geoms]
        self._object = {b: _top_object(core, b) for b in self.bodies}
        self._cache: dict[tuple[str, bool], bytes] = {}
        world = core.world_geoms()
        self._world = self._make_entity("world", "world", world, "static") if world else b""

    def encode(self, t_ns: int) -> bytes:
        selected = set(self.core.selection)
        stamp = Timestamp(seconds=t_ns // 1_000_000_000, nanos=t_ns % 1_000_000_000).SerializeToString()
        stamp_field = b"\x0a" + varint(len(stamp)) + stamp
        out = bytearray()
        entities = [self._entity(b, self._object[b] not in selected) for b in self.bodies]
        for entity in [self._world, *entities] if self._world else entities:
            entity += stamp_field
            out += b"\x12" + varint(len(entity)) + entity
        return bytes(out)

    def _entity(self, body: str, frozen: bool) -> bytes:
        key = (body, frozen)
        cached = self._cache.get(key)
        if cached is None:
            cached = self._cache[key] = self._make_entity(body, body, self.core.body_info(body).geoms,
                                                          "frozen" if frozen else "simulated")
        return cached

    def imagined(self, bodies: Sequence[str], frames: Sequence[str], t_ns: int, lifetime_ns: int) -> bytes:
        """A ``SceneUpdate`` drawing ``bodies`` translucent, each in its frame of ``frames`` (an imagined
        branch's), from ``t_ns`` for ``lifetime_ns``; empty when none of them has geometry."""
        known = set(self.bodies)
        stamp = Timestamp(seconds=t_ns // 1_000_000_000, nanos=t_ns % 1_000_000_000)
        life = Duration(seconds=lifetime_ns // 1_000_000_000, nanos=lifetime_ns % 1_000_000_000)
        entities = []
        for body, frame in zip(bodies, frames, strict=True):
            if body in known:
                entity = self._entity_proto(frame, frame, self.core.body_info(body).geoms, "imagined", IMAGINED_ALPHA)
                entity.timestamp.CopyFrom(stamp)
                entity.lifetime.CopyFrom(life)
                entities.append(entity)
        return SceneUpdate(entities=entities).SerializeToString() if entities else b""

    def _make_entity(self, name: str, frame: str, geoms: Sequence[dict], state: str) -> bytes:
        return self._entity_proto(name, frame, geoms, state, FROZEN_ALPHA if state == "frozen" else 1.0
                                  ).SerializeToString()

    def _entity_proto(self, name: str, frame: str, geoms: Sequence[dict], state: str, alpha: float) -> SceneEntity:
        entity = SceneEntity(frame_id=frame, id=name, frame_locked=True,
                             metadata=[KeyValuePair(key="state", value=state)])
        for geom in geoms:
            self._add_geom(entity, geom, alpha)
        return entity

    def _add_geom(self, entity: SceneEntity, geom: dict, alpha: float) -> None:
        kind = geom["type"]
        r, g, b, a = geom.get("rgba", (0.5, 0.5, 0.5, 1.0))
        color = Color(r=r, g=g, b=b, a=a * alpha)
        pos, quat = tuple(geom.get("pos", (0.0, 0.0, 0.0))), tuple(geom.get("quat", (1.0, 0.0, 0.0, 0.0)))
        size = tuple(geom.get("size", ()))
        if kind == "mesh":
            mesh = self.core.mesh(geom.get("mesh", ""))
            if mesh is not None:
                verts, faces = mesh
                entity.triangles.append(TriangleListPrimitive(
                    pose=_pose(pos, quat), color=color, points=[Point3(x=x, y=y, z=z) for x, y, z in verts.tolist()],
                    indices=faces.reshape(-1).tolist()))
        elif kind in _DRAW:
            _DRAW[kind](entity, size, pos, quat, color)
        else:
            _log.info("scene: geom %r of type %s is not drawn", geom.get("name"), kind)


def _box(entity: SceneEntity, size: tuple, pos: tuple, quat: tuple, color: Color) -> None:
    entity.cubes.append(CubePrimitive(pose=_pose(pos, quat), size=_vec(size), color=color))


def _sphere(entity: SceneEntity, size: tuple, pos: tuple, quat: tuple, color: Color) -> None:
    diameters = [2 * size[0]] * 3 if len(size) == 1 else [2 * s for s in size[:3]]  # sphere, ellipsoid
    entity.spheres.append(SpherePrimitive(pose=_pose(pos, quat), size=_vec(diameters), color=color))


def _cylinder(entity: SceneEntity, size: tuple, pos: tuple, quat: tuple, color: Color) -> None:
    radius, length = size[0], size[1]
    entity.cylinders.append(CylinderPrimitive(pose=_pose(pos, quat), size=_vec((2 * radius, 2 * radius, length)),
                                              bottom_scale=1.0, top_scale=1.0, color=color))


def _capsule(entity: SceneEntity, size: tuple, pos: tuple, quat: tuple, color: Color) -> None:
    _cylinder(entity, size, pos, quat, color)
    radius, length = size[0], size[1]
    for sign in (-1.0, 1.0):
        end = np.add(pos, _rotate(quat, (0.0, 0.0, sign * length / 2)))
        entity.spheres.append(SpherePrimitive(pose=_pose(end, quat), size=_vec([2 * radius] * 3), color=color))


def _plane(entity: SceneEntity, size: tuple, pos: tuple, quat: tuple, color: Color) -> None:
    sx, sy = (2 * size[0], 2 * size[1]) if len(size) >= 2 and size[0] > 0 else (INFINITE_PLANE,) * 2
    below = np.add(pos, _rotate(quat, (0.0, 0.0, -0.001)))  # a 2 mm slab whose top face is the plane
    entity.cubes.append(CubePrimitive(pose=_pose(below, quat), size=_vec((sx, sy, 0.002)), color=color))


_DRAW = {"box": _box, "sphere": _sphere, "ellipsoid": _sphere, "cylinder": _cylinder, "capsule": _capsule,
         "plane": _plane}


def _top_object(core: Any, body: str) -> str:
    seen = set()
    while True:
        parent = core.body_info(body).parent
        if parent is None or parent in seen:
            return body
        seen.add(body)
        body = parent


def _pose(pos: Sequence[float], quat_wxyz: Sequence[float]) -> Pose:
    w, x, y, z = (float(q) for q in quat_wxyz)
    return Pose(position=_vec(pos), orientation=Quaternion(x=x, y=y, z=z, w=w))


def _vec(v: Sequence[float]) -> Vector3:
    return Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _rotate(quat_wxyz: Sequence[float], v: Sequence[float]) -> np.ndarray:
    """``v`` rotated by the unit quaternion ``quat`` (w, x, y, z)."""
    w, x, y, z = quat_wxyz
    norm = math.sqrt(w * w + x * x + y * y + z * z) or 1.0
    u = np.array([x, y, z]) / norm
    w /= norm
    v = np.asarray(v, dtype=float)
    return v + 2 * w * np.cross(u, v) + 2 * np.cross(u, np.cross(u, v))
