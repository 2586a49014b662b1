"""The Exudyn physics core: a scene of primitives (and flexible cables) simulated by Exudyn as a
dynabrain module, exchangeable with the MuJoCo core by one word (``core: exudyn``).

Choices (see also `exudyn.topology` and `exudyn.plan` for bodies, joints and welds, `exudyn.system`
and `exudyn.outputs` for the Exudyn system, `exudyn.contact` and `exudyn.calibrate` for contacts,
`exudyn.tree` for joint chains, `exudyn.cable` for flexible cables):

- a scene of primitives only (and meshes, as their convex hull: triangles and corner spheres in
  Exudyn's general contact, `exudyn.geometry`); a model file (MJCF), a joint chain under a free body
  and unknown shapes or joints are refused when the core is made, naming the feature and the core;
- hinges and slides are exact: chains hang from the world or a fixed body as Exudyn kinematic trees
  in minimal coordinates (their links do not touch one another; ``link_contacts: false`` drops
  their contact geometry altogether, three to four times cheaper for chains that touch nothing);
- explicit time integration with a fixed step, velocity Verlet by default (``integrator``): one
  force evaluation per step, second order for forces that depend on positions only (first order
  with damping), exact for a constant force, and a state that restores exactly (coordinates, their
  derivatives, the last accelerations, the data coordinates of limit stops); Exudyn's implicit
  solvers converge badly on penalty contact (tens of Newton iterations a step, about 50 times the
  cost) and keep Jacobians between steps;
- the engine step is ``period / substeps``; ``substeps: 0`` (the default) takes as many as keep the
  step at most ``max_step`` (0.5 ms) and below what every cable needs (`exudyn.cable.stable_step`);
- penalty contact scaled to each body's mass, its natural frequency ``contact_frequency`` (default
  ``CONTACT_PER_STEP / step``) and its damping from ``restitution`` (calibrated); friction
  regularised below ``friction_zone`` (default ``max(MIN_ZONE, ZONE_PER_STEP * friction * g *
  step)``, what an explicit step needs to stay stable when a box slides and spins on its corners;
  a wider zone calms impacts, a narrower one lets less creep on slopes);
- a joint's range is a limit stop as stiff as the contacts; a weld (`make_joint`) merges the two
  bodies into one rigid body, exactly; a hinge, slider or ball made at run time is a stiff,
  critically damped spring between the two carriers (`exudyn.joints`); the joint ports, parameter
  names and queries are MuJoCo's;
- `make` freezes the objects not selected onto the world carrier as static contact geometry; with
  ``others="absent"`` they stay there for their outputs (where they stood) but get no contact geometry,
  so nothing touches them and nothing is computed for them (`Plan.absent`);
- bodies added or removed (`add_body`, `remove_body`) make another topology with other ports (a
  `TopView` per `Edits.scene_key`, kept for the core's life; `bind` takes the one whose ports it is
  bound to); a body's own friction is a friction material of its own, its own restitution the damping
  of its contact spheres; changing their values changes parameters of the same system, giving a body
  its first one builds the system again (carried over, like an edit);
- the free bodies' inputs (`PhysicsCore`): a ``B.wrench`` becomes loads on the body's free carrier
  (its force on top of gravity's mass-proportional load, its torque, and the force's moment about the
  carrier's centre of mass, as a torque load), set again before a step only when they change; a
  ``B.velocity`` that holds a value sets the carrier's node velocities at the start of the step
  (`exudyn.inputs`). Velocity Verlet starts each step from the accelerations of the last, so a
  changed force or velocity is felt half an engine step late (a 1 N push on 1 kg for 0.1 s gives
  0.09975 m/s at the default 0.5 ms engine step; MuJoCo, 0.1);
- structural edits (`make`, `make_joint`, `no_collision`) build a new Exudyn system (welds merge
  rigid bodies exactly); systems are cached by their edits, so a rollback across an edit costs a
  dictionary look-up. The state is ``(edits, array)``: see `get_state`.

It writes no files (Exudyn's solution, sensor and restart files are off) and prints nothing unless
``verbose``.
"""

from __future__ import annotations

import copy
import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from dynabrain.orchestrator.kernel.core import (
    NO_EDITS,
    BodyInfo,
    BodySpec,
    Edits,
    SceneSpec,
    body_inputs,
    scene_bodies,
)
from dynabrain.orchestrator.kernel.edited import EditedCore
from dynabrain.orchestrator.kernel.errors import PhysicsDivergedError
from dynabrain.orchestrator.kernel.module import Param, Port, SetupContext
from dynabrain.orchestrator.kernel.suggest import did_you_mean

