"""The MuJoCo physics core: a SceneSpec (or an MJCF file) simulated by MuJoCo as a dynabrain module.

Choices (see also `mujoco.scene`):

- integrator ``implicitfast``: joint damping and velocity-dependent actuator forces are integrated
  implicitly, so damped joints and stiff drives stay stable at the world's step, at the cost of an
  explicit step (no Coriolis derivatives); elliptic friction cones with the Newton solver (MuJoCo's
  most accurate friction model); automatic reset on bad numbers is off, so a divergence stays visible
  and `step` raises `PhysicsDivergedError` instead of silently restarting the model. A model file's own
  ``<option>`` (timestep, integrator, cone, solver, iterations ...) is kept, and the scene's ``options``
  override both (`mujoco.options`); a timestep of its own sets the substeps (unless ``substeps`` is given):
  MuJoCo steps at it when it divides the world's step;
- the data is kept "after `mj_step1`": a step is `mj_step2` (inputs already in place), more full steps
  for the substeps, then `mj_step1`, so positions, velocities and sensors of the new state are current
  for the outputs at no extra cost;
- ports are block ports (``body_pos`` ...) written with one array operation each; every named object
  has its own port as a view into a block (a joint's ``q``, ``qd``, ``force`` and an actuator's ``ctrl``
  have shape (1,), like the other modules' one-value signals). Body velocities come from MuJoCo frame-velocity sensors
  the core adds for moving bodies (computed in C). ``sensordata`` holds all the model's sensor values
  in MuJoCo's order, and each sensor's port (``sensor.<name>``) is a view into it. The outputs are
  declared in the order of the MuJoCo arrays they come from, so a step writes them all with five
  memory copies (poses, joints, and one run of sensordata for the sensors and the velocities);
- the free bodies' inputs (`PhysicsCore`): ``B.wrench`` goes into ``xfrc_applied`` (world frame, at
  the body's centre of mass, MuJoCo's own convention) before every step, as joint forces go into
  ``qfrc_applied``; a ``B.velocity`` that holds a value is written into the body's free joint
  (``qvel``: its linear velocity is the body origin's in the world frame, its angular one in the body
  frame) at the start of the step, bodies welded to it (`make_joint`) moved with it as one rigid
  body, and the velocity-dependent half of the step is computed again (``mj_step1``, as after a
  parameter change). Neither is state (`STATE`): both come from the inputs, on the bus;
- structural edits (`make`, `make_joint`, `no_collision`, `add_body`, `remove_body`) recompile the
  model (`mujoco.scene`; `make` with ``others="absent"`` leaves the others out of it, their outputs
  holding where they stood, as a frozen body's do); each compiled model (a `CompiledScene`) is cached by its edits, so a
  rollback across an edit costs a dictionary look-up. The state is ``(edits, integration state
  array, sensor values)`` (see `STATE`);
- bodies added or removed change the ports: each set of bodies (`Edits.scene_key`) has its layout and
  ports (a `SceneView`, compiled once from the model with those bodies and no other edit, kept for the
  core's life), and `bind` takes the one whose ports it is bound to (a rollback binds the old ones);
- joints made at run time: a weld is a weld equality, a ball a connect equality at the anchor, a hinge
  two connects on its axis (10 cm apart), a slider a carriage body (a hundredth of the sliding body's
  mass) on a slide joint in body a with body b welded to it; all at the welds' stiffness (solref
  2 steps). MuJoCo computes a connect's second anchor from the model's reference pose, so the core
  writes it after compiling;
- a body's own friction and restitution (the scene's, an added body's, `set_material`'s) go to its
  geoms with priority 1: a contact takes the coefficients of the geom of higher priority (MuJoCo's
  rule), so they rule its contacts with bodies without; between two bodies with their own, MuJoCo's
  mix (the larger friction, the mean contact stiffness and damping). They are model parameters,
  applied without recompiling (`_apply_params`), like the core's;
- a fork (`World.fork`, a deep copy) copies only the MuJoCo data of the current structure, into data a
  closed fork left when there is some; the compiled model is shared until either core changes a
  run-time parameter, which copies it first (`ModelShare`, `CompiledScene.own_model`);
- a robot (an object whose joints actuators drive) that `make` leaves out is animated, not frozen: it
  keeps its joints and follows its input ``joint_target`` kinematically (`mujoco.animate`);
- modules that need MuJoCo's own model and data (native sensors, contacts) read them through
  `MujocoCore.mj` (a `MujocoView`), through `mujoco.access.MujocoLink`;
- MuJoCo's warnings go to the ``dynabrain.mujoco`` log, the first of each kind only, the rest counted
  (`mujoco.warning_log`; `dynabrain run` prints how many were not shown).
"""

from __future__ import annotations

