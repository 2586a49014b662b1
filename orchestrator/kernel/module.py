"""The module contract: every simulation function is a Module.

A module keeps configuration and code; everything that changes while the world runs is *state*
that it can hand out (`get_state`) and take back (`set_state`). The world owns time, the signal bus
and history; a module only ever sees one step at a time.

Lifecycle (the order the world calls a module in; `check_module` verifies it)::

    m = MyModule("name", **params)     # 1. configuration only: parse and check params, no resources
    m.inputs(), m.outputs()            # 2. declared ports (may depend on the params, and on the scene
                                       #    once setup has run, for physics cores)
    m.setup(ctx)                       # 3. once, when the module joins a world: resolve targets
                                       #    against the scene, allocate resources, take ctx.rng
    m.bind_ports(binding)              # 4. the world gives the module its ports on the bus (a
    m.bind()                           #    `PortBinding`: m.inp / m.out / m.inp_flat / m.out_flat),
                                       #    then calls `bind`; again whenever the world's structure
                                       #    changes (the bus is laid out anew)
    m.start(t_ns)                      # 5. initial state at the tick the module joins; writes initial
                                       #    values of every output port
    loop, at ticks where the module is due (every `period` of its own):
        m.step(t_ns, dt_ns)            # 6. advance state from t_ns to t_ns + dt_ns: read m.inp[...],
                                       #    write m.out[...] in place (`m.out["y"][...] = v`); or all
                                       #    ports at once: m.inp_flat, m.out_flat (declaration order)
        m.get_state()                  # 7. after each tick, for history (only when can_rollback;
                                       #    once per stretch when m.steps_change_state() is False)
    m.set_state(s)                     #    on rollback / restore, between steps, any number of times
    m.on_param(name, value)            #    a run-time parameter changed (also when a rollback changes
                                       #    it back); apply it to whatever depends on it
    m.close()                          # 8. once, when the world closes (a removed module stays alive
                                       #    while history may bring it back)

Fork: `World.fork` unbinds every module (``bind_ports(None)``), asks each for its copy (`Module.fork`,
with one shared memo, so a sensor holding the core gets the copied core), binds the originals again
and binds the copies to the new world. The copies share their originals' parameter values
(`ParamValues`: a change replaces them, never edits them, as history relies on too). A module holding
foreign resources (an engine handle, an FMU instance) overrides `fork` to copy them properly, or
declares ``can_fork=False``; one holding what never changes (a compiled model, a table) may share it
with its copy rather than copy it.

Optional hooks are methods of this class with a documented default (`scenario_spec`,
`steps_change_state`, ...; a physics core has more, see `PhysicsCore`): the kernel calls them
directly, never looks them up by name.

Failure policy: an exception from `setup` or `start` refuses the module (the world is unchanged);
an exception from `step` (or a `PhysicsDivergedError`) rolls the whole world back to the state at
the start of the failed tick and is re-raised as `ModuleError` naming the module, call and tick; so
does an output left NaN or infinite (`NonFiniteOutputError`), unless the module declares
``Capabilities(finite_outputs=False)``.
`get_state` must return a value the module will never mutate afterwards (copy arrays); `set_state`
must copy what it keeps. Randomness comes from `ctx.rng` and its state belongs in `get_state`.
"""

from __future__ import annotations

import copy
import functools
import math
from abc import ABCMeta
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np

from .errors import DynabrainError, UnitError
from .portable import state_type
from .suggest import did_you_mean
from .units import parse_quantity

if TYPE_CHECKING:
    from .core import PhysicsCore
    from .structure import Copies