from . import cable as xc
from . import geometry as geo
from .calibrate import zeta_for
from .plan import FrozenObject, make_plan, to7
from .system import INTEGRATORS, Options, Start, System
from .topology import Topology, analyse, fail

CACHE_SIZE = 8
DEFAULT_PERIOD_S = 0.002
CONTACT_PER_STEP = 0.5
"""Contact natural frequency times engine step: a bounce lasts about 6 steps. Velocity Verlet is
stable below 2; measured bounces follow the restitution best here (drops of 0.1 to 1 m: within 2 %
for e = 0.3 and 0.8, against 8 % at 0.3 and 0.2, where the damper's switching on within a step and
gravity during the longer contact weigh more)."""
ZONE_PER_STEP = 4.0
"""Friction regularisation velocity per (friction * g * step)."""
MIN_ZONE = 0.01
"""Smallest default friction regularisation velocity (m/s): impacts make the friction force jitter by up
to friction * (impact force / mass) * step a step, and a wider zone calms it (at the price of creep)."""


@dataclass(frozen=True, eq=False)
class TopView:
    """The bodies of one scene key (`Edits.scene_key`: bodies added and removed at run time) as the core
    shows them: the topology, the rows of the bodies and the ports."""

    top: Topology
    rows: dict[str, int]
    ports_in: tuple[Port, ...]
    ports_out: tuple[Port, ...]
    out_names: frozenset[str]
    """The outputs' names: how `ExudynCore.bind` knows the topology of a binding."""


