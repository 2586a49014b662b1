"""What a MuJoCo model file holds for drawing beside its bodies: the geoms of no body (its ground) and
mesh vertices, read from the file again (the compiled model may have frozen objects fused into static
geometry, which the drawing shows as their bodies). A logger or a viewer reaches them through the
core's `PhysicsCore.world_geoms` and `PhysicsCore.mesh`, never through MuJoCo itself."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

_log = logging.getLogger("dynabrain.mcap")

_MJ_TYPES = {0: "plane", 2: "sphere", 3: "capsule", 4: "ellipsoid", 5: "cylinder", 6: "box", 7: "mesh"}


class ModelFileDrawing:
    """The drawing's parts of model file ``path`` (compiled again on first use; a failure only loses
    the drawing, the core compiled it already)."""

    def __init__(self, path: str | None):
        self.path = path
        self._model: Any = None
        self._tried = False

    def world_geoms(self) -> list[dict]:
        model = self._mujoco_model()
        if model is None:
            return []
        return [_mujoco_geom(model, g) for g in range(model.ngeom) if int(model.geom_bodyid[g]) == 0]

    def mesh(self, name: str) -> tuple[np.ndarray, np.ndarray] | None:
        model = self._mujoco_model()
        if model is None:
            return None
        try:
            mid = model.mesh(name).id
        except KeyError:
            _log.warning("scene: mesh %r is not in the model file; it is not drawn", name)
            return None
        v0, nv = int(model.mesh_vertadr[mid]), int(model.mesh_vertnum[mid])
        f0, nf = int(model.mesh_faceadr[mid]), int(model.mesh_facenum[mid])
        return np.array(model.mesh_vert[v0:v0 + nv]), np.array(model.mesh_face[f0:f0 + nf])

    def _mujoco_model(self) -> Any:
        if self._tried:
            return self._model
        self._tried = True
        if not self.path:
            return None
        try:
            import mujoco

            self._model = mujoco.MjModel.from_xml_path(str(self.path))
        except Exception as exc:  # the core compiled it already; a failure here only loses the drawing
            _log.warning("scene: cannot read %s for drawing: %s", self.path, exc)
        return self._model


def _mujoco_geom(model: Any, g: int) -> dict:
    """A MuJoCo geom in the core's geom description (full box edges, capsule/cylinder full lengths)."""
    kind = _MJ_TYPES.get(int(model.geom_type[g]), "unknown")
    size = [float(x) for x in model.geom_size[g]]
    sizes = {"box": [2 * x for x in size], "sphere": size[:1], "capsule": [size[0], 2 * size[1]],
             "cylinder": [size[0], 2 * size[1]], "plane": size[:2] if size[0] > 0 else []}
    geom = {"name": model.geom(g).name, "type": kind, "size": tuple(sizes.get(kind, size)),
            "rgba": tuple(float(x) for x in model.geom_rgba[g]), "pos": tuple(float(x) for x in model.geom_pos[g]),
            "quat": tuple(float(x) for x in model.geom_quat[g])}
    if kind == "mesh":
        geom["mesh"] = model.mesh(int(model.geom_dataid[g])).name
    return geom
