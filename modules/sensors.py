"""Sensors on the MuJoCo core: 6-axis force, acceleration, gyro, and joint encoders.

Every sensor is declared the same way (after dm_control's observables): it *samples* a native
quantity of the physics core, holds the samples for a ``delay``, and adds white Gaussian noise from
its own seeded generator.

- **rate**: the module's period (``period: 200Hz`` or ``period: 5ms`` in a scenario); between two
  samples the outputs hold their value;
- **delay**: the latency of a reading, a whole number of the sensor's periods (else refused at
  load); until the delay has passed, the sensor reads the value it had when it started;
- **noise**: standard deviation of the noise, in the unit of the output (run-time settable); the
  generator's state is part of the sensor's state, so a rollback replays the same noise.

What each sensor reads is MuJoCo's native sensor on a site of the model (force, torque,
accelerometer, gyro) or the joint positions and velocities (encoders), through `MujocoLink` (see
there when a reading is taken). Frames are the site's: a foot's force sensor at its ankle site
reads in the foot's frame.

Ports (outputs):

=================  ====================  ==========================================================
module             port                  meaning
=================  ====================  ==========================================================
`ForceSensor`      ``force`` (3, N)      force between the site's body and its parent (MuJoCo's
                                         ``force`` sensor: at rest under a standing robot's foot,
                                         z is minus the weight the foot carries)
                   ``torque`` (3, N*m)   torque about the site (MuJoCo's ``torque`` sensor)
`Accelerometer`    ``acc`` (3, m/s^2)    proper acceleration at the site (reads +g up at rest)
`Gyro`             ``angvel`` (3, rad/s) angular velocity of the site's body, in the site frame
`Encoders`         ``q``, ``qd`` (n)     joint positions (rad, m) and velocities; a view port
                                         ``<joint>.q`` / ``<joint>.qd`` per joint
=================  ====================  ==========================================================

Targets: one site for the site sensors (``targets: [l_foot_ft]``); joint names or glob patterns for
the encoders (default: every joint with a motor, in the order of the core's ``ctrl``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.module import Module, Param, Port, SetupContext
from dynabrain.orchestrator.kernel.structure import Copies

from .mujoco.access import MujocoLink, contiguous, fail

_SENS = mujoco.mjtSensor


@dataclass(frozen=True)
class Channel:
    """One output of a sensor: port name, size, unit, and the parameter holding its noise level."""

    port: str
    size: int
    unit: str
    noise: str
    doc: str = ""


def _noise(name: str, unit: str) -> Param:
    return Param(name, 0.0, unit=unit, runtime=True, doc=f"standard deviation of white noise ({unit})")


DELAY = Param("delay", 0.0, unit="s", dimension="time",
              doc="latency of a reading, a whole number of the sensor's periods")


class Sensor(Module):
    """Base of the sensors: sample -> delay line -> noise -> outputs. A subclass gives `channels` and
    `_resolve`, which finds, in the core's current model, the array and the indices each channel
    reads (re-run when the core switches structure). Without delay and noise, a step copies them
    straight to the outputs."""

    PARAMS: ClassVar[tuple[Param, ...]] = (DELAY,)
    _fused_in: FusedSensors | None = None
    """The group this sensor steps in (`Sensor.fuse`), whose plan drops when this sensor plans again."""

    def channels(self) -> tuple[Channel, ...]:
        raise NotImplementedError

    def outputs(self) -> list[Port]:
        return [Port(c.port, (c.size,), c.unit, c.doc) for c in self.channels()]

    # -- lifecycle ------------------------------------------------------------------------------------
    def setup(self, ctx: SetupContext) -> None:
        self._link = MujocoLink(self.name, ctx.core)
        self._prepare()
        delay_ns = round(self.params["delay"] * 1e9)
        if delay_ns < 0 or delay_ns % ctx.period_ns:
            raise fail(self.name, "params.delay", f"delay {delay_ns / 1e9:g} s is not a whole number of the "
                       f"sensor's period ({ctx.period_ns / 1e9:g} s)")
        self._depth = delay_ns // ctx.period_ns + 1
        self._size = sum(c.size for c in self.channels())
        self._ring = np.zeros((self._depth, self._size))
        self._head = 0
        self._rng = ctx.rng
        self._rng_state = self._rng.bit_generator.state
        self._rng_dirty = False
        self._saved: tuple | None = None
        self._sigma = self._sigmas()
        self._link.changed()
        self._resolve()

    def bind(self) -> None:
        cuts = np.cumsum([0] + [c.size for c in self.channels()])
        self._writes = [(self.out[c.port], slice(int(a), int(b))) for c, a, b in
                        zip(self.channels(), cuts[:-1], cuts[1:], strict=True) if c.port in self.out]
        self._plan()

    def _plan(self) -> None:
        """The fast path (no delay, no noise): each output copied straight from the core's data, as a
        memoryview copy for a contiguous run of the data (a third of the cost of a numpy copy), else
        by an index array."""
        if self._fused_in is not None:  # the sensors stepped with this one copy by the plans they had
            self._fused_in.plan = None
        ready = hasattr(self, "_sources") and hasattr(self, "_writes")
        self._views, self._gathers = [], []
        for (port, _cut), (source, index) in zip(self._writes, self._sources, strict=True) if ready else ():
            run = contiguous(index)
            if isinstance(run, slice):
                self._views.append((memoryview(port), memoryview(source[run])))
            else:
                self._gathers.append((port, source, run))
        self._fast = ready and self._depth == 1 and self._sigma is None

    def __getstate__(self) -> dict[str, Any]:
        """For a fork's deep copy: memoryviews do not copy; the copy plans its fast path again when it
        is bound (and when it first steps, on its own core)."""
        state = dict(self.__dict__)
        state.update(_views=[], _gathers=[], _fast=False, _fused_in=None)
        return state

    @classmethod
    def fuse(cls, members: Sequence[Module], copies: Sequence[Copies]) -> FusedSensors | None:
        """Sensors next to each other in the schedule (any of this file's, due at the same ticks) step
        as one call while they all take the fast path: their copies, in schedule order."""
        if (len(members) < 2 or any(copies)  # (a sensor that takes inputs steps on its own)
                or any(not isinstance(m, Sensor) or type(m).step is not Sensor.step for m in members)):
            return None
        return FusedSensors(members)  # type: ignore[arg-type]

    def start(self, t_ns: int) -> None:
        if self._link.changed():
            self._resolve()
            self._plan()
        self._ring[:] = self._sample()
        self._emit(self._ring[0])

    def step(self, t_ns: int, dt_ns: int) -> None:
        link = self._link
        if link.core.mj is not link.seen:  # the core switched model: find the ids again
            link.changed()
            self._resolve()
            self._plan()
        if self._fast:  # the common case: the native values straight to the outputs
            for dst, src in self._views:
                dst[:] = src
            for port, source, index in self._gathers:
                port[...] = source[index]
            return
        raw = self._sample()
        if self._depth == 1:
            self._emit(raw)
            return
        self._ring[self._head] = raw
        self._head = (self._head + 1) % self._depth
        self._emit(self._ring[self._head])

    def _emit(self, value: np.ndarray) -> None:
        if self._sigma is not None:
            value = value + self._rng.normal(0.0, self._sigma)
            self._rng_dirty = True
        for port, cut in self._writes:
            port[...] = value[cut]

    # -- state ----------------------------------------------------------------------------------------
    def get_state(self) -> tuple:
        if self._rng_dirty:
            self._rng_state = self._rng.bit_generator.state
            self._rng_dirty = False
            self._saved = None
        if self._depth > 1:
            return (self._ring.copy(), self._head, self._rng_state)
        if self._saved is None:  # no delay line: the same state until the noise draws again
            self._saved = (None, self._head, self._rng_state)
        return self._saved

    def steps_change_state(self) -> bool:
        return self._depth > 1 or self._sigma is not None  # a delay line, or noise drawn

    def set_state(self, state: tuple) -> None:
        self._saved = None
        ring, head, rng_state = state
        if ring is not None:
            self._ring[...] = ring
        self._head = head
        if self._rng_dirty or rng_state is not self._rng_state:
            self._rng.bit_generator.state = rng_state
            self._rng_state = rng_state
            self._rng_dirty = False

    def set_param(self, name: str, value: Any, *, running: bool = True) -> None:
        spec = self.param_specs().get(name)
        if spec is not None and name in {c.noise for c in self.channels()}:
            level = spec.convert(value)  # refuse a bad value before it becomes the parameter's value
            if not level >= 0:
                raise fail(self.name, f"params.{name}", f"must be zero or positive, got {level!r}")
        super().set_param(name, value, running=running)

    def on_param(self, name: str, value: Any) -> None:
        if hasattr(self, "_size"):
            self._sigma = self._sigmas()
            self._plan()

    def _sigmas(self) -> np.ndarray | None:
        for c in self.channels():
            if not self.params[c.noise] >= 0:
                raise fail(self.name, f"params.{c.noise}", f"must be zero or positive, got {self.params[c.noise]!r}")
        parts = [np.full(c.size, float(self.params[c.noise])) for c in self.channels()]
        sigma = np.concatenate(parts) if parts else np.zeros(0)
        return sigma if np.any(sigma > 0) else None

    # -- for subclasses -------------------------------------------------------------------------------
    def _prepare(self) -> None:
        """Resolve the targets (before the channels are needed); ``self._link`` is set."""

    def _site(self) -> str:
        if len(self.targets) != 1:
            raise fail(self.name, "targets", f"a {type(self).__name__} takes one site: targets: [site], "
                       f"got {list(self.targets)}")
        return self.targets[0]

    def _resolve(self) -> None:
        """Set ``self._sources``: per channel, (array of the core's data, indices into it)."""
        raise NotImplementedError

    def _sample(self) -> np.ndarray:
        return np.concatenate([source[index] for source, index in self._sources])


class FusedSensors:
    """Sensors stepped as one (`Sensor.fuse`): while each of them takes its fast path (no delay, no
    noise, ids resolved against the core's current model), one call makes all their copies in schedule
    order, the same copies as their steps (so the same bits); otherwise each steps on its own, and the
    copies are planned again after. A sensor that plans again (a noise level set, a new binding, the
    core on another model) drops the plan. Four sensors of the humanoid: 0.35 us a tick against 0.83
    for their four steps (`bench/humanoid.py`)."""

    def __init__(self, members: Sequence[Sensor]):
        self.members = tuple(members)
        self.failing: str | None = None
        self.plan: tuple | None = None  # (the core's view, the core, the memoryview copies, the index
        # copies); () while a member is off its fast path; None: to be made after the members' next steps
        for m in self.members:
            m._fused_in = self

    def bind(self, buf: np.ndarray) -> Callable[[int, int], None]:
        self.plan = None  # the members bind after the tick is made: plan at the first call

        def step(t_ns: int, period_ns: int) -> None:
            plan = self.plan
            if not plan or plan[1].mj is not plan[0]:  # (the core on another model)
                self._one_by_one(t_ns, period_ns)
                return
            for dst, src in plan[2]:
                dst[:] = src
            for port, source, index in plan[3]:
                port[...] = source[index]

        return step

    def _one_by_one(self, t_ns: int, period_ns: int) -> None:
        for m in self.members:
            self.failing = m.name
            m.step(t_ns, period_ns)
        self.failing = None
        if self.plan is not None:  # () until a member plans again: one is off its fast path
            return
        members = self.members
        core = members[0]._link.core
        view = core.mj
        if all(m._fast and m._link.core is core and m._link.seen is view for m in members):
            self.plan = (view, core, tuple(c for m in members for c in m._views),
                         tuple(g for m in members for g in m._gathers))
        else:
            self.plan = ()


class _NativeSiteSensor(Sensor):
    """A sensor made of MuJoCo native sensors on one site (``KINDS``: (sensor type, MJCF tag) per channel)."""

    KINDS: ClassVar[tuple[tuple[mujoco.mjtSensor, str], ...]] = ()

    def _resolve(self) -> None:
        site, data = self._site(), self._link.data.sensordata
        self._sources = [(data, self._link.native_sensor(site, kind, tag)) for kind, tag in self.KINDS]


class ForceSensor(_NativeSiteSensor):
    """A 6-axis force/torque sensor on a site (MuJoCo's ``force`` and ``torque`` sensors there)."""

    PARAMS = (DELAY, _noise("noise", "N"), _noise("torque_noise", "N*m"))
    KINDS = ((_SENS.mjSENS_FORCE, "force"), (_SENS.mjSENS_TORQUE, "torque"))
    _CHANNELS = (Channel("force", 3, "N", "noise", "force on the site's body from its parent, site frame"),
                 Channel("torque", 3, "N*m", "torque_noise", "torque about the site, site frame"))

    def channels(self) -> tuple[Channel, ...]:
        return self._CHANNELS


class Accelerometer(_NativeSiteSensor):
    """A 3-axis accelerometer on a site: proper acceleration, +g upward at rest (MuJoCo's ``accelerometer``)."""

    PARAMS = (DELAY, _noise("noise", "m/s^2"))
    KINDS = ((_SENS.mjSENS_ACCELEROMETER, "accelerometer"),)
    _CHANNELS = (Channel("acc", 3, "m/s^2", "noise", "proper acceleration, site frame"),)

    def channels(self) -> tuple[Channel, ...]:
        return self._CHANNELS


class Gyro(_NativeSiteSensor):
    """A 3-axis gyro on a site: angular velocity in the site frame (MuJoCo's ``gyro``)."""

    PARAMS = (DELAY, _noise("noise", "rad/s"))
    KINDS = ((_SENS.mjSENS_GYRO, "gyro"),)
    _CHANNELS = (Channel("angvel", 3, "rad/s", "noise", "angular velocity, site frame"),)

    def channels(self) -> tuple[Channel, ...]:
        return self._CHANNELS


class Encoders(Sensor):
    """Joint encoders: positions and velocities of hinge/slide joints (targets: names or patterns;
    default: every joint with a motor, in the core's actuator order)."""

    PARAMS = (DELAY, _noise("noise", "rad"), _noise("velocity_noise", "rad/s"))

    def __init__(self, name: str, **kwargs: Any):
        super().__init__(name, **kwargs)
        self._joints: list[str] = [t for t in self.targets if not any(ch in t for ch in "*?[")]
        self._unit = "rad"

    @property
    def joints(self) -> list[str]:
        """The joints read, in output order (known after setup when targets are patterns or empty)."""
        return list(self._joints)

    def _prepare(self) -> None:
        link = self._link
        self._joints = link.expand_joints(self.targets)
        m = link.model
        kinds = {int(m.jnt_type[link.lookup("joint", j)]) for j in self._joints}
        self._unit = "m" if kinds == {int(mujoco.mjtJoint.mjJNT_SLIDE)} else ("rad" if len(kinds) == 1 else "1")

    def channels(self) -> tuple[Channel, ...]:
        n, u = len(self._joints), self._unit
        return (Channel("q", n, u, "noise", "joint positions"),
                Channel("qd", n, f"{u}/s" if u != "1" else "1", "velocity_noise", "joint velocities"))

    def outputs(self) -> list[Port]:
        ports = super().outputs()
        unit_q, unit_qd = ports[0].unit, ports[1].unit
        for i, j in enumerate(self._joints):
            ports += [Port(f"{j}.q", (), unit_q, view_of=("q", i)), Port(f"{j}.qd", (), unit_qd, view_of=("qd", i))]
        return ports

    def _resolve(self) -> None:
        qadr, dadr = self._link.joint_addresses(self._joints)
        self._sources = [(self._link.data.qpos, qadr), (self._link.data.qvel, dadr)]