class ExudynCore(EditedCore):
    """A physics core on Exudyn. ``scene`` is primitives (no model files); see the module docstring."""

    ENGINE = "exudyn"
    PARAMS = (
        Param("friction", 1.0, runtime=True, doc="sliding friction coefficient of every body without its own"),
        Param("restitution", 0.0, runtime=True, doc="coefficient of restitution of contacts, 0..1"),
        Param("gravity", (0.0, 0.0, -9.81), unit="m/s^2", runtime=True, dimension="acceleration",
              doc="gravity vector"),
        Param("substeps", 0, runtime=True, doc="Exudyn steps per module step; 0: enough for max_step and cables"),
        Param("max_step", 5e-4, unit="s", dimension="time", doc="largest Exudyn step when substeps is 0"),
        Param("contact_frequency", 0.0, unit="rad/s", runtime=True,
              doc="natural frequency of a body on its contacts; 0: CONTACT_PER_STEP / step"),
        Param("friction_zone", 0.0, unit="m/s", runtime=True,
              doc="sliding speed below which friction is proportional to it; 0: from the step"),
        Param("integrator", "velocity_verlet", doc=f"explicit solver: {', '.join(INTEGRATORS)}"),
        Param("verbose", False, doc="let Exudyn print its messages"),
        Param("link_contacts", True, doc="links of joint chains touch things (off: 3-4 times cheaper chains)"),
    )

    MADE_JOINTS = ("weld", "hinge", "slider", "ball")

    def __init__(self, name: str, scene: SceneSpec, *, scenario_dir: str | None = None, **params: Any):
        super().__init__(name, scene, **params)
        for key, value in self.params.items():
            self._check_param(key, value)
        self._scenario_dir = scenario_dir
        self._period = DEFAULT_PERIOD_S
        self._tops: dict[tuple, TopView] = {}  # scene key -> its topology and ports (never dropped: see bind)
        self._by_ports: dict[frozenset[str], TopView] = {}  # the same, by the names of its outputs
        self._cache: OrderedDict[tuple, System] = OrderedDict()
        self._edits = NO_EDITS
        self._materials_of: tuple | None = None  # (key, `_own_materials`) of the last edits asked
        self._use_top(self._top_view(NO_EDITS))
        self._s = self._structure(NO_EDITS, Start())
        self._unbind()
        self._apply_params()
        self._write_all()

    def _top_view(self, edits: Edits) -> TopView:
        """The topology and ports of the bodies of ``edits`` (added and removed: `Edits.scene_key`),
        made once per scene key."""
        key = edits.scene_key()
        view = self._tops.get(key)
        if view is None:
            scene = self.scene if key == ((), ()) else SceneSpec(bodies=scene_bodies(self.scene, key),
                                                                 options=self.scene.options)
            top = analyse(self.name, scene)
            ports_in, ports_out = self._make_ports(top)
            view = TopView(top, {b: i for i, b in enumerate(top.bodies)}, ports_in, ports_out,
                           frozenset(p.name for p in ports_out))
            self._tops[key] = view
            self._by_ports.setdefault(view.out_names, view)
        return view

    def _use_top(self, view: TopView) -> None:
        """Make ``view`` the topology the core's ports, rows and output arrays follow."""
        self._view, self._top, self._rows = view, view.top, view.rows
        self._ports_in, self._ports_out = view.ports_in, view.ports_out
        self._init_state()

    def _init_state(self) -> None:
        n, nj = len(self._top.bodies), len(self._top.qjoints)
        self._bp, self._bq = np.zeros((n, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        self._bl, self._ba = np.zeros((n, 3)), np.zeros((n, 3))
        self._jq, self._jqd = np.zeros(nj), np.zeros(nj)

    # -- ports ------------------------------------------------------------------------------------------------
    @staticmethod
    def _make_ports(top: Topology) -> tuple[tuple[Port, ...], tuple[Port, ...]]:
        outs, ins = [], []
        for block, q, n, unit in (("body_pos", "pos", 3, "m"), ("body_quat", "quat", 4, "1"),
                                  ("body_linvel", "linvel", 3, "m/s"), ("body_angvel", "angvel", 3, "rad/s")):
            outs.append(Port(block, (len(top.bodies), n), unit, doc=f"{q} of every body"))
            outs += [Port(f"{b}.{q}", (n,), unit, view_of=(block, i)) for i, b in enumerate(top.bodies)]
        if top.qjoints:
            units = [top.qunit(j) for j in top.qjoints]
            uq, uf = (u[0] if len({x[k] for x in units}) == 1 else "1" for k, u in enumerate(zip(*units, strict=True)))
            outs += [Port("joint_q", (len(top.qjoints),), uq),
                     Port("joint_qd", (len(top.qjoints),), f"{uq}/s" if uq != "1" else "1")]
            ins.append(Port("joint_force", (len(top.qjoints),), uf))
            for i, (j, (q, f)) in enumerate(zip(top.qjoints, units, strict=True)):
                outs += [Port(f"{j}.q", (), q, view_of=("joint_q", i)),
                         Port(f"{j}.qd", (), f"{q}/s", view_of=("joint_qd", i))]
                ins.append(Port(f"{j}.force", (), f, view_of=("joint_force", i)))
        ins += body_inputs(top.free_bodies())
        for b in top.bodies:
            if top.role[b] == "cable":
                outs.append(Port(f"{b}.points", (top.spec[b].cable.segments + 1, 3), "m", doc="node positions"))
        return tuple(ins), tuple(outs)

    def _unbind(self) -> None:
        nj = len(self._top.qjoints)
        self._out: dict[str, np.ndarray] = {}
        self._points: list[tuple[str, np.ndarray]] = []
        self._force = np.zeros(nj)
        nf = len(self._top.free_bodies())
        self._wrench, self._vel = np.zeros(6 * nf), np.full(6 * nf, np.nan)
        self._no_wrench, self._vel_unset = self._wrench.tobytes(), self._vel.tobytes()  # bytes of inputs at rest

    def bind(self) -> None:
        """Take the ports of the binding: those of the current bodies, or (a rollback across an added or
        removed body) those of an earlier topology, which the state restored next goes with."""
        names = frozenset(self.out)
        if names and names != self._view.out_names:
            view = self._by_ports.get(names)
            if view is None:
                raise fail(self.name, f"bound to outputs of no body layout it has had ({len(names)} ports; it has "
                           f"{len(self._view.out_names)} now)")
            self._use_top(view)
        self._attach(names)

    def _attach(self, names: frozenset[str] | None = None) -> None:
        """Views on the bus when the binding holds the current topology's ports; otherwise (an edit that
        added or removed bodies, until the world binds the new ports) arrays of its own."""
        self._unbind()
        if self.out and (frozenset(self.out) if names is None else names) != self._view.out_names:
            return
        for key in ("body_pos", "body_quat", "body_linvel", "body_angvel", "joint_q", "joint_qd"):
            if self.out.get(key) is not None:
                self._out[key] = self.out[key]
        self._points = [(b, self.out[f"{b}.points"]) for b in self._top.bodies
                        if self._top.role[b] == "cable" and self.out.get(f"{b}.points") is not None]
        for attr, key in (("_force", "joint_force"), ("_wrench", "body_wrench"), ("_vel", "body_velocity")):
            if self.inp.get(key) is not None:
                setattr(self, attr, np.asarray(self.inp[key]).reshape(-1))

    # -- lifecycle --------------------------------------------------------------------------------------------
    def setup(self, ctx: SetupContext) -> None:
        self._period = ctx.period_ns * 1e-9
        self._cache.clear()  # built again for this period: its first accelerations come from its parameters
        self._s = self._structure(self._edits, Start())
        self._write_all()

    def step(self, t_ns: int, dt_ns: int) -> None:
        s = self._s
        if s.trees:
            s.set_forces(self._force)
        if s.pushing or self._wrench.tobytes() != self._no_wrench:
            s.push(self._wrench)
        if self._vel.tobytes() != self._vel_unset:  # a velocity input holds a value
            s.set_velocities(self._vel)
        try:
            s.step(t_ns * 1e-9, (t_ns + dt_ns) * 1e-9, self._nsub)
        except Exception as exc:  # Exudyn raises on a failed step (e.g. a contact search gone wild)
            raise PhysicsDivergedError(self.name, "step", None, f"Exudyn failed: {exc}") from None
        bad = s.diverged()
        if bad is not None:
            raise PhysicsDivergedError(self.name, "step", None, f"{bad} became NaN, infinite or larger than 1e10; "
                                       "check the inputs, or reduce forces or the step (substeps)")
        self._write_outputs()

    def get_state(self) -> tuple:
        """``(edits, coordinates | velocities | accelerations | data coordinates)``: the structure and
        everything Exudyn's explicit solver carries from one step to the next."""
        return (self._edits, self._s.get_state())

    def set_state(self, state: tuple) -> None:
        edits, arr = state
        if edits is not self._edits and edits != self._edits:
            self._activate(edits, carry=False)
        self._s.set_state(np.asarray(arr, dtype=np.float64))
        self._write_all()

    def on_param(self, name: str, value: Any) -> None:
        self._check_param(name, value)
        self._apply_params()

    def close(self) -> None:
        self._cache.clear()

    def fork(self, memo: dict) -> ExudynCore:
        """An independent copy (`World.fork`): its own Exudyn system, built again from the same scene
        and edits (building is deterministic) and set to the same state; unbound."""
        twin = copy.copy(self)
        memo[id(self)] = twin
        twin.bind_ports(None)
        twin._unbind()
        for attr in ("_bp", "_bq", "_bl", "_ba", "_jq", "_jqd"):
            setattr(twin, attr, getattr(self, attr).copy())
        twin._cache = OrderedDict()
        twin._s = twin._structure(self._edits, Start())
        twin._apply_params()
        twin._s.set_state(self._s.get_state())
        twin._write_all()
        return twin

    # -- parameters -------------------------------------------------------------------------------------------
    def _check_param(self, name: str, value: Any) -> None:
        bad = {"friction": lambda v: v < 0, "restitution": lambda v: not 0 <= v <= 1,
               "substeps": lambda v: v < 0, "gravity": lambda v: not np.all(np.isfinite(v)),
               "max_step": lambda v: not v > 0, "contact_frequency": lambda v: not v >= 0,
               "friction_zone": lambda v: not v >= 0, "integrator": lambda v: v not in INTEGRATORS}
        if name in bad and bad[name](value):
            extra = did_you_mean(str(value), INTEGRATORS) if name == "integrator" else ""
            raise fail(self.name, f"parameter {name} = {value!r} is out of range" + extra)

    @property
    def engine_step(self) -> float:
        """The Exudyn step (s) in use: the module period over the substeps."""
        return self._period / self._nsub

    def _substeps(self) -> int:
        p = self.params
        if p["substeps"]:
            return int(p["substeps"])
        limit = float(p["max_step"])
        for b in self._top.bodies:
            if self._top.role[b] == "cable":
                limit = min(limit, xc.stable_step(self._top.spec[b]))
        return max(1, math.ceil(self._period / limit - 1e-9))

    def contact_settings(self) -> dict[str, float]:
        """The contact parameters in use: wn (rad/s), zeta, friction_zone (m/s), step (s)."""
        p = self.params
        h = self._period / self._nsub
        g = float(np.linalg.norm(p["gravity"]))
        mu = max([float(p["friction"])] + [f or 0.0 for f, _e in self._own_materials(self._edits).values()])
        zone = float(p["friction_zone"]) or max(MIN_ZONE, ZONE_PER_STEP * mu * g * h)
        wn = float(p["contact_frequency"]) or CONTACT_PER_STEP / h
        zeta = zeta_for(float(p["restitution"]), h, wn, g, str(p["integrator"]))
        return {"wn": wn, "zeta": zeta, "friction_zone": zone, "step": h}

    def _settings(self) -> dict:
        """What `System.apply` takes, from the parameters (and the bodies' own materials)."""
        self._nsub = self._substeps()
        c = self.contact_settings()
        p = self.params
        g = float(np.linalg.norm(p["gravity"]))
        own = {b: (f, None if e is None else zeta_for(float(e), c["step"], c["wn"], g, str(p["integrator"])))
               for b, (f, e) in self._own_materials(self._edits).items()}
        return {"gravity": np.asarray(p["gravity"], dtype=float), "wn": c["wn"], "zeta": c["zeta"],
                "friction_zone": c["friction_zone"], "friction": float(p["friction"]), "step": c["step"], "own": own}

    def _own_materials(self, edits: Edits) -> dict[str, tuple[float | None, float | None]]:
        """Body -> its own (friction, restitution), for the bodies that have one: the scene's and the
        added bodies' values, and those set at run time (`set_material`)."""
        key = (edits.scene_key(), edits.materials)
        hit = self._materials_of
        if hit is not None and hit[0] == key:
            return hit[1]
        top = self._top_view(edits).top
        own = {n: (b.friction, b.restitution) for n, b in top.spec.items()
               if b.friction is not None or b.restitution is not None}
        for mat in edits.materials:
            own[mat.body] = (mat.friction, mat.restitution)
        own = {b: v for b, v in own.items() if v != (None, None)}
        self._materials_of = (key, own)
        return own

    def _apply_params(self) -> None:
        settings = self._settings()
        if settings["wn"] != self._s.wn:  # triangle stiffness is fixed when a system is built
            self._activate(self._edits, carry=True)
        else:
            self._s.apply(**settings)

    # -- outputs ----------------------------------------------------------------------------------------------
    def _write_outputs(self) -> None:
        self._s.write(self._bp, self._bq, self._bl, self._ba, self._jq, self._jqd)
        self._publish()

    def _write_all(self) -> None:
        self._s.write_static(self._bp, self._bq, self._bl, self._ba, self._jq, self._jqd)
        self._write_outputs()

    def _publish(self) -> None:
        out = self._out
        for key, src in (("body_pos", self._bp), ("body_quat", self._bq), ("body_linvel", self._bl),
                         ("body_angvel", self._ba), ("joint_q", self._jq), ("joint_qd", self._jqd)):
            if key in out:
                out[key][...] = src
        for name, array in self._points:
            array[...] = self._s.cable_coords(name)[0][:, :3]

    # -- scene queries ----------------------------------------------------------------------------------------
    @property
    def _index(self) -> Any:
        return self._top

    def body_info(self, name: str) -> BodyInfo:
        row, top = self._row(name), self._top
        b = top.spec[name]
        size = tuple(float(x) for x in b.size)
        geom = {"name": name, "type": b.shape, "size": size, "rgba": tuple(float(x) for x in b.color),
                "pos": (0.0, 0.0, 0.0), "quat": (1.0, 0.0, 0.0, 0.0)}
        if b.cable is not None:
            geom["points"] = self._s.cable_coords(name)[0][:, :3].tolist()
        return BodyInfo(name=name, free=name in top.free, parent=top.parents[row], geoms=(geom,))

    def body_pose(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        row = self._row(name)
        return self._bp[row].copy(), self._bq[row].copy()

    def body_velocity(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        row = self._row(name)
        return self._bl[row].copy(), self._ba[row].copy()

    def cable_points(self, name: str) -> np.ndarray:
        """Node positions (n+1, 3) of a cable, now."""
        self._row(name)
        if self._top.role[name] != "cable":
            raise fail(self.name, f"{name!r} is not a cable")
        return self._s.cable_coords(name)[0][:, :3].copy()

    # -- structural edits --------------------------------------------------------------------------------------
    def _freeze_entry(self, obj: str) -> FrozenObject:
        """Where the bodies, joints and cables of ``obj`` stand now."""
        top = self._top
        bodies, joints, cables = [], [], []
        for b in top.subtree[obj]:
            row = self._rows[b]
            bodies.append((b, to7((self._bp[row], self._bq[row]))))
            if top.role[b] == "link":
                j = top.joint_of[b]
                joints.append((j, float(self._jq[top.qjoints.index(j)])))
            if top.role[b] == "cable":
                cables.append((b, tuple(map(float, self._s.cable_coords(b)[0].reshape(-1)))))
        return FrozenObject(obj, tuple(bodies), tuple(joints), tuple(cables))

    def _weld_data(self, a: str, b: str) -> tuple:
        return to7(geo.compose(geo.inverse(self.body_pose(a)), self.body_pose(b)))

    def _parent(self, body: str) -> str | None:
        return self._top.spec[body].parent

    def _reserved_joint_names(self) -> set[str]:
        return set(self._top.joints) | set(self._top.bodies)

    def _ports_of(self, edits: Edits) -> tuple[tuple[Port, ...], tuple[Port, ...]]:
        view = self._top_view(edits)
        return view.ports_in, view.ports_out

    def _body_spec(self, body: str) -> BodySpec | None:
        return self._top.spec.get(body)

    def place(self, body: str, pos: Sequence[float], quat: Sequence[float] | None = None) -> None:
        row = self._row(body)
        if body not in self._top.free:
            raise fail(self.name, f"body {body!r} has no free joint; place moves free bodies")
        frame = self._s.frames[body]
        if frame.kind != "free":
            raise fail(self.name, f"body {body!r} is frozen or welded to something static; select its object "
                       "with make() first")
        p = np.asarray(pos, dtype=np.float64)
        q = np.asarray(self._bq[row] if quat is None else quat, dtype=np.float64)
        if p.shape != (3,) or q.shape != (4,) or not (np.all(np.isfinite(p)) and np.linalg.norm(q) > 0):
            raise fail(self.name, f"place({body!r}): pos must be 3 numbers and quat 4 (w, x, y, z), not 0")
        self._s.place(body, geo.pose(p, q))
        self._write_all()

    # -- structures -------------------------------------------------------------------------------------------
    def _structure(self, edits: Edits, start: Start) -> System:
        """The system of ``edits`` (its structure and which bodies have materials of their own; their values
        are parameters), from the cache or built now, starting at ``start``."""
        settings = self._settings()
        key = self._key(edits, settings["wn"])
        s = self._cache.get(key)
        if s is None:
            top = self._top_view(edits).top
            plan = make_plan(top, edits)
            p = self.params
            options = Options(str(p["integrator"]), bool(p["verbose"]), bool(p["link_contacts"]))
            s = System(top, plan, key[0], start, options, settings, key[1])
        self._cache[key] = s
        self._cache.move_to_end(key)
        while len(self._cache) > CACHE_SIZE:
            self._cache.popitem(last=False)
        return s

    def _start_now(self) -> Start:
        """The present, as a start for another structure: body poses and velocities, joints, cables."""
        top = self._top
        start = Start()
        for row, b in enumerate(top.bodies):
            start.pose[b] = (self._bp[row].copy(), self._bq[row].copy())
            start.vel[b] = (self._bl[row].copy(), self._ba[row].copy())
            if top.role[b] == "cable":
                start.cables[b] = tuple(x.reshape(-1) for x in self._s.cable_coords(b))
        for i, j in enumerate(top.qjoints):
            start.q[j], start.qd[j] = float(self._jq[i]), float(self._jqd[i])
        return start

    def _key(self, edits: Edits, wn: float) -> tuple:
        """What a system is built for: the structure, the bodies with materials of their own, the contact
        frequency."""
        return (edits.structural(), frozenset(self._own_materials(edits)), wn)

    def _activate(self, edits: Edits, *, carry: bool) -> None:
        old = self._edits
        if edits.structural() == old.structural() and self._key(edits, self._s.wn)[1] == self._s.own:
            self._edits = edits  # other materials only: parameters of the same system
            self._s.apply(**self._settings())
            return
        view = self._top_view(edits)
        if carry:
            start = self._start_now()
            self._edits = edits  # (the key: its materials)
            self._cache.pop(self._key(edits, self._settings()["wn"]), None)  # a cached one would start where it was
        else:
            start = Start()
            self._edits = edits
        try:
            new = self._structure(edits, start)
        except BaseException:
            self._edits = old
            raise
        if view is not self._view:  # bodies added or removed: other ports
            self._use_top(view)
            self._attach()
        self._s = new
        self._s.apply(**self._settings())
