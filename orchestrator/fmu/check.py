"""`check_fmu`: the FMU counterpart of `check_module`, for FMU authors (``dynabrain fmu check``).

It reads and validates the FMU (FMPy's full validation: schema, names, model structure, start
values, units), then runs it as a module through the kernel's `check_module` (lifecycle, a short
simulation with seeded inputs, the save/restore round trip, step -> restore -> step equality, fork
through the serialized state), and checks that every output stays finite.

    report = check_fmu("fmus/servo")        # a .fmu file, or a source folder (built first)
    print(report); report.assert_ok()
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..kernel.checks import CheckReport, check_module
from ..kernel.errors import DynabrainError
from ..kernel.world import World
from . import load_fmu_info
from .info import FmuInfo
from .module import FMUModule


@dataclass
class FmuCheckReport(CheckReport):
    """`CheckReport` of an FMU (``module`` is the FMU's path), with its model description."""

    info: FmuInfo | None = None
    CHECK: ClassVar[str] = "check_fmu"


def check_fmu(fmu: str, *, base_dir: str = ".", ticks: int = 40, step: str | int | None = None,
              seed: int = 0) -> FmuCheckReport:
    """Check the FMU at ``fmu``; ``step`` defaults to the FMU's default step, else 1 ms."""
    report = FmuCheckReport(fmu)
    try:
        info = load_fmu_info(fmu, base_dir=base_dir)
    except DynabrainError as exc:
        report.problems.append(str(exc))
        return report
    report.info = info
    report.checked.append("model description")
    _validate(info, report)
    dt = step if step is not None else (f"{round(info.default_step * 1e9)}ns" if info.default_step else "1ms")
    module = FMUModule("fmu", info, source=fmu)
    sub = check_module(module, step=dt, ticks=ticks, seed=seed)
    report.checked += sub.checked
    report.problems += sub.problems
    if sub.ok:
        _finite(info, fmu, dt, ticks, seed, report)
    return report


def _validate(info: FmuInfo, report: FmuCheckReport) -> None:
    from fmpy.validation import validate_fmu

    report.checked.append("FMPy validation")
    report.problems += [f"validation: {p}" for p in validate_fmu(info.path)]


def _finite(info: FmuInfo, fmu: str, dt: str | int, ticks: int, seed: int, report: FmuCheckReport) -> None:
    """Outputs stay finite under seeded inputs."""
    report.checked.append("finite outputs")
    rng = np.random.default_rng(seed)
    with World("check-fmu", step=dt, history=4) as world:
        world.add_module(FMUModule("fmu", info, source=fmu))
        for _ in range(ticks):
            for sig in info.inputs:
                world.set(f"fmu.{sig.name}", rng.normal(0.0, 0.1, sig.shape))
            world.tick()
            for sig in info.outputs:
                value = np.asarray(world.get(f"fmu.{sig.name}"))
                if not np.all(np.isfinite(value)):
                    report.problems.append(f"output {sig.name} is not finite at tick {world.tick_count}: {value}")
                    return