@state_type
class ParamValues(dict):
    """A module's parameter values (`Module.params`): a dict that cannot be changed. A change makes a
    new one (`Module.set_param`), so history, forks and the module's own caches may keep and share it,
    and may tell a change by identity (``params is not kept``). Lookups cost what a dict's cost."""

    __slots__ = ()

    def _refuse(self, *_args: Any, **_kw: Any) -> None:
        raise TypeError("a module's parameters are read-only here; change one with World.set (module.param)")

    __setitem__ = __delitem__ = clear = pop = popitem = setdefault = update = __ior__ = _refuse  # type: ignore

    def __reduce__(self) -> tuple:
        return ParamValues, (dict(self),)

    def __copy__(self) -> ParamValues:
        return self

    def __deepcopy__(self, memo: dict[int, Any]) -> ParamValues:
        return self  # never changed in place: a copy is the same values


NO_PORTS = np.zeros(0)  # what `Module.inp_flat` and `out_flat` are while a module is not bound
NO_PORTS.setflags(write=False)


@dataclass(frozen=True)
class Port:
    """A named, typed slot on the signal bus. Values are float64 arrays of ``shape``.

    ``view_of`` makes this port a view into a block port of the same module:
    ``("body_pos", 3)`` is row 3 of ``body_pos`` (n, 3); of a one-dimensional block it is the run of
    ``size`` elements from element 3 (``("sensordata", 3)`` with shape (3,): elements 3 to 5). Block
    ports let a module write many values with one array operation while each still has a name of
    its own.
    """

    name: str
    shape: tuple[int, ...] = ()
    unit: str = "1"
    doc: str = ""
    view_of: tuple[str, int] | None = None
    start: float | tuple[float, ...] | None = None
    """The value the bus slot holds when the port appears (default 0): an input nothing drives yet
    reads it (an FMU input's start value, a servo's neutral target)."""

    @functools.cached_property
    def size(self) -> int:
        """The number of values (the product of ``shape``; 1 for a scalar), worked out once per port:
        laying out a bus asks it of every port."""
        return int(math.prod(self.shape))


