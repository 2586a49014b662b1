"""`check_fmu`: the FMU counterpart of `check_module`, for FMU authors (``dynabrain fmu check``).

It reads and validates the FMU (FMPy's full validation: schema, names, model structure, start
values, units), runs it alone for ``ticks`` ticks with seeded inputs (every output must stay finite:
the world checks that), then runs it as a module through the kernel's `check_module` (lifecycle, the
save/restore round trip, step -> restore -> step equality, fork through the serialized state).

``ticks`` bounds every run: no world of the check goes past tick ``ticks``. An FMU that asks to end
the simulation (FMI 3.0 ``terminateSimulation``, FMI 2.0 ``fmi2Terminated``) at tick T is a valid FMU
that ends there: the checks then run up to tick T and no further. Each problem is reported once.

    report = check_fmu("fmus/servo")        # a .fmu file, or a source folder (built first)
    print(report); report.assert_ok()
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ..kernel.checks import CheckReport, check_module
from ..kernel.errors import DynabrainError, ModuleError
from ..kernel.world import World
from . import load_fmu_info
from .errors import FMUTerminatedError
from .info import FmuInfo, Signal
from .module import FMUModule

MIN_TICKS = 12
"""The fewest ticks the state checks need (a run, five steady ticks, a replay, five forked ticks)."""


@dataclass
class FmuCheckReport(CheckReport):
    """`CheckReport` of an FMU (``module`` is the FMU's path), with its model description and notes
    that are no problems (variables not on the bus, where the FMU asked to end)."""

    info: FmuInfo | None = None
    notes: list[str] = field(default_factory=list)
    CHECK: ClassVar[str] = "check_fmu"

    def __str__(self) -> str:
        return super().__str__() + "".join(f"\n  note: {n}" for n in self.notes)


def check_fmu(fmu: str, *, base_dir: str = ".", ticks: int = 40, step: str | int | None = None,
              seed: int = 0, on_phase: Callable[[str], None] | None = None) -> FmuCheckReport:
    """Check the FMU at ``fmu`` in runs of at most ``ticks`` ticks (at least `MIN_TICKS`); ``step``
    defaults to the FMU's default step, else 1 ms. ``on_phase`` is told each phase as it begins (the
    check's child process keeps it for a crash report: `checkproc`)."""
    if ticks < MIN_TICKS:
        raise DynabrainError(f"check_fmu needs at least {MIN_TICKS} ticks, got {ticks}")
    phase = on_phase or (lambda _: None)
    report = FmuCheckReport(fmu)
    phase("loading")
    try:
        info = load_fmu_info(fmu, base_dir=base_dir)
    except DynabrainError as exc:
        report.problems.append(str(exc))
        return report
    report.info = info
    report.checked.append("model description")
    if info.skipped:
        report.notes.append("not on the bus: " + ", ".join(info.skipped))
    phase("validation")
    _validate(info, report)
    dt = step if step is not None else (f"{round(info.default_step * 1e9)}ns" if info.default_step else "1ms")
    phase(f"run of {ticks} ticks")
    limit = _simulate(info, fmu, dt, ticks, seed, report)
    if limit is None:
        return _once(report)
    phase("state checks")
    module = FMUModule("fmu", info, source=fmu)
    # check_module runs ticks k (+ 5 steady, + a replay of k, + 5 forked when the module can roll back)
    sub_ticks = (limit - 10) // 2 if module.CAPABILITIES.can_rollback else limit
    if sub_ticks < 1:
        report.notes.append(f"the state checks need {MIN_TICKS} ticks before the FMU asks to end; it asked at "
                            f"tick {limit}")
    else:
        sub = check_module(module, step=dt, ticks=sub_ticks, seed=seed, drive=_driver(info))
        report.checked += [c for c in sub.checked if c not in report.checked]
        report.problems += sub.problems
    return _once(report)


def _once(report: FmuCheckReport) -> FmuCheckReport:
    report.problems = list(dict.fromkeys(report.problems))  # each problem once
    return report


def _validate(info: FmuInfo, report: FmuCheckReport) -> None:
    from fmpy.validation import validate_fmu

    report.checked.append("FMPy validation")
    report.problems += [f"validation: {p}" for p in validate_fmu(info.path)]


def _simulate(info: FmuInfo, fmu: str, dt: str | int, ticks: int, seed: int, report: FmuCheckReport) -> int | None:
    """Run the FMU alone with seeded inputs for ``ticks`` ticks: the ticks the state checks may use
    (fewer when the FMU asks to end the simulation), or None after a problem."""
    report.checked.append(f"a run of {ticks} ticks with finite outputs")
    rng = np.random.default_rng(seed)
    with World("check-fmu", step=dt, history=4) as world:
        try:
            world.add_module(FMUModule("fmu", info, source=fmu))
        except DynabrainError as exc:
            report.problems.append(f"joining a world failed: {exc}")
            return None
        for _ in range(ticks):
            for sig in info.inputs:
                world.set(f"fmu.{sig.name}", _drive(rng, sig))
            try:
                world.tick()
            except FMUTerminatedError as exc:
                report.notes.append(f"the FMU asked to end the simulation at tick {exc.tick} (t={world.time:g} s of "
                                    f"the world); the checks run up to there: {exc.cause}")
                return world.tick_count
            except ModuleError as exc:
                report.problems.append(f"tick {world.tick_count} failed: {exc}")
                return None
    return ticks


def _driver(info: FmuInfo) -> Callable[[np.random.Generator, tuple[int, ...]], np.ndarray]:
    """`check_module`'s input maker: it asks for each input in port order, tick after tick, so the
    values can fit each input's type (an enumeration takes no 0)."""
    order = itertools.cycle(info.inputs)

    def drive(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
        sig = next(order) if info.inputs else None
        if sig is None or tuple(sig.shape) != tuple(shape):
            return rng.normal(0.0, 0.1, shape)
        return _drive(rng, sig)

    return drive


def _drive(rng: np.random.Generator, sig: Signal) -> np.ndarray:
    """Small seeded input values that fit the variable's type."""
    values = rng.normal(0.0, 0.1, sig.shape)
    if sig.fmi_type == "Enumeration":
        return np.ones(sig.shape)  # the first item
    if sig.type == "boolean":
        return (values > 0).astype(float)
    if sig.type not in ("real", "float32"):
        return np.rint(np.abs(values) * 10)  # small whole numbers from 0 (unsigned types too)
    return values
