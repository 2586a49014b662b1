"""A compiled model of the MuJoCo core (`CompiledScene`: the model and data of one set of edits, with where
each port's values lie in them), the views modules read it through (`MujocoView`), the ports of a set of
bodies (`SceneView`) and the sharing of one compiled model among forks (`ModelShare`). `mujoco.core`
compiles them and steps them; see its docstring for the choices behind them.
"""

from __future__ import annotations

import copy
import threading
import weakref
from dataclasses import dataclass

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.core import BodySpec, Edits
from dynabrain.orchestrator.kernel.module import Port

from . import animate
from . import scene as ms
from .spec_source import VEL_PREFIX

_S = mujoco.mjtState
STATE = int(_S.mjSTATE_INTEGRATION) & ~int(_S.mjSTATE_QFRC_APPLIED) & ~int(_S.mjSTATE_XFRC_APPLIED)
"""MuJoCo's integration state without the applied forces: the core rewrites ``qfrc_applied`` (joint
forces) and ``xfrc_applied`` (the free bodies' wrenches) from its inputs before every step, so they
carry no state (and for free bodies they were 40 % of it)."""
SPARE_DATA = 4
"""MuJoCo data kept per shared model from closed forks, for the next forks (`ModelShare`)."""
_SHARING = threading.Lock()  # guards every `ModelShare` (forks step, and close, in threads)


def _plain(array: np.ndarray) -> bool:
    """A 1-D, contiguous float64 array (one a memoryview copies with memcpy)."""
    return array.ndim == 1 and array.dtype == np.float64 and array.flags.c_contiguous


def _empty(index: slice | np.ndarray) -> bool:
    return index.stop <= index.start if isinstance(index, slice) else not len(index)


def _positions(index: slice | np.ndarray) -> np.ndarray:
    """The flat positions an index (a slice or an index array) names, as an index array."""
    return np.arange(index.start, index.stop) if isinstance(index, slice) else index


def _move(dst: np.ndarray, di, src: np.ndarray, si) -> tuple:
    """One copy of `MujocoCore.step` as ``(target, index, source, gather)``: ``target[index] = source``,
    or ``target[index] = source[gather]`` for an index array. A slice of the source is taken once, here
    (a view; about 0.1 us less a copy), and a copy from slice to slice of plain arrays goes through
    memoryviews (a memcpy)."""
    if not isinstance(si, slice):
        return (dst, di, src, si)
    if isinstance(di, slice) and _plain(dst) and _plain(src):
        return (memoryview(dst), di, memoryview(src)[si], None)
    return (dst, di, src[si], None)


@dataclass(frozen=True, eq=False)
class MujocoView:
    """Read access to the MuJoCo model and data the core simulates now (`MujocoCore.mj`), for modules
    that need what the bus does not carry (native sensors by site, contacts, geoms).

    A structural edit (`make`, `make_joint`, `no_collision`) or a restore across one switches the core
    to another compiled model, where ids differ; each compiled model has its own view, so a module
    keeps the view it resolved its ids against and compares it with ``core.mj is not seen`` (one
    identity check) to know when to resolve them again. Read only: what a module writes into
    ``model`` or ``data`` is not part of any state and a rollback does not undo it (and the model is
    shared with the core's forks: a write would reach them too).
    """

    model: mujoco.MjModel
    data: mujoco.MjData
    edits: Edits
    """The structure this model was compiled for."""


class ModelShare:
    """A compiled model shared by compiled scenes: a core's and its forks' (`CompiledScene.clone`),
    until one writes it (`CompiledScene.own_model`); and the MuJoCo data of the closed ones, kept for
    the next forks (`CompiledScene.release`): a new MjData costs about 0.35 ms in MuJoCo's Python
    bindings whatever the model, filling a kept one with `mujoco.mj_copyData` a few microseconds."""

    def __init__(self) -> None:
        self.scenes: weakref.WeakSet[CompiledScene] = weakref.WeakSet()
        """The scenes whose ``model`` is the shared one."""
        self.spare: list[mujoco.MjData] = []
        """Data of this model's shape no scene uses any more (at most `SPARE_DATA`)."""