import copy
import operator
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.core import (
    NO_EDITS,
    BodyInfo,
    BodySpec,
    Edits,
    SceneSpec,
    body_inputs,
    requested_velocity,
)
from dynabrain.orchestrator.kernel.edited import EditedCore
from dynabrain.orchestrator.kernel.errors import DynabrainError, PhysicsDivergedError
from dynabrain.orchestrator.kernel.module import Capabilities, Param, Port, SetupContext

from . import animate, batched, restitution, warning_log
from . import options as mo
from . import scene as ms
from .compiled import (
    STATE,
    CompiledScene,
    SceneView,
    _empty,
    _move,
    _positions,
)
from .drawing import ModelFileDrawing
from .spec_source import SpecSource, fail

warning_log.install()  # MuJoCo's warnings to the log, each kind once, counted (no MUJOCO_LOG.TXT)

CACHE_SIZE = 16
DEFAULT_PERIOD_S = 0.002
_step1, _step2 = mujoco.mj_step1, mujoco.mj_step2  # the two halves of a step, looked up once


class MujocoCore(EditedCore):
    """A physics core on MuJoCo. ``scene`` is primitives or an MJCF file (``scene.model``)."""

    ENGINE = "mujoco"
    # finite_outputs off: the step checks MuJoCo's own warnings for NaN, infinite or huge values in
    # qpos, qvel and qacc (`PhysicsDivergedError` at that tick, naming the joint), and every output is
    # computed from those, so the kernel's sum over ~700 outputs (0.3 us a humanoid tick) adds nothing
    CAPABILITIES = Capabilities(can_rollback=True, can_fork=True, feedthrough=False, finite_outputs=False)
    PARAMS = (
        Param("friction", 1.0, runtime=True, doc="sliding friction coefficient of every geom"),
        Param("restitution", 0.0, runtime=True, doc="coefficient of restitution of contacts, 0..1"),
        Param("gravity", (0.0, 0.0, -9.81), unit="m/s^2", runtime=True, dimension="acceleration",
              doc="gravity vector"),
        Param("substeps", 1, runtime=True, doc="MuJoCo steps per module step (timestep = period/substeps)"),
    )

    MADE_JOINTS = ("weld", "hinge", "slider", "ball")
    MASSES = True
    option_problem = staticmethod(mo.option_problem)
    """What is wrong with a scene option (`SceneSpec.options`, MuJoCo's ``<option>``), or None: the scenario
    reports it with its line."""

    def __init__(self, name: str, scene: SceneSpec, *, scenario_dir: str | None = None, **params: Any):
        super().__init__(name, scene, **params)
        for key, value in self.params.items():
            self._check_param(key, value)
        self._period = DEFAULT_PERIOD_S
        self._substeps_given = "substeps" in params  # else a model file's own timestep sets them (`setup`)
        self._source = SpecSource(name, scene, scenario_dir)
        self._scenes: dict[tuple, SceneView] = {}  # scene key -> its layout and ports (never dropped: see bind)
        self._by_ports: dict[frozenset[str], SceneView] = {}  # the same, by the names of its outputs
        self._cache: OrderedDict[Edits, CompiledScene] = OrderedDict()
        self._edits = NO_EDITS
        self._use_scene(self._scene_view(NO_EDITS))
        self._use(self._compiled_for(NO_EDITS))
        self._apply_params(self._compiled)
        mujoco.mj_forward(self._compiled.model, self._compiled.data)
        self._unbind()

    # -- ports --------------------------------------------------------------------------------------------
    @staticmethod
    def _make_ports(lay: ms.Layout) -> tuple[tuple[Port, ...], tuple[Port, ...]]:
        """Block ports, each object's port a view into one. The outputs come in the order of the
        arrays they are copied from, so that a step fills them with few copies: poses (xpos, xquat),
        joints (qpos, qvel), then the model's sensors and the body velocities (one run of sensordata)."""
        outs, ins, views = [], [], []
        body_blocks = (("body_pos", "pos", 3, "m"), ("body_quat", "quat", 4, "1"),
                       ("body_linvel", "linvel", 3, "m/s"), ("body_angvel", "angvel", 3, "rad/s"))

        def bodies(blocks: tuple) -> None:
            for block, q, n, unit in blocks:
                outs.append(Port(block, (len(lay.bodies), n), unit, doc=f"{q} of every body"))
                views.extend(Port(f"{b}.{q}", (n,), unit, view_of=(block, i)) for i, b in enumerate(lay.bodies))

        if lay.bodies:
            bodies(body_blocks[:2])
        if lay.qjoints:
            units = list(zip(*lay.qunits, strict=True))
            uq, uf = (u[0] if len(set(u)) == 1 else "1" for u in units)
            uqd = f"{uq}/s" if uq != "1" else "1"
            outs += [Port("joint_q", (len(lay.qjoints),), uq), Port("joint_qd", (len(lay.qjoints),), uqd)]
            ins.append(Port("joint_force", (len(lay.qjoints),), uf))
            for i, (j, (q, f)) in enumerate(zip(lay.qjoints, lay.qunits, strict=True)):
                views += [Port(f"{j}.q", (), q, view_of=("joint_q", i)),
                          Port(f"{j}.qd", (), f"{q}/s", view_of=("joint_qd", i))]
                ins.append(Port(f"{j}.force", (), f, view_of=("joint_force", i)))
        if lay.actuators:
            ins.append(Port("ctrl", (len(lay.actuators),), "1"))
            ins += [Port(f"{a}.ctrl", (), "1", view_of=("ctrl", i)) for i, a in enumerate(lay.actuators)]
        if lay.motor_joints:
            unit = {lay.qunits[lay.qjoints.index(j)][0] for j in lay.motor_joints}
            ut = unit.pop() if len(unit) == 1 else "1"
            nan = float("nan")
            ins.append(Port("joint_target", (len(lay.motor_joints),), ut, start=nan, doc="where each joint with "
                            "a motor goes while its robot is animated (not selected; `mujoco.animate`); NaN: "
                            "it stays where it is"))
            ins += [Port(f"{j}.target", (), ut, view_of=("joint_target", i), start=nan)
                    for i, j in enumerate(lay.motor_joints)]
        ins += body_inputs(lay.free_bodies)
        if lay.sensors:
            outs.append(Port("sensordata", (lay.nsensordata,), "1", doc="all sensor values, MuJoCo order"))
            views += [Port(f"sensor.{n}", (dim,), "1", view_of=("sensordata", adr)) for n, dim, adr in lay.sensors]
        if lay.bodies:
            bodies(body_blocks[2:])
        return tuple(ins), tuple(outs + views)

    def _unbind(self) -> None:
        """A private buffer in place of the bus (laid out as the bus lays out the outputs): the step
        code never tests for missing ports."""
        self._own_out = np.zeros(sum(p.size for p in self._ports_out if p.view_of is None))
        self._out_views(self._own_out)
        lay = self._layout
        self._force, self._ctrl = np.zeros(len(lay.qjoints)), np.zeros(len(lay.actuators))
        self._target = np.full(len(lay.motor_joints), np.nan)
        self._wrench, self._vel = np.zeros(6 * len(lay.free_bodies)), np.full(6 * len(lay.free_bodies), np.nan)
        self._vel_unset = self._vel.tobytes()  # the velocity inputs' bytes while they ask for nothing
        self._moves: tuple | None = None  # (structure, copies) of `step`, made on first use

    def _out_views(self, flat: np.ndarray) -> None:
        """``self._out`` (every output, flat, in declaration order), the offset of each block in it,
        and a flat view of each block."""
        self._out, self._offset, at, blocks = flat, {}, 0, {}
        for port in self._ports_out:
            if port.view_of is None:
                self._offset[port.name], blocks[port.name] = at, flat[at:at + port.size]
                at += port.size
        empty = np.zeros(0)
        self._pos, self._quat, self._lin, self._ang = (blocks.get(f"body_{q}", empty)
                                                       for q in ("pos", "quat", "linvel", "angvel"))
        self._q, self._qd, self._sd = (blocks.get(k, empty) for k in ("joint_q", "joint_qd", "sensordata"))

    def bind(self) -> None:
        """Take the ports of the binding: those of the current bodies, or (a rollback across an added or
        removed body) those of an earlier layout, which the state restored next goes with."""
        names = frozenset(self.out)
        if names and names != self._scene.out_names:
            view = self._by_ports.get(names)
            if view is None:
                raise DynabrainError(f"core {self.name!r}: bound to outputs of no body layout it has had "
                                     f"({len(names)} ports; it has {len(self._scene.out_names)} now)")
            self._use_scene(view)
        self._attach(names)

    def _attach(self, names: frozenset[str] | None = None) -> None:
        """Views on the bus when the binding holds the current layout's ports; otherwise (an edit that
        added or removed bodies, until the world binds the new ports) private buffers."""
        self._unbind()
        if not self.out or (frozenset(self.out) if names is None else names) != self._scene.out_names:
            return
        if self.out_flat.size == self._own_out.size:  # bound to the bus: write there
            self._out_views(self.out_flat)
        else:
            raise DynabrainError(f"core {self.name!r}: its outputs are bound without `out_flat`; the core writes "
                                 "them through it (bind as the World does)")
        for attr, key in (("_force", "joint_force"), ("_ctrl", "ctrl"), ("_wrench", "body_wrench"),
                          ("_vel", "body_velocity"), ("_target", "joint_target")):
            if self.inp.get(key) is not None:
                setattr(self, attr, np.asarray(self.inp[key]).reshape(-1))

    # -- lifecycle --------------------------------------------------------------------------------------------
    def setup(self, ctx: SetupContext) -> None:
        self._period = ctx.period_ns * 1e-9
        own = self._source.timestep_s  # a model file's own timestep, or the scene options': MuJoCo steps at it
        if own is not None and not self._substeps_given:
            try:
                substeps = mo.substeps_for(self._period, own)
            except ValueError as exc:
                raise fail(self.name, f"scene, field options: {exc}") from None
            if substeps != self.params["substeps"]:
                self.set_param("substeps", substeps, running=False)
        self._apply_params(self._compiled)
        mujoco.mj_forward(self._compiled.model, self._compiled.data)

    def step(self, t_ns: int, dt_ns: int) -> None:
        s = self._compiled
        moves = self._moves
        if moves is None or moves[0] is not s:
            moves = self._moves = (s, *self._plan_moves(s))
        for dst, di, src, si in moves[1]:  # inputs: joint forces, motor controls, wrenches
            dst[di] = src if si is None else src[si]
        if self._vel.tobytes() != self._vel_unset:  # a velocity input holds a value
            self._set_velocities(s)
        m, d = s.model, s.data
        anim = s.anim
        before = s.qpos[anim.drive_qadr] if anim is not None else None  # (a copy: fancy indexing)
        _step2(m, d)
        if self._nsub > 1:
            mujoco.mj_step(m, d, self._nsub - 1)
        if anim is not None:  # animated robots: where their motion puts them, before kinematics and sensors
            animate.animate(anim, s.qpos, s.qvel, self._target, before, dt_ns * 1e-9)
        _step1(m, d)
        bad = s.bad_qpos.number + s.bad_qvel.number + s.bad_qacc.number
        if bad != s.warnings_seen:  # MuJoCo's own checks: NaN, inf or |x| > 1e10 in qpos, qvel, qacc
            raise PhysicsDivergedError(self.name, "step", None, self._divergence(s, bad))
        for dst, di, src, si in moves[2]:  # the outputs that can change in a step (`_write_outputs`)
            dst[di] = src if si is None else src[si]

    @classmethod
    def step_batch(cls, members: Sequence[Any], t_ns: int, dt_ns: int, inp: Any, out: Any,
                   failed: dict[int, BaseException]) -> None:
        """The cores of N branches stepped one tick, their physics on threads (`batched.step_cores`)."""
        batched.step_cores(members, t_ns, dt_ns, failed)

    def get_state(self) -> tuple:
        s = self._compiled
        arr = np.empty(s.state_size)
        mujoco.mj_getState(s.model, s.data, arr, STATE)
        sensors = s.sensordata[:s.n_model_sensordata].copy() if s.n_model_sensordata else None
        return (self._edits, arr, sensors)

    def set_state(self, state: tuple) -> None:
        edits, arr, sensors = state
        if edits is not self._edits and edits != self._edits:
            self._activate(edits, carry=False)
        s = self._compiled
        mujoco.mj_setState(s.model, s.data, np.asarray(arr, dtype=np.float64), STATE)
        mujoco.mj_step1(s.model, s.data)
        if sensors is not None:
            s.sensordata[:len(sensors)] = sensors  # acceleration-stage sensors of the last step
        self._write_all()

    def _set_velocities(self, s: CompiledScene) -> None:
        """Give each free body the velocity its input asks for (components that are not NaN; see
        `PhysicsCore`), then compute the velocity-dependent half of the step again (the data is kept
        after ``mj_step1``, computed with the old velocities), as `on_param` does."""
        want, qvel, xmat, xpos, changed = self._vel, s.qvel, s.data.xmat, s.data.xpos, False
        for row, bid, dof in s.free_dofs:
            rot = xmat[bid].reshape(3, 3)  # body frame -> world; a free joint's angular velocity is in the body frame
            omega = rot @ qvel[dof + 3:dof + 6]
            lin, ang = requested_velocity(want[6 * row:6 * row + 6], qvel[dof:dof + 3], omega)
            if lin is None and ang is None:
                continue
            if lin is not None:  # a free joint's linear velocity is its body origin's, in the world frame
                qvel[dof:dof + 3] = lin
            if ang is not None:
                qvel[dof + 3:dof + 6] = rot.T @ ang
            changed = True
            for other, odof in s.welded.get(row, ()):  # what it is welded to moves with it, rigidly
                omega = omega if ang is None else ang
                qvel[odof:odof + 3] = qvel[dof:dof + 3] + np.cross(omega, xpos[other] - xpos[bid])
                qvel[odof + 3:odof + 6] = xmat[other].reshape(3, 3).T @ omega
        if changed:
            mujoco.mj_step1(s.model, s.data)

    def on_param(self, name: str, value: Any) -> None:
        self._check_param(name, value)
        s = self._compiled
        self._apply_params(s)
        # the data is kept after mj_step1, computed with the old values (gravity's bias forces, the
        # contacts' friction and stiffness): compute it again, as restoring this state would
        mujoco.mj_step1(s.model, s.data)

    def close(self) -> None:
        """Let go of every compiled scene (a fork's next sibling may take their data: `CompiledScene.release`)."""
        self._compiled.release()
        for s in self._cache.values():
            s.release()
        self._cache.clear()
        self._view = None

    def fork(self, memo: dict) -> MujocoCore:
        """An independent copy (`fork`, `World.fork`), unbound, that copies only what changes: the
        MuJoCo data of the current structure. It shares what never changes: the spec source, the port
        layout, the index maps, and the compiled model until either core writes it (a run-time parameter
        change copies it first: `CompiledScene.own_model`); the parameter dict is shared too, as history
        shares it (a change makes a new one). The cache of other structures starts empty (they are
        recompiled, identically, when needed)."""
        twin = copy.copy(self)
        memo[id(self)] = twin
        twin.bind_ports(None)
        twin._unbind()
        twin._cache = OrderedDict()
        twin._use(twin._remember(self._compiled.clone()))
        return twin

    def engine_notes(self) -> str | None:
        """MuJoCo's warnings the run counted but did not show again (`warning_log`)."""
        return warning_log.summary()

    # -- drawing (logs, viewers) --------------------------------------------------------------------------
    def world_geoms(self) -> list[dict]:
        """The model file's geoms of no body (its ground), read from the file again (`drawing`)."""
        return self._drawing().world_geoms()

    def mesh(self, name: str) -> tuple[np.ndarray, np.ndarray] | None:
        """A model file's mesh for drawing (`drawing`)."""
        return self._drawing().mesh(name)

    def _drawing(self) -> ModelFileDrawing:
        drawing = self.__dict__.get("_drawing_of")
        if drawing is None:
            drawing = self.__dict__["_drawing_of"] = ModelFileDrawing(self.scene.model)
        return drawing

    mj = property(operator.attrgetter("_view"), doc=(
        "The MuJoCo model and data simulated now (a `MujocoView`), read only; another view after each switch "
        "to another compiled model. Its getter is C code (`operator.attrgetter`): sensors read it every step."))

    # -- parameters -----------------------------------------------------------------------------------------
    def _check_param(self, name: str, value: Any) -> None:
        bad = {"friction": lambda v: v < 0, "restitution": lambda v: not 0 <= v <= 1,
               "substeps": lambda v: v < 1, "gravity": lambda v: not np.all(np.isfinite(v))}
        if name in bad and bad[name](value):
            raise fail(self.name, f"parameter {name} = {value!r} is out of range")

    def _apply_params(self, s: CompiledScene) -> None:
        """Apply every run-time parameter to a structure's model (idempotent). The only place the
        core writes a model: it makes it the structure's own first (a fork may share it), and does
        nothing when the model holds these very values already (the same parameter dict and period:
        dicts are never changed in place)."""
        p = self.params
        self._nsub = int(p["substeps"])
        materials = self._edits.materials
        if (s.applied is not None and s.applied[0] is p and s.applied[1] == self._period
                and s.applied_materials == materials):
            return
        if s.own_model() and s is self._compiled:
            self._view = s.view
        m = s.model
        dt = self._period / self._nsub
        m.opt.timestep = dt
        m.opt.gravity[:] = p["gravity"]
        fr, g = float(p["friction"]), float(np.linalg.norm(p["gravity"]))
        solref, solimp = restitution.contact_params(float(p["restitution"]), dt, g)
        friction, priority, solrefs = np.full(m.ngeom, fr), np.zeros(m.ngeom, dtype=int), np.tile(solref, (m.ngeom, 1))
        for body, (own_f, own_e) in self._own_materials().items():  # a body's own coefficients rule its contacts
            geoms = s.body_geoms.get(body)
            if geoms is not None:
                priority[geoms] = 1
                if own_f is not None:
                    friction[geoms] = own_f
                if own_e is not None:
                    solrefs[geoms] = restitution.contact_params(own_e, dt, g)[0]
        m.geom_friction[:, 0], m.geom_priority[:], m.geom_solref[:] = friction, priority, solrefs
        m.geom_solimp[:] = solimp
        if m.npair:
            m.pair_solref[:], m.pair_solimp[:], m.pair_friction[:, :2] = solref, solimp, fr
        if len(s.weld_ids):
            m.eq_solref[s.weld_ids] = (2.0 * dt, 1.0)
            m.eq_solimp[s.weld_ids] = (0.99, 0.99, 0.001, 0.5, 2.0)
        self._apply_masses(s, materials)
        s.applied, s.applied_materials = (p, self._period), materials

    @staticmethod
    def _apply_masses(s: CompiledScene, materials: tuple) -> None:
        """Bodies' own masses (`set_material(mass=...)`): each body's mass and its inertia scaled alike
        from the compiled ones, then the model's constants that depend on them (subtree masses, the
        inverse weights) computed again on scratch data. Nothing is done while no body has one."""
        own = {mat.body: mat.mass for mat in materials if mat.mass is not None}
        if not own and not s.masses_set:
            return
        m = s.model
        m.body_mass[:], m.body_inertia[:] = s.mass0, s.inertia0
        for body, mass in own.items():
            bid = s.body_id.get(body)
            if bid is not None and s.mass0[bid] > 0:
                m.body_mass[bid] = mass
                m.body_inertia[bid] = s.inertia0[bid] * (mass / s.mass0[bid])
        mujoco.mj_setConst(m, mujoco.MjData(m))
        s.masses_set = bool(own)

    def _own_materials(self) -> dict[str, tuple[float | None, float | None]]:
        """Body -> its own (friction, restitution), for the bodies that have one: the scene's and the
        added bodies' values, and those set at run time (`set_material`)."""
        key = (self._edits.scene_key(), self._edits.materials)
        hit = self._materials_of
        if hit is not None and hit[0] == key:
            return hit[1]
        own = {n: (b.friction, b.restitution) for n, b in self._scene_view(self._edits).specs.items()
               if b.friction is not None or b.restitution is not None}
        for mat in self._edits.materials:
            own[mat.body] = (mat.friction, mat.restitution)
        own = {b: v for b, v in own.items() if v != (None, None)}
        self._materials_of = (key, own)
        return own

    # -- outputs ------------------------------------------------------------------------------------------------
    def _write_outputs(self, s: CompiledScene) -> None:
        """Outputs that can change in a step: moving bodies, joints, sensors."""
        moves = self._moves
        if moves is None or moves[0] is not s:
            moves = self._moves = (s, *self._plan_moves(s))
        for dst, di, src, si in moves[2]:
            dst[di] = src if si is None else src[si]

    def _plan_moves(self, s: CompiledScene) -> tuple[list[tuple], list[tuple]]:
        """The copies `step` makes from the inputs and `_write_outputs` into the outputs (`copies`),
        each made fast: where both indexes are slices the copy goes through memoryviews (a memcpy, ~4x
        cheaper than a numpy slice copy)."""
        ins, outs = self.copies(s)
        return [_move(*c) for c in ins], [_move(*c) for c in outs]

    def copies(self, s: CompiledScene | None = None) -> tuple[list[tuple], list[tuple]]:
        """What a step of scene ``s`` (default: the current one) copies, as ``(dst, index, src, index)``
        (``dst[index] = src[index]``): from the input ports into the MuJoCo data (joint forces, motor
        controls, wrenches), and from the data into the outputs (`_write_outputs`: what can change in a
        step). Copies of neighbouring runs of one array into neighbouring outputs are merged; neighbouring
        runs of one array into scattered outputs (the bodies of a selection: their rows are apart) become
        one copy through an index array. A lockstep batch's physics reads them to make the same copies
        for every branch at once (`modules.mujoco.mjbatch`)."""
        s = self._compiled if s is None else s
        ins = []
        if s.n_joints:
            ins.append((s.qfrc_applied, s.joint_dof_adr, self._force, s.joint_rows))
        if len(s.ctrl):
            ins.append((s.ctrl, slice(None), self._ctrl, s.ctrl_rows))
        if not _empty(s.free_rows):
            ins.append((s.xfrc_flat, s.free_xfrc, self._wrench, s.free_rows))
        outs: list[list] = []  # [dst index in self._out, src array, src index], in output order
        for block, rows, src, index in (("body_pos", s.moving_pos_rows, s.xpos_flat, s.moving_pos_src),
                                        ("body_quat", s.moving_quat_rows, s.xquat_flat, s.moving_quat_src),
                                        ("joint_q", s.joint_rows, s.qpos, s.joint_qpos_adr),
                                        ("joint_qd", s.joint_rows, s.qvel, s.joint_dof_adr),
                                        ("sensordata", s.sensor_rows, s.sensordata, s.sensor_src),
                                        ("body_linvel", s.moving_pos_rows, s.sensordata, s.linvel_src),
                                        ("body_angvel", s.moving_pos_rows, s.sensordata, s.angvel_src)):
            at = self._offset.get(block)
            if at is None or _empty(rows):
                continue
            dst = slice(at + rows.start, at + rows.stop) if isinstance(rows, slice) else rows + at
            last = outs[-1] if outs else None
            follows = (last is not None and last[1] is src and isinstance(last[2], slice) and isinstance(index, slice)
                       and last[2].stop == index.start)  # the next run of the same source array
            if follows and isinstance(last[0], slice) and isinstance(dst, slice) and last[0].stop == dst.start:
                last[0], last[2] = slice(last[0].start, dst.stop), slice(last[2].start, index.stop)
            elif follows:  # scattered rows (a selection): one gather into both blocks, not two
                last[0] = np.concatenate([_positions(last[0]), _positions(dst)])
                last[2] = slice(last[2].start, index.stop)
            else:
                outs.append([dst, src, index])
        return ins, [(self._out, dst, src, index) for dst, src, index in outs]

    def _write_all(self) -> None:
        """Every output, with the constant ones of static and frozen bodies and joints."""
        s = self._compiled
        self._pos[s.pos_rows] = s.xpos_flat[s.pos_src]
        self._quat[s.quat_rows] = s.xquat_flat[s.quat_src]
        self._pos[s.fused_pos_rows] = s.fused_pos
        self._quat[s.fused_quat_rows] = s.fused_quat
        self._lin[s.still_rows] = 0.0
        self._ang[s.still_rows] = 0.0
        self._q[s.frozen_joint_rows] = s.frozen_q
        self._qd[s.frozen_joint_rows] = 0.0
        self._write_outputs(s)

    def _divergence(self, s: CompiledScene, bad: int) -> str:
        """Which joint diverged first (acceleration before velocity before position)."""
        now = [w.number for _what, w in s.warnings]
        what, index = next(((what, int(w.lastinfo)) for (what, w), n0, n in zip(s.warnings, s.warning_counts, now,
                                                                                strict=True) if n > n0))
        s.warning_counts, s.warnings_seen = now, bad
        m = s.model
        if what == "position":
            j = int(np.searchsorted(m.jnt_qposadr, index, side="right")) - 1
        else:
            j = int(m.dof_jntid[index]) if m.nv else -1
        if j < 0:
            return f"{what}s became NaN, infinite or larger than 1e10"
        body = m.body(int(m.jnt_bodyid[j])).name
        return (f"the {what} of joint {m.joint(j).name!r} (body {body!r}) became NaN, infinite or "
                f"larger than 1e10; check the inputs, or reduce forces or the timestep (substeps)")

    # -- scene queries --------------------------------------------------------------------------------------
    @property
    def _index(self) -> Any:
        return self._layout

    def body_info(self, name: str) -> BodyInfo:
        row, lay = self._row(name), self._layout
        return BodyInfo(name=name, free=name in lay.free, parent=lay.parents[row], geoms=lay.geoms[name])

    def body_pose(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        self._row(name)
        s = self._compiled
        bid = s.body_id.get(name)
        if bid is None:
            pose = s.fused_pose[name]
            return np.array(pose[:3]), np.array(pose[3:])
        d = s.data
        return d.xpos[bid].copy(), d.xquat[bid].copy()

    def body_velocity(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        self._row(name)
        s = self._compiled
        bid = s.body_id.get(name)
        res = np.zeros(6)
        if bid is not None:
            mujoco.mj_objectVelocity(s.model, s.data, mujoco.mjtObj.mjOBJ_XBODY, bid, res, 0)
        return res[3:].copy(), res[:3].copy()

    # -- structural edits -----------------------------------------------------------------------------------
    def _freeze_entry(self, obj: str) -> ms.FrozenObject:
        """Where the bodies and joints of ``obj`` stand now."""
        s, lay = self._compiled, self._layout
        bodies, joints = [], []
        for b in lay.subtree[obj]:
            bid = s.body_id[b]
            rel = ms.relative_pose(s.model, s.data, bid) if lay.body_joints[b] else None
            bodies.append(ms.FrozenBody(b, rel, (*map(float, s.data.xpos[bid]), *map(float, s.data.xquat[bid]))))
            for j in lay.body_joints[b]:
                qa, nq, _da, _nv = s.joint_slices[j]
                joints.append((j, tuple(map(float, s.qpos[qa:qa + nq]))))
        robot = any(j in s.driven for j, _ in joints)  # a robot is animated, not frozen
        return ms.FrozenObject(obj, tuple(bodies), tuple(joints), robot)

    def _weld_data(self, a: str, b: str) -> tuple:
        return ms.weld_data(*self.body_pose(a), *self.body_pose(b))

    def _parent(self, body: str) -> str | None:
        return self._layout.parents[self._rows[body]]

    def _reserved_joint_names(self) -> set[str]:
        model = self._compiled.model
        return set(self._layout.joints) | {model.equality(e).name for e in range(model.neq)}

    def place(self, body: str, pos: Sequence[float], quat: Sequence[float] | None = None) -> None:
        self._row(body)
        s, lay = self._compiled, self._layout
        if body not in lay.free:
            raise fail(self.name, f"body {body!r} has no free joint; place moves free bodies")
        joint = next((j for j in lay.body_joints[body] if j in s.joint_slices and s.joint_slices[j].nq == 7), None)
        if joint is not None and s.anim is not None and body in s.anim.bodies:
            raise fail(self.name, f"body {body!r} is animated (a robot not selected: it holds its place); "
                          "select its object with make() first")
        if joint is None:
            state = "absent" if body not in s.body_id else "frozen"
            raise fail(self.name, f"body {body!r} is {state}; select its object with make() first")
        p = np.asarray(pos, dtype=np.float64)
        q = np.asarray(s.qpos[s.joint_slices[joint].qpos_adr + 3:][:4] if quat is None else quat, dtype=np.float64)
        if p.shape != (3,) or q.shape != (4,) or not (np.all(np.isfinite(p)) and np.linalg.norm(q) > 0):
            raise fail(self.name, f"place({body!r}): pos must be 3 numbers and quat 4 (w, x, y, z), not 0")
        qa, _nq, da, _nv = s.joint_slices[joint]
        s.qpos[qa:qa + 3], s.qpos[qa + 3:qa + 7] = p, q / np.linalg.norm(q)
        s.qvel[da:da + 6] = 0.0
        mujoco.mj_forward(s.model, s.data)
        self._write_all()

    # -- structures -----------------------------------------------------------------------------------------
    def _use(self, compiled: CompiledScene) -> None:
        """Make ``compiled`` the compiled scene the core steps (and its view the one `mj` hands out)."""
        self._compiled, self._view = compiled, compiled.view

    def _remember(self, s: CompiledScene) -> CompiledScene:
        self._cache[s.edits] = s
        self._cache.move_to_end(s.edits)
        while len(self._cache) > CACHE_SIZE:
            self._cache.popitem(last=False)
        return s

    def _compiled_for(self, edits: Edits) -> CompiledScene:
        """The compiled scene of ``edits`` (its structure: materials are applied to it, not compiled):
        from the cache, or compiled now."""
        key = edits.structural()
        s = self._cache.get(key)
        if s is None:
            view = self._scene_view(key)  # (new bodies and nothing else: compiles and caches this very structure)
            s = self._cache.get(key)
            if s is None:
                model, movers = ms.build_structure(self.name, self._source, key)
                s = CompiledScene(view.layout, key, model, movers, self._source.geom_body)
        return self._remember(s)

    def _scene_view(self, edits: Edits) -> SceneView:
        """The layout and ports of the bodies of ``edits`` (added and removed ones: `Edits.scene_key`),
        made once per scene key from the model compiled with those bodies and no other edit."""
        key = edits.scene_key()
        view = self._scenes.get(key)
        if view is None:
            bare = NO_EDITS._replace(added=edits.added, removed=edits.removed)
            model, movers = ms.build_structure(self.name, self._source, bare)
            layout = ms.make_layout(model)
            self._remember(CompiledScene(layout, bare, model, movers, self._source.geom_body))
            ports_in, ports_out = self._make_ports(layout)
            specs = {b.name: b for b in (self._source.bodies(key) if self._source.base is None else edits.added)}
            view = SceneView(layout, {b: i for i, b in enumerate(layout.bodies)}, ports_in, ports_out,
                             frozenset(p.name for p in ports_out), specs)
            self._scenes[key] = view
            self._by_ports.setdefault(view.out_names, view)
        return view

    def _use_scene(self, view: SceneView) -> None:
        """Make ``view`` the layout the core's ports and rows follow."""
        self._scene, self._layout, self._rows = view, view.layout, view.rows
        self._ports_in, self._ports_out = view.ports_in, view.ports_out
        self._materials_of: tuple | None = None

    def _activate(self, edits: Edits, *, carry: bool) -> None:
        old = self._compiled
        new = old if edits.structural() == old.edits else self._compiled_for(edits)
        view = self._scene_view(edits)  # (both may compile, and raise: nothing has changed yet)
        self._edits = edits
        self._apply_params(new)
        if new is not old:
            if carry:
                ms.carry_over(old, new)
                mujoco.mj_forward(new.model, new.data)
            self._use(new)
        elif carry:  # the same structure, other materials: the contacts of mj_step1 again
            mujoco.mj_step1(new.model, new.data)
        if view is not self._scene:  # bodies added or removed: other ports
            self._use_scene(view)
            self._attach()

    def _ports_of(self, edits: Edits) -> tuple[tuple[Port, ...], tuple[Port, ...]]:
        view = self._scene_view(edits)
        return view.ports_in, view.ports_out

    def _body_spec(self, body: str) -> BodySpec | None:
        return self._scene.specs.get(body)
