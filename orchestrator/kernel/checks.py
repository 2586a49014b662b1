"""`check_module`: the checker we ship for module authors (the module counterpart of a determinism test).

It puts a module in a small world, drives its inputs with seeded values, and checks:
- the declared ports and parameters are well formed;
- the lifecycle order (setup, bind, start, then steps; close once at the end);
- the save/restore round trip (``set_state(get_state())`` changes nothing);
- a module that says its steps leave its state alone (``steps_change_state()`` False) keeps it;
- step -> restore -> step equality: after a rollback, the same inputs give bit-identical outputs and
  states (the world's ``backtick``, which is what the brain uses);
- fork: a forked world steps exactly like the original (when the module can fork).

    report = check_module(MyModule("m", gain=2.0))
    report.assert_ok()
"""

from __future__ import annotations

import pickle
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from .core import PhysicsCore
from .module import Module
from .world import World


@dataclass
class CheckReport:
    """What a check found. ``module`` names what was checked (a module, or an FMU for `check_fmu`)."""

    module: str
    problems: list[str] = field(default_factory=list)
    calls: list[str] = field(default_factory=list)
    checked: list[str] = field(default_factory=list)
    CHECK: ClassVar[str] = "check_module"

    @property
    def ok(self) -> bool:
        return not self.problems

    def assert_ok(self) -> None:
        if self.problems:
            raise AssertionError(f"{self.CHECK}({self.module!r}) found problems:\n"
                                 + "\n".join(f"  - {p}" for p in self.problems))

    def __str__(self) -> str:
        checked = ", ".join(self.checked) or "nothing"
        head = f"{self.CHECK}({self.module!r}): {'ok' if self.ok else 'FAILED'}; checked {checked}"
        return head + "".join(f"\n  - {p}" for p in self.problems)


_TRACED = ("setup", "bind", "start", "step", "get_state", "set_state", "close")


def check_module(module: Module, *, core: PhysicsCore | None = None, step: str | int = "2ms",
                 period: str | int | None = None, ticks: int = 40, seed: int = 0,
                 drive: Callable[[np.random.Generator, tuple[int, ...]], np.ndarray] | None = None) -> CheckReport:
    """Run the checks on ``module`` (a fresh, unconfigured-into-a-world instance). ``core`` is the
    physics core a sensor or actuator module needs; ``drive`` makes input values (default: small
    seeded normals)."""
    report = CheckReport(module.name)
    _check_declarations(module, report)
    _trace(module, report.calls)
    rng = np.random.default_rng(seed)
    drive = drive or (lambda r, shape: r.normal(0.0, 0.1, shape))
    world = World(f"check-{module.name}", step=step, seed=seed, history=4 * ticks + 4,
                  core=core if core is not module else None)
    try:
        try:
            world.add_module(module, period=period)
        except Exception as exc:
            report.problems.append(f"joining a world failed: {exc}")
            return report
        _check_order(report)
        inputs = [n for n in world.signals if n.startswith(module.name + ".") and
                  world.structure.layout.slots[n].direction == "in" and
                  world.structure.layout.slots[n].port.view_of is None]
        plan = [{n: drive(rng, world.structure.layout.slots[n].shape) for n in inputs} for _ in range(2 * ticks + 5)]
        _run(world, plan[:ticks], report)
        _check_roundtrip(module, report)
        if module.CAPABILITIES.can_rollback:
            _check_steady(world, module, plan[2 * ticks:], report)
            _check_replay(world, module, plan[ticks:2 * ticks], report)
        if module.CAPABILITIES.can_fork:
            _untrace(module)  # a fork deep-copies the module; it must not copy our wrappers
            try:
                _check_fork(world, plan[ticks:], report)
            finally:
                _trace(module, report.calls)
    finally:
        world.close()
        closes = report.calls.count("close")
        if closes != 1:
            report.problems.append(f"close() was called {closes} times when the world closed (expected once)")
    return report