@dataclass(frozen=True)
class Param:
    """A parameter: default value, unit, and whether it may be changed while the world runs.

    ``dimension`` (``"time"``, ``"frequency"``, ``"mass"``, ``"length"``, ...) lets a scenario
    write the value with a unit (``2Hz``, ``50g``); it is converted to SI.
    """

    name: str
    default: Any
    unit: str = "1"
    runtime: bool = False
    doc: str = ""
    dimension: str | None = None

    def convert(self, value: Any) -> Any:
        """Turn a scenario value into the parameter's type, in SI units. A number must be finite (the
        declared default excepted: a module author's choice)."""
        try:
            out = self._convert(value)
        except OverflowError:
            raise UnitError(f"expected a finite number, got {value!r} (too large)") from None
        numeric = isinstance(out, float) or (isinstance(out, np.ndarray) and out.dtype.kind == "f")
        if numeric and value is not self.default and not np.all(np.isfinite(out)):
            raise UnitError(f"expected a finite number, got {value!r}")
        return out

    def _convert(self, value: Any) -> Any:
        default = self.default
        if self.dimension is not None and isinstance(value, str):
            return parse_quantity(value, self.dimension)
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise UnitError(f"expected true or false, got {value!r}")
            return value
        if isinstance(default, int) and not isinstance(default, bool):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or int(value) != value:
                raise UnitError(f"expected an integer, got {value!r}")
            return int(value)
        if isinstance(default, float):
            if isinstance(value, str):
                return parse_quantity(value)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise UnitError(f"expected a number, got {value!r}")
            return float(value)
        if isinstance(default, (tuple, list, np.ndarray)):
            try:
                items = [parse_quantity(v, self.dimension) if isinstance(v, str) else v for v in value]
                arr = np.asarray(items, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise UnitError(f"expected a list of numbers, got {value!r}") from exc
            expected = np.shape(default)
            if expected and len(expected) == 1 and expected[0] and arr.shape != expected:
                raise UnitError(f"expected {expected[0]} numbers, got shape {arr.shape}")
            arr.setflags(write=False)
            return arr
        if isinstance(default, str) and not isinstance(value, str):
            raise UnitError(f"expected a string, got {value!r}")
        return value


@dataclass(frozen=True)
class Capabilities:
    """What a module can do.

    - ``can_rollback``: its state can be saved and restored exactly (history, backtick, snapshot).
    - ``can_fork``: it can be copied into an independent world (`World.fork`).
    - ``feedthrough``: its outputs after a step depend on the inputs of that step. A module whose
      outputs depend on its state only (a physics core, an integrator) is not feedthrough; the
      schedule lets its consumers read its outputs before it steps, which breaks feedback loops.
    - ``finite_outputs``: the world checks that its outputs are finite numbers after every tick; one
      that holds NaN or an infinity fails the tick (rolled back, `NonFiniteOutputError` naming module,
      port and tick). False for a module whose outputs mean something by NaN or an infinity (a ZMP
      sensor with no foot on the ground, a meter before its first reading), or one that checks its
      own and raises `NonFiniteOutputError` itself (an FMU, as it reads them): the world does not
      look. A single module opts out with
      ``module.CAPABILITIES = dataclasses.replace(module.CAPABILITIES, finite_outputs=False)``.
    """

    can_rollback: bool = True
    can_fork: bool = True
    feedthrough: bool = True
    finite_outputs: bool = True


@dataclass
class SetupContext:
    """What a module gets from the world when it joins it."""

    world_name: str
    dt_ns: int
    """The world's base step in nanoseconds."""
    period_ns: int
    """This module's period (a whole multiple of ``dt_ns``)."""
    tick: int
    """The tick the module joins at."""
    rng: np.random.Generator
    """This module's own seeded generator (derived from the world seed and the module name)."""
    core: PhysicsCore | None = None
    """The world's physics core, when there is one (targets are resolved against its scene)."""
    extras: dict[str, Any] = field(default_factory=dict)
    importing: bool = False
    """True when the module is made to take a state imported next (`World.import_state` of a state that
    holds it, as a batch's worker does): what its setup would check against the world now (the core's
    selection, say) is the state's to decide, and the state is not there yet."""


@dataclass(frozen=True, eq=False)
class PortBinding:
    """What a world gives a module when it binds it (`Module.bind_ports`): views of its ports on the
    world's bus, and whom to tell when its parameters change. The views stay valid until the world
    binds the module again (a change of structure lays the bus out anew)."""

    inp: Mapping[str, np.ndarray]
    """Input name -> read-only view of its slot (shape of the port)."""
    out: Mapping[str, np.ndarray]
    """Output name -> writable view of its slot (shape of the port)."""
    inp_flat: np.ndarray = field(default_factory=lambda: NO_PORTS)
    """Every input (in the order `Module.inputs` declares them) as one flat, read-only float64 array."""
    out_flat: np.ndarray = field(default_factory=lambda: NO_PORTS)
    """The module's own outputs (not the ``view_of`` ports), in declaration order, as one flat
    float64 array."""
    param_changed: Callable[[Module], None] | None = None
    """Called with the module after each change of its parameters (`Module.set_param`, a restore):
    the world that bound it then records the new values in the states it saves from then on."""


class Fused(Protocol):
    """Modules stepped as one (`Module.fuse`). ``bind(buf)`` gives the tick's call for the bus ``buf``:
    ``step(t_ns, dt_ns)`` makes the members' copies and steps, in order. After an exception out of
    it, ``failing`` names the member whose step raised."""

    failing: str | None

    def bind(self, buf: np.ndarray) -> Callable[[int, int], None]: ...


class Module(metaclass=ABCMeta):  # noqa: B024 - no abstract method: every hook has a default
    """Base class of every module. See the module docstring for the lifecycle.

    An abstract base class with no abstract method: every hook has a documented default, and a
    subclass overrides what it needs (a physics core must implement `PhysicsCore`'s abstract
    methods, and cannot be made without them)."""

    PARAMS: ClassVar[tuple[Param, ...]] = ()
    CAPABILITIES: ClassVar[Capabilities] = Capabilities()
    DEFAULT_PERIOD: ClassVar[str | int | None] = None
    """Default period (``"10ms"`` or ns); None means the world's base step."""

    def __init__(self, name: str, *, targets: Sequence[str] = (), **params: Any):
        if not isinstance(name, str) or not name or "." in name:
            raise DynabrainError(f"module name {name!r} must be a non-empty string without dots")
        self.name = name
        self.targets: tuple[str, ...] = tuple(targets)
        self._param_values = ParamValues(self._resolve_params(params))
        self._param_version = 0
        self._binding: PortBinding | None = None
        self.inp: Mapping[str, np.ndarray] = {}
        """Input name -> a read-only view of its slot on the bus (empty while unbound)."""
        self.out: Mapping[str, np.ndarray] = {}
        """Output name -> a writable view of its slot on the bus (empty while unbound)."""
        self.inp_flat: np.ndarray = NO_PORTS
        """Every input (in the order `inputs` declares them) as one flat, read-only float64 array."""
        self.out_flat: np.ndarray = NO_PORTS
        """All of this module's own outputs (not the ``view_of`` ports) as one flat float64 array, in
        the order `outputs` declares them: a module with many small outputs writes them all with one
        assignment (``self.out_flat[:] = values``)."""

    # -- ports on the bus -----------------------------------------------------------------------
    @property
    def binding(self) -> PortBinding | None:
        """How the module is bound now (None while unbound)."""
        return self._binding

    def bind_ports(self, binding: PortBinding | None) -> PortBinding | None:
        """Take the ports of ``binding`` (``inp``, ``out``, ``inp_flat``, ``out_flat``), or drop them
        when it is None (then ``inp`` and ``out`` are empty and the flat arrays have no element);
        returns the binding that was in place. The world calls this, then `bind` (see the lifecycle
        in the module docstring); a copy of a module (``__deepcopy__``) unbinds itself with
        ``bind_ports(None)``. Rebinding costs nothing at step time: the ports are plain attributes."""
        if binding is not None and not isinstance(binding, PortBinding):
            raise DynabrainError(f"module {self.name!r}: bind_ports takes a PortBinding or None, "
                                 f"got {type(binding).__name__}")
        previous, self._binding = self._binding, binding
        if binding is None:
            self.inp, self.out, self.inp_flat, self.out_flat = {}, {}, NO_PORTS, NO_PORTS
        else:
            self.inp, self.out = binding.inp, binding.out
            self.inp_flat, self.out_flat = binding.inp_flat, binding.out_flat
        return previous

    # -- parameters -----------------------------------------------------------------------------
    @classmethod
    def param_specs(cls) -> dict[str, Param]:
        return {p.name: p for p in cls.PARAMS}

    def _resolve_params(self, given: Mapping[str, Any]) -> dict[str, Any]:
        specs = self.param_specs()
        values: dict[str, Any] = {}
        for key, value in given.items():
            if key not in specs:
                raise DynabrainError(
                    f"module {self.name!r} ({type(self).__name__}) has no parameter {key!r}"
                    + did_you_mean(key, specs) + (f"; it has: {', '.join(specs)}" if specs else "")
                )
            try:
                values[key] = specs[key].convert(value)
            except UnitError as exc:
                raise UnitError(f"module {self.name!r}, parameter {key!r}: {exc}") from None
        for key, spec in specs.items():
            if key not in values:
                values[key] = spec.convert(spec.default) if spec.default is not None else None
        return values

    @property
    def params(self) -> ParamValues:
        """Current parameter values (read-only; change them through `World.set`). A change replaces them:
        a module may keep the values it derived something from and compare by identity."""
        return self._param_values

    @property
    def param_version(self) -> int:
        """How many times this module's parameters have changed (`set_param`, a restore that brought
        other values back): two readings differ exactly when a change happened in between."""
        return self._param_version

    def _params_changed(self) -> None:
        self._param_version += 1
        binding = self._binding
        if binding is not None and binding.param_changed is not None:
            binding.param_changed(self)

    def set_param(self, name: str, value: Any, *, running: bool = True) -> None:
        """Change a parameter. `World.set` calls this (and checks the name first); a module bound in a
        world tells it through its binding (`PortBinding.param_changed`), so the world's history
        records the new value from this tick on."""
        specs = self.param_specs()
        if name not in specs:
            raise DynabrainError(f"module {self.name!r} has no parameter {name!r}" + did_you_mean(name, specs))
        spec = specs[name]
        if running and not spec.runtime:
            raise DynabrainError(f"parameter {self.name}.{name} cannot be changed at run time")
        converted = spec.convert(value)
        self._param_values = ParamValues({**self._param_values, name: converted})  # history keeps the old
        self._params_changed()
        self.on_param(name, converted)

    def param_state(self) -> ParamValues:
        """The parameters as part of the module's state: history keeps them with each state (shared
        while they do not change) and `restore_param_state` brings them back."""
        return self._param_values

    def restore_param_state(self, values: Mapping[str, Any]) -> None:
        """Make ``values`` (from `param_state`, now or from an exported state) the parameters again; each
        that differs is told to `on_param`, as a change is."""
        if values is self._param_values:
            return
        old = self._param_values
        self._param_values = values if isinstance(values, ParamValues) else ParamValues(values)
        self._params_changed()
        for key, value in self._param_values.items():
            if old.get(key) is not value:
                self.on_param(key, value)

    def adopt_param_state(self, values: Mapping[str, Any]) -> None:
        """Take ``values`` as this module's parameters without telling it (a copy of a module made with
        these same values: its fork)."""
        self._param_values = values if isinstance(values, ParamValues) else ParamValues(values)

    # -- fork -----------------------------------------------------------------------------------
    def fork(self, memo: dict[int, Any]) -> Module:
        """A copy of this module in its current state, for a forked world (`World.fork`): unbound (the
        world unbinds it first), sharing the parameter values. ``memo`` holds the copies made so far
        (Python's deepcopy memo): a module holding another gets that one's copy. The default copies
        every attribute by Python's deepcopy protocol (``__getstate__`` included). A module holding
        foreign resources (an engine's data, an FMU instance, a GL context) overrides it, without
        calling it, and is then copied by its own `fork` wherever it is copied, also as an attribute of
        another module (`__init_subclass__` makes it the class's ``__deepcopy__``)."""
        return copy.deepcopy(self, memo)

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "fork" in vars(cls):
            cls.__deepcopy__ = cls.fork  # type: ignore[attr-defined]

    # -- the contract ---------------------------------------------------------------------------
    # (the hooks that do nothing by default are so on purpose, not abstract: noqa B027)
    def inputs(self) -> Sequence[Port]:
        """Input ports."""
        return ()

    def outputs(self) -> Sequence[Port]:
        """Output ports."""
        return ()

    def setup(self, ctx: SetupContext) -> None:  # noqa: B027
        """Join a world: resolve targets, allocate resources. Called once per world."""

    def bind(self) -> None:  # noqa: B027
        """``self.inp`` / ``self.out`` (and their flat forms) were (re)bound; refresh any cached views of them."""

    def start(self, t_ns: int) -> None:  # noqa: B027
        """Initial state at the joining tick; write every output's initial value."""

    def step(self, t_ns: int, dt_ns: int) -> None:  # noqa: B027
        """Advance from ``t_ns`` to ``t_ns + dt_ns``."""

    def get_state(self) -> Any:
        """The module's state, as a value the module will not mutate later."""
        return None

    def set_state(self, state: Any) -> None:  # noqa: B027
        """Take back a state returned by `get_state` (copy what you keep)."""

    @classmethod
    def fuse(cls, members: Sequence[Module], copies: Sequence[Copies]) -> Fused | None:
        """Step ``members`` (modules whose classes share this ``fuse``, next to each other in the
        schedule, due at the same ticks; check that you can step each of them) as one: a `Fused` that
        makes each member's input ``copies`` (``Copies`` on the bus, as the tick makes them) and steps
        it, in schedule order, with the same results bit for bit as the separate steps. The compiled
        tick asks when it is built; None (the default) keeps the steps apart. A class answers when one
        call is cheaper than the members' calls from Python: the FMU module's C step helper does
        (`orchestrator.fmu.fused`), and so do the MuJoCo sensors (`modules.sensors.FusedSensors`)."""
        return None

    @classmethod
    def step_batch(cls, members: Sequence[Module], t_ns: int, dt_ns: int, inp: np.ndarray, out: np.ndarray,
                   failed: dict[int, BaseException]) -> np.ndarray | None:
        """Step ``members`` (the same module of N branches of one world, each bound to its own row of a
        stacked bus, each in its own state) from ``t_ns`` to ``t_ns + dt_ns``, as one call: what a
        batch's ``lockstep`` backend calls once a tick instead of N `step` calls. ``inp`` is every
        member's inputs as one ``(N, inputs)`` array (row k: member k's `inp_flat`), ``out`` their
        outputs before the step, ``(N, outputs)`` (row k: member k's `out_flat`); both read-only here.

        Return the outputs after the step as one ``(N, outputs)`` float64 array (the batch writes it into
        each member's outputs, after checking its shape: a wrong one is an error naming the module and
        its ports), or None when each member wrote its own through its binding. A member whose step
        fails goes into ``failed`` (its index in ``members`` -> the exception) and the others go on; its
        branch is stepped again alone, so that it fails as it would have. Each member's state, and each
        row of what it returns, must be bit for bit what the member's own `step` makes (elementwise
        numpy over a leading branch axis is; a sum over a differently ordered axis may not be).

        By default each member steps on its own (a module without a batched step is stepped branch by
        branch); a class overrides it when one call over the branches costs less, as the servo does
        (numpy), the FMU module (its N instances in one call into C) and the MuJoCo core (its N physics
        steps on threads, with the GIL released). A lockstep batch's physics may step a class in its
        stead: MuJoCo's own batch steps the core and the sensors and ZMP that read it from arrays
        (`modules.mujoco.mjbatch`); a module that reads the core's data itself must hold the core or a
        `MujocoLink` to it, so that the batch sees it and steps the branches on threads."""
        for k, member in enumerate(members):
            try:
                member.step(t_ns, dt_ns)
            except Exception as exc:  # the branch's failure, reported through `failed`
                failed[k] = exc
        return None

    def steps_change_state(self) -> bool:
        """Whether `step` may change what `get_state` returns. The answer holds until a parameter
        changes, the structure changes or the world restores a state; the kernel asks again after
        each. A module that answers False has its state saved once and shared by the states of
        history that follow, instead of a `get_state` call per tick (a sensor without noise or delay,
        a servo between programs); it may answer so only if nothing else (no method of its own
        called between ticks) changes its state meanwhile. True, the default, is always correct."""
        return True

    def on_param(self, name: str, value: Any) -> None:  # noqa: B027
        """A run-time parameter changed to ``value``; apply it."""

    def close(self) -> None:  # noqa: B027
        """Release resources. Called once."""

    def scenario_spec(self) -> dict[str, Any]:
        """The scenario syntax that makes this module again (logs, replay, the bridge), parameters in
        SI; the world adds the period, targets and connections. By default the Python class path; a
        module not made from one (an FMU) says how it is made."""
        return {"name": self.name, "python": f"{type(self).__module__}:{type(self).__qualname__}",
                "params": self._plain_params()}

    def _plain_params(self) -> dict[str, Any]:
        """The parameter values as plain data (arrays as lists), for descriptions and specs."""
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self._param_values.items()}

    def describe(self) -> dict[str, Any]:
        """A plain description (for `dynabrain check`, logs and the bridge)."""
        return {
            "name": self.name,
            "class": f"{type(self).__module__}:{type(self).__qualname__}",
            "inputs": [(p.name, p.shape, p.unit) for p in self.inputs()],
            "outputs": [(p.name, p.shape, p.unit) for p in self.outputs()],
            "params": self._plain_params(),
            "targets": list(self.targets),
            "capabilities": self.CAPABILITIES,
        }

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}>"