@dataclass(frozen=True, eq=False)
class SceneView:
    """The bodies of one scene key (`Edits.scene_key`: bodies added and removed at run time) as the core
    shows them: the port layout, the rows of the bodies, the ports, and the specs of its primitives."""

    layout: ms.Layout
    rows: dict[str, int]
    ports_in: tuple[Port, ...]
    ports_out: tuple[Port, ...]
    out_names: frozenset[str]
    """The outputs' names: how `MujocoCore.bind` knows the layout of a binding."""
    specs: dict[str, BodySpec]
    """Body -> its spec, for the scene's primitives and the bodies added at run time."""


class CompiledScene:
    """One compiled structure of the core: the MuJoCo model and data for one `Edits` value, and
    where each value of the core's fixed port layout (`mujoco.scene.Layout`) comes from in them.

    Index attributes are flat positions into C-ordered arrays: ``*_rows`` into the core's port
    blocks (``body_pos`` (n, 3) as 3n values ...), ``*_src`` and ``*_adr`` into MuJoCo's arrays; each
    is a slice where the positions are contiguous (a cheaper copy), else an index array. They depend
    on the model only, and a `clone` shares them.

    The model is written only by the core's run-time parameters (`MujocoCore._apply_params`); a clone
    (a fork's) shares it until one of them writes it, and that one copies it first (`own_model`).
    A closed core's scenes give their data back for the next clone (`release`) and keep none.
    """

    def __init__(self, layout: ms.Layout, edits: Edits, model: mujoco.MjModel, movers: tuple,
                 geom_body: dict[str, str], data: mujoco.MjData | None = None):
        self.edits = edits  # the structure compiled here (`Edits.structural`: no materials)
        self.model = model
        self.movers = movers  # the bodies that move (not fused, not static), in model order
        self.share: ModelShare | None = None
        """Who else has this ``model`` (a fork's scene, or the one this was forked from), or None while it
        is this scene's own (`clone`, `own_model`)."""
        self.applied: tuple | None = None
        """(parameter dict, period) the model's run-time parameters were last set from."""
        self.state_size = mujoco.mj_stateSize(model, STATE)  # values in a saved integration state
        self.body_id = {model.body(i).name: i for i in range(1, model.nbody)}  # body name -> MuJoCo id
        # joint name -> where its values lie in qpos and qvel
        self.joint_slices = {model.joint(j).name: ms.joint_slice(model, j) for j in range(model.njnt)}
        # the equalities of the joints made at run time (those between absent bodies are not in the model)
        gone = {b.name for f in edits.frozen if f.object in edits.absent for b in f.bodies}
        self.weld_ids = np.array([model.equality(e).id for w in edits.welds if w.a not in gone
                                  for e in ms.made_equalities(w)], dtype=int)
        owners: dict[str, list[int]] = {}  # body -> its geoms (a primitive's geom is named as its body)
        for g in range(model.ngeom):
            name = model.geom(g).name
            owners.setdefault(geom_body.get(name, name), []).append(g)
        self.body_geoms = {b: np.array(g, dtype=int) for b, g in owners.items()}
        self.applied_materials: tuple | None = None  # the materials the model's geoms were last set for
        self.mass0 = model.body_mass.copy()  # the compiled masses and inertias: a body's own mass scales them
        self.inertia0 = model.body_inertia.copy()
        self.masses_set = False  # whether the model's masses differ from those
        self._map_bodies(layout, edits)
        self._map_joints(layout, edits)
        self._map_actuators_sensors(layout)
        # the robots a selection left out, animated (`mujoco.animate`); None when there are none
        robots = [e for e in edits.frozen if getattr(e, "animated", False) and e.object not in edits.absent]
        self.anim = animate.plan(layout.motor_joints, self.joint_slices, robots)
        self.driven = animate.driven_joints(model)  # joints actuators drive: an object with one is a robot
        self._map_free(layout)
        self._attach(data if data is not None else mujoco.MjData(model))

    def _attach(self, d: mujoco.MjData) -> None:
        """Take ``d`` as this scene's data, with the views into it the core reads and writes."""
        self.data = d
        self.view = MujocoView(self.model, d, self.edits)  # what `MujocoCore.mj` hands out while this is current
        self.xpos_flat, self.xquat_flat = d.xpos.reshape(-1), d.xquat.reshape(-1)  # body poses, flat
        self.qpos, self.qvel, self.sensordata = d.qpos, d.qvel, d.sensordata
        # where the inputs go: joint forces, motor controls, the free bodies' wrenches (flat)
        self.ctrl, self.qfrc_applied, self.xfrc_flat = d.ctrl, d.qfrc_applied, d.xfrc_applied.reshape(-1)
        w = mujoco.mjtWarning
        # MuJoCo's counters of bad numbers (NaN, inf, |x| > 1e10): (what, counter), the worst first
        self.warnings = tuple((what, d.warning[int(k)]) for what, k in (
            ("acceleration", w.mjWARN_BADQACC), ("velocity", w.mjWARN_BADQVEL), ("position", w.mjWARN_BADQPOS)))
        self.bad_qacc, self.bad_qvel, self.bad_qpos = (x[1] for x in self.warnings)
        self.warning_counts = [x[1].number for x in self.warnings]  # each counter as of the last check
        self.warnings_seen = sum(self.warning_counts)  # their sum (a step compares the sum)

    def clone(self) -> CompiledScene:
        """A copy for a fork: data of its own (a copy of this data: `mujoco.mj_copyData`, into data a
        closed fork left when there is some), the index maps and the model shared; the model stays
        shared until either scene writes it (`own_model`)."""
        twin = copy.copy(self)
        with _SHARING:
            share = self.share
            if share is None:
                share = self.share = ModelShare()
                share.scenes.add(self)
            share.scenes.add(twin)
            twin.share = share
            data = share.spare.pop() if share.spare else None
        if data is None:
            data = mujoco.MjData(self.model)
        mujoco.mj_copyData(data, self.model, self.data)
        twin._attach(data)
        return twin

    def own_model(self) -> bool:
        """Make ``model`` this scene's own before it is written: a copy of it when another scene
        (a fork's, or the one it was forked from) still shares it. Whether it copied."""
        if self.share is None:
            return False
        with _SHARING:  # the copy too: the last sharer left may not write while it is being copied
            share, self.share = self.share, None
            share.scenes.discard(self)
            if not share.scenes:
                return False
            self.model = copy.deepcopy(self.model)
        self.view = MujocoView(self.model, self.data, self.edits)
        return True

    def release(self) -> None:
        """Let go of model and data (the core closes): a shared model's other scenes need not copy it
        on this one's account, and they take its data for their next fork. The scene keeps neither:
        a closed core's `MujocoCore.mj` is None."""
        with _SHARING:
            share, self.share = self.share, None
            if share is not None and self.data is not None:
                share.scenes.discard(self)
                if share.scenes and len(share.spare) < SPARE_DATA:
                    share.spare.append(self.data)
        self.data = self.view = None

    def _map_bodies(self, layout: ms.Layout, edits: Edits) -> None:
        row = {b: r for r, b in enumerate(layout.bodies)}
        present = [b for b in layout.bodies if b in self.body_id]
        pairs = [(row[b], self.body_id[b]) for b in present]
        # every body present in the model: its rows in body_pos / body_quat, its values in xpos / xquat
        self.pos_rows, self.pos_src, self.quat_rows, self.quat_src = ms.pose_index(pairs)
        # the same for the moving bodies only (what a step rewrites)
        (self.moving_pos_rows, self.moving_pos_src, self.moving_quat_rows,
         self.moving_quat_src) = ms.pose_index([(row[b], self.body_id[b]) for b in self.movers])
        moving = set(self.movers)
        # rows in body_linvel / body_angvel of the bodies that do not move (their velocity is 0)
        self.still_rows = ms.flat_index([r for r, b in enumerate(layout.bodies) if b not in moving], 3)
        world = {b.name: b.in_world for entry in edits.frozen for b in entry.bodies}
        fused = [b for b in layout.bodies if b not in self.body_id]  # frozen, fused into the world
        # rows of the fused bodies in body_pos / body_quat, and the poses they stay at
        self.fused_pos_rows, self.fused_quat_rows = (ms.flat_index([row[b] for b in fused], k) for k in (3, 4))
        self.fused_pose = {b: world[b] for b in fused}  # body -> world pose (x, y, z, qw, qx, qy, qz)
        self.fused_pos = np.array([world[b][:3] for b in fused]).reshape(-1)
        self.fused_quat = np.array([world[b][3:] for b in fused]).reshape(-1)
        n = len(self.movers)
        start = int(self.model.sensor_adr[self.model.sensor(f"{VEL_PREFIX}lin_{self.movers[0]}").id]) if n else 0
        # the moving bodies' velocities in sensordata (the core's frame-velocity sensors, in mover order)
        self.linvel_src, self.angvel_src = slice(start, start + 3 * n), slice(start + 3 * n, start + 6 * n)

    def _map_joints(self, layout: ms.Layout, edits: Edits) -> None:
        frozen = {j: v for entry in edits.frozen for j, v in entry.joints}
        kept = [(r, self.joint_slices[j]) for r, j in enumerate(layout.qjoints) if j in self.joint_slices]
        self.n_joints = len(kept)  # hinge and slide joints of the layout present in the model
        self.joint_rows = ms.flat_index([r for r, _ in kept], 1)  # their rows in joint_q / joint_qd / joint_force
        # ... and their values in qpos, and in qvel and qfrc_applied
        self.joint_qpos_adr, self.joint_dof_adr = (ms.flat_index([js.qpos_adr for _, js in kept], 1),
                                                    ms.flat_index([js.dof_adr for _, js in kept], 1))
        gone = [r for r, j in enumerate(layout.qjoints) if j not in self.joint_slices]
        self.frozen_joint_rows = ms.flat_index(gone, 1)  # rows of the joints of frozen objects
        self.frozen_q = np.array([frozen[layout.qjoints[r]][0] for r in gone])  # ... and their values

    def _map_actuators_sensors(self, layout: ms.Layout) -> None:
        m = self.model
        index = {a: i for i, a in enumerate(layout.actuators)}
        # for each actuator of the model (MuJoCo order), its row in the ctrl input block
        self.ctrl_rows = ms.flat_index([index[m.actuator(a).name] for a in range(m.nu)], 1)
        sensors = {m.sensor(s).name: s for s in range(m.nsensor)}
        rows, src = [], []
        for name, dim, adr in layout.sensors:
            if name in sensors:
                rows.extend(range(adr, adr + dim))
                src.extend(range(int(m.sensor_adr[sensors[name]]), int(m.sensor_adr[sensors[name]]) + dim))
        self.n_sensor_values = len(rows)  # values of the layout's sensors present in the model
        self.sensor_rows = ms.flat_index(rows, 1)  # ... their positions in the sensordata output
        self.sensor_src = ms.flat_index(src, 1)  # ... and in data.sensordata
        ours = VEL_PREFIX
        # values of the model's own sensors, at the start of sensordata (the core's velocity sensors follow)
        self.n_model_sensordata = sum(int(m.sensor_dim[s]) for n, s in sensors.items() if not n.startswith(ours))

    def _map_free(self, layout: ms.Layout) -> None:
        rows, ids, dofs = [], [], []
        animated = self.anim.bodies if self.anim is not None else frozenset()
        for row, b in enumerate(layout.free_bodies):
            bid = self.body_id.get(b) if b not in animated else None  # (an animated robot ignores them)
            free = [self.joint_slices[j] for j in layout.body_joints[b]
                    if j in self.joint_slices and self.joint_slices[j].nq == 7]
            if bid is not None and free:  # not frozen (fused into the world, or kept as a static body)
                rows.append(row)
                ids.append(bid)
                dofs.append(free[0].dof_adr)
        self.free_rows = ms.flat_index(rows, 6)  # the moving free bodies' rows in body_wrench / body_velocity
        self.free_xfrc = ms.flat_index(ids, 6)  # ... and their wrenches in xfrc_applied (flat)
        # (row, body id, first dof of its free joint) of each: where a velocity input goes
        self.free_dofs = tuple(zip(rows, ids, dofs, strict=True))
        # row -> (body id, first dof) of the other moving free bodies welded to it (`make_joint`, through
        # any chain of welds): a velocity set moves them with it, as one rigid body
        welds = [w for w in self.edits.welds if w.kind == "weld"]
        group = {b: {b} for w in welds for b in (w.a, w.b)}
        for w in welds:
            if group[w.a] is not group[w.b]:
                merged = group[w.a] | group[w.b]
                for b in merged:
                    group[b] = merged
        moving = {layout.free_bodies[r]: (r, i, d) for r, i, d in self.free_dofs}
        self.welded = {moving[b][0]: tuple(moving[o][1:] for o in sorted(group[b]) if o != b and o in moving)
                       for b in moving if b in group}