def _check_declarations(module: Module, report: CheckReport) -> None:
    report.checked.append("declarations")
    seen: set[str] = set()
    for kind, ports in (("input", module.inputs()), ("output", module.outputs())):
        for port in ports:
            if port.name in seen:
                report.problems.append(f"port name {port.name!r} is declared twice")
            seen.add(port.name)
            if not all(isinstance(d, int) and d >= 0 for d in port.shape):
                report.problems.append(f"{kind} {port.name!r}: shape {port.shape} is not a tuple of sizes")
            if not isinstance(port.unit, str):
                report.problems.append(f"{kind} {port.name!r}: unit must be a string")
    for name in module.param_specs():
        if name in seen:
            report.problems.append(f"{name!r} is both a port and a parameter")


def _trace(module: Module, calls: list[str]) -> None:
    for name in _TRACED:
        original = getattr(module, name)

        def traced(*args: Any, __name: str = name, __fn: Callable[..., Any] = original, **kwargs: Any) -> Any:
            calls.append(__name)
            return __fn(*args, **kwargs)

        setattr(module, name, traced)


def _untrace(module: Module) -> None:
    for name in _TRACED:
        module.__dict__.pop(name, None)


def _check_order(report: CheckReport) -> None:
    report.checked.append("lifecycle order")
    life = [c for c in report.calls if c in ("setup", "bind", "start")]
    if not life or life[0] != "setup" or "start" not in life or life.index("start") < life.index("bind"):
        report.problems.append(f"lifecycle order is {life}, expected setup, bind (one or more), start")


def _run(world: World, plan: list[dict[str, np.ndarray]], report: CheckReport) -> list[np.ndarray]:
    frames = []
    for inputs in plan:
        for name, value in inputs.items():
            world.set(name, value)
        try:
            world.tick()
        except Exception as exc:
            report.problems.append(f"tick {world.tick_count} failed: {exc}")
            break
        frames.append(world.bus.copy())
    return frames


def _check_roundtrip(module: Module, report: CheckReport) -> None:
    if not module.CAPABILITIES.can_rollback:
        return
    report.checked.append("save/restore round trip")
    state = module.get_state()
    before = _dump(state)
    module.set_state(state)
    if _dump(module.get_state()) != before:
        report.problems.append("set_state(get_state()) changed the state")
    if _dump(state) != before:
        report.problems.append("the value get_state() returned was mutated by set_state()")


def _check_steady(world: World, module: Module, plan: list[dict[str, np.ndarray]], report: CheckReport) -> None:
    report.checked.append("steps_change_state")
    for inputs in plan:
        claim, before = module.steps_change_state(), _dump(module.get_state())
        if not _run(world, [inputs], report):
            return
        if not claim and _dump(module.get_state()) != before:
            report.problems.append(f"steps_change_state() said False, and the step at tick {world.tick_count - 1} "
                                   "changed the state: history would keep a stale state (answer True)")
            return


def _check_replay(world: World, module: Module, plan: list[dict[str, np.ndarray]], report: CheckReport) -> None:
    report.checked.append("step -> restore -> step")
    start = world.tick_count
    state0 = _dump(module.get_state())
    first = _run(world, plan, report)
    state1 = _dump(module.get_state())
    world.backtick(world.tick_count - start)
    if _dump(module.get_state()) != state0:
        report.problems.append("after backtick the module state differs from the state saved at that tick")
    second = _run(world, plan, report)
    for i, (a, b) in enumerate(zip(first, second, strict=False)):
        if not np.array_equal(a, b, equal_nan=True):
            report.problems.append(f"replay differs at tick {start + i + 1}: outputs are not bit-identical")
            break
    if _dump(module.get_state()) != state1:
        report.problems.append("replay ends in a different module state")


def _check_fork(world: World, plan: list[dict[str, np.ndarray]], report: CheckReport) -> None:
    report.checked.append("fork")
    try:
        other = world.fork()
    except Exception as exc:
        report.problems.append(f"fork failed: {exc}")
        return
    try:
        a, b = _run(world, plan[:5], report), _run(other, plan[:5], report)
        if not all(np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b, strict=True)):
            report.problems.append("a forked world does not step like the original")
    finally:
        other.close()


def _dump(state: Any) -> bytes:
    """A byte form of a state, for exact comparison."""
    try:
        return pickle.dumps(state, protocol=5)
    except Exception:
        return repr(state).encode()
