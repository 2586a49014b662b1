"""Where each recorded signal of a ``threads`` batch comes from in what `mujoco.rollout` returns
(`modules.mujoco.rollout_backend`): the core's port columns (`_Ports`), the source of each column in the
rolled-out state, sensor data or kinematics (`_Sources`), and the signals of one rolled-out branch taken
from there (`_Gather`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.errors import DynabrainError

if TYPE_CHECKING:
    from .rollout_backend import _Job

# where the value of one column of a core port comes from (`_Sources`)
CONST, QPOS, QVEL, SENS_PV, SENS_ACC, XPOS, XQUAT, UNKNOWN = range(8)
OUTPUT_BLOCKS = ("body_pos", "body_quat", "joint_q", "joint_qd", "sensordata", "body_linvel", "body_angvel")
DRIVEN_BLOCKS = ("ctrl", "joint_force", "body_wrench")  # inputs that become rollout's controls
HELD_BLOCKS = ("body_velocity",)  # inputs it runs with only while they ask for nothing (NaN)
ANIMATION_BLOCKS = ("joint_target",)  # inputs only animated robots follow (which it refuses): no effect here
INPUT_BLOCKS = DRIVEN_BLOCKS + HELD_BLOCKS + ANIMATION_BLOCKS
SUPPORTED_INPUTS = ("the core's actuator controls, joint forces and free-body wrenches (core.ctrl, "
                    "core.<actuator>.ctrl, core.joint_force, core.<joint>.force, core.body_wrench, core.<body>.wrench)")
SUPPORTED_RECORD = ("the core's ports: body pos, quat, linvel, angvel; joint q, qd; sensors and sensordata; its inputs "
                    "(ctrl, joint forces, wrenches)")


def refuse(message: str) -> DynabrainError:
    return DynabrainError(f"batch backend 'threads': {message}")


@dataclass(frozen=True)
class _Column:
    """A port of the core as a run of columns of one of its block ports."""

    block: str
    start: int
    size: int
    shape: tuple[int, ...]


class _Ports:
    """The core's fixed port layout (the same for every structure): each port as columns of a block,
    and which object each row of a block is."""

    def __init__(self, core: Any):
        self.core = core.name
        self.ports: dict[str, _Column] = {}
        self.rows: dict[str, dict[int, str]] = {}  # block -> {row: object name}
        ports = [*core.inputs(), *core.outputs()]
        blocks = {p.name: p for p in ports if p.view_of is None}
        for p in ports:
            if p.view_of is None:
                self.ports[p.name] = _Column(p.name, 0, p.size, tuple(p.shape))
                continue
            block, row = p.view_of
            width = int(np.prod(blocks[block].shape[1:], dtype=np.int64))
            self.ports[p.name] = _Column(block, row * width, p.size, tuple(p.shape))
            self.rows.setdefault(block, {})[row] = p.name.rpartition(".")[0] if block != "sensordata" \
                else p.name.partition(".")[2]
        self.sizes = {name: p.size for name, p in blocks.items()}
        self.inputs = [p.name for p in core.inputs() if p.view_of is None]

    def column(self, full: str) -> _Column | None:
        prefix = f"{self.core}."
        return self.ports.get(full[len(prefix):]) if full.startswith(prefix) else None


class _Sources:
    """Where each column of each output block comes from in one compiled structure (`CONST` ...
    ``XQUAT``, with its index into that source), and where each driven input block goes: ``routes``
    maps it to (the rollout control bit, the width of that MuJoCo array, the block's columns, their
    positions in the array)."""

    def __init__(self, model: Any, ports: _Ports, vel_prefix: str):
        self.model, self.ports = model, ports
        self.ids = {"body": {model.body(i).name: i for i in range(model.nbody)},
                    "joint": {model.joint(i).name: i for i in range(model.njnt)},
                    "sensor": {model.sensor(i).name: i for i in range(model.nsensor)}}
        self.kind = {b: np.full(ports.sizes[b], CONST) for b in OUTPUT_BLOCKS if b in ports.sizes}
        self.index = {b: np.zeros(ports.sizes[b], dtype=np.int64) for b in self.kind}
        self._bodies(vel_prefix, int(mujoco.mjtJoint.mjJNT_FREE))
        self._joints_sensors({int(mujoco.mjtStage.mjSTAGE_POS): SENS_PV, int(mujoco.mjtStage.mjSTAGE_VEL): SENS_PV,
                              int(mujoco.mjtStage.mjSTAGE_ACC): SENS_ACC})
        self.routes = self._routes(mujoco.mjtState)
        own = [s for s in range(model.nsensor) if not model.sensor(s).name.startswith(vel_prefix)]
        self.n_own_sensordata = int(sum(model.sensor_dim[s] for s in own))  # the model's sensors (first in it)
        del self.model, self.ports, self.ids

    def _bodies(self, vel_prefix: str, free: int) -> None:
        """Poses and velocities of the bodies that move (the core gives them velocity sensors); the others
        (static, or fused into the world) keep their bus value."""
        m, sensors = self.model, self.ids["sensor"]
        self.free_body = {}  # body name -> its id, for the moving bodies with a free joint
        for row, body in self.ports.rows.get("body_pos", {}).items():
            bid, lin = self.ids["body"].get(body), sensors.get(f"{vel_prefix}lin_{body}")
            if bid is None or lin is None:
                continue
            if m.body_jntnum[bid] > 0 and m.jnt_type[m.body_jntadr[bid]] == free:
                self.free_body[body] = bid  # mj_kinematics copies its position from qpos as it is
                self._set("body_pos", row, 3, QPOS, m.jnt_qposadr[m.body_jntadr[bid]])
            else:
                self._set("body_pos", row, 3, XPOS, 3 * bid)
            self._set("body_quat", row, 4, XQUAT, 4 * bid)
            self._set("body_linvel", row, 3, SENS_PV, m.sensor_adr[lin])
            self._set("body_angvel", row, 3, SENS_PV, m.sensor_adr[sensors[f"{vel_prefix}ang_{body}"]])

    def _joints_sensors(self, stage: dict[int, int]) -> None:
        m = self.model
        for row, joint in self.ports.rows.get("joint_q", {}).items():
            jid = self.ids["joint"].get(joint)
            if jid is not None:
                self._set("joint_q", row, 1, QPOS, m.jnt_qposadr[jid])
                self._set("joint_qd", row, 1, QVEL, m.jnt_dofadr[jid])
        for adr, name in self.ports.rows.get("sensordata", {}).items():
            sid = self.ids["sensor"].get(name)
            if sid is not None:
                dim, first = int(m.sensor_dim[sid]), int(m.sensor_adr[sid])
                self.kind["sensordata"][adr:adr + dim] = stage.get(int(m.sensor_needstage[sid]), UNKNOWN)
                self.index["sensordata"][adr:adr + dim] = np.arange(first, first + dim)

    def _routes(self, bits: Any) -> dict[str, tuple[int, int, np.ndarray, np.ndarray]]:
        m, rows, joints = self.model, self.ports.rows, self.ids["joint"]
        acts = {name: row for row, name in rows.get("ctrl", {}).items()}
        pairs = {  # block -> (control bit, width of the MuJoCo array, [(block column, array index)])
            "ctrl": (bits.mjSTATE_CTRL, m.nu, [(acts[m.actuator(a).name], a) for a in range(m.nu)]),
            "joint_force": (bits.mjSTATE_QFRC_APPLIED, m.nv, [
                (r, m.jnt_dofadr[joints[j]]) for r, j in sorted(rows.get("joint_force", {}).items()) if j in joints]),
            "body_wrench": (bits.mjSTATE_XFRC_APPLIED, 6 * m.nbody, [
                (6 * r + c, 6 * self.free_body[b] + c) for r, b in sorted(rows.get("body_wrench", {}).items())
                if b in self.free_body for c in range(6)])}
        return {block: (int(bit), width, np.array([p[0] for p in cols], dtype=np.int64),
                        np.array([p[1] for p in cols], dtype=np.int64))
                for block, (bit, width, cols) in pairs.items() if cols}

    def _set(self, block: str, row: int, width: int, kind: int, first: int) -> None:
        if block in self.kind:
            self.kind[block][row * width:(row + 1) * width] = kind
            self.index[block][row * width:(row + 1) * width] = np.arange(first, first + width)


class _Gather:
    """The recorded signals of one rolled-out branch, each value taken from where the world has it
    after each tick (see the module docstring)."""

    def __init__(self, job: _Job, state: np.ndarray, sensordata: np.ndarray | None, data: Any, kin: Any):
        self.job, self.state, self.sensordata, self.data, self.kin = job, state, sensordata, data, kin
        nsub, ticks = job.start.substeps, job.task.ticks
        self.after = np.arange(1, ticks + 1) * nsub - 1  # the step that ends tick k: its state is state k+1
        self.cache: dict[int, np.ndarray] = {}
        self.poses: tuple[np.ndarray, np.ndarray] | None = None  # (xpos, xquat) after each tick

    def signals(self, columns: dict[str, _Column]) -> dict[str, np.ndarray]:
        out = {}
        ticks, start = self.job.task.ticks, self.job.start
        for name in self.job.task.record:
            col = columns[name]
            cols = slice(col.start, col.start + col.size)
            if col.block in INPUT_BLOCKS:
                values = self.job.inputs[col.block][:, cols]
            else:
                values = np.empty((ticks, col.size))
                kinds, index = start.sources.kind[col.block][cols], start.sources.index[col.block][cols]
                for kind in np.unique(kinds):
                    at = kinds == kind
                    if kind == CONST:
                        values[:, at] = start.bus[col.block][cols][at]
                    else:
                        values[:, at] = self.source(int(kind))[:, index[at]]
            out[name] = values.reshape(ticks, *col.shape)
        return out

    def source(self, kind: int) -> np.ndarray:
        """(ticks, n): one source array's value after each tick."""
        hit = self.cache.get(kind)
        if hit is None:
            hit = self.cache[kind] = self._make(kind)
        return hit

    def _make(self, kind: int) -> np.ndarray:
        model = self.job.start.model
        if kind == QPOS:  # a mjSTATE_FULLPHYSICS row: time, qpos, qvel, ...
            return self.state[self.after, 1:1 + model.nq]
        if kind == QVEL:
            return self.state[self.after, 1 + model.nq:1 + model.nq + model.nv]
        if kind == SENS_ACC:
            assert self.sensordata is not None
            return self.sensordata[self.after]
        if kind == SENS_PV:  # the next step's first half; the last tick's from the final mj_step1
            assert self.sensordata is not None
            return np.concatenate([self.sensordata[self.after[:-1] + 1], self.data.sensordata[None]])
        return self._kinematics()[0 if kind == XPOS else 1]

    def _kinematics(self) -> tuple[np.ndarray, np.ndarray]:
        """(xpos, xquat) of every body after each tick: mj_kinematics of each tick's positions."""
        if self.poses is None:
            start, kin = self.job.start, self.kin
            model = start.model
            kin.mocap_pos[:], kin.mocap_quat[:] = start.mocap
            qpos = self.state[self.after, 1:1 + model.nq]
            xpos, xquat = np.empty((len(qpos), model.nbody * 3)), np.empty((len(qpos), model.nbody * 4))
            for k, q in enumerate(qpos):
                kin.qpos[:] = q
                mujoco.mj_kinematics(model, kin)
                xpos[k], xquat[k] = kin.xpos.reshape(-1), kin.xquat.reshape(-1)
            self.poses = (xpos, xquat)
        return self.poses
