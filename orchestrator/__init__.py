"""dynabrain's orchestrator: the public face.

    from dynabrain.orchestrator import World, Module, Port, Param, load_world

    world = load_world("scenarios/two_cubes.yaml")
    world.tick(100)
    world.backtick(10)

The rooms behind it, bottom up (each imports only the rooms below it; `ARCHITECTURE.md` draws them):
`kernel` (World, the module and core contracts, bus, schedule, history), `fmu` (the FMU adapter),
`scenario` (YAML in, a World out), `logs` (MCAP) and `brain` (batches of futures), `cli` (the
``dynabrain`` command). A module author
needs nothing but the names here.

The names are loaded on first use, so importing one room does not import the others.
"""

from __future__ import annotations

import importlib as _importlib
from typing import TYPE_CHECKING

_FACE = {
    "kernel": (
        "World", "Module", "Port", "Param", "Capabilities", "SetupContext", "PhysicsCore", "SceneSpec",
        "BodySpec", "JointSpec", "Observer", "WorldView", "WorldEvent", "WorldState", "Connection",
        "check_module", "CheckReport", "DynabrainError", "UnitError", "ScenarioError", "Problem", "WiringError",
        "AlgebraicLoopError", "ModuleError", "PhysicsDivergedError", "RollbackError", "ForkError",
        "WorldClosedError",
    ),
    "scenario": ("load_world", "load_scenario", "make_module", "run_scenario", "Scenario", "RunResult"),
    "brain": ("Batch", "BatchResult", "BranchStatus"),
}
_WHERE = {name: room for room, names in _FACE.items() for name in names}

__all__ = [  # the same names as `_FACE`, written out for tools that read __all__
    "AlgebraicLoopError", "Batch", "BatchResult", "BodySpec", "BranchStatus", "Capabilities", "CheckReport",
    "Connection", "DynabrainError", "ForkError", "JointSpec", "Module", "ModuleError", "Observer", "Param",
    "PhysicsCore", "PhysicsDivergedError", "Port", "Problem", "RollbackError", "RunResult", "Scenario",
    "ScenarioError", "SceneSpec", "SetupContext", "UnitError", "WiringError", "World", "WorldClosedError",
    "WorldEvent", "WorldState", "WorldView", "check_module", "load_scenario", "load_world", "make_module",
    "run_scenario",
]


def __getattr__(name: str) -> object:
    room = _WHERE.get(name)
    if room is None:
        raise AttributeError(f"module 'dynabrain.orchestrator' has no attribute {name!r}")
    try:
        value = getattr(_importlib.import_module(f"{__name__}.{room}"), name)
    except ModuleNotFoundError as exc:  # a part whose extra is not installed: say which
        from .kernel.extras import hint

        missing = hint(exc)
        if missing is None:
            raise
        raise missing from None
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    """The public names only (not this file's own imports)."""
    return sorted(__all__)


if TYPE_CHECKING:
    from .brain import Batch, BatchResult, BranchStatus
    from .kernel import (
        AlgebraicLoopError,
        BodySpec,
        Capabilities,
        CheckReport,
        Connection,
        DynabrainError,
        ForkError,
        JointSpec,
        Module,
        ModuleError,
        Observer,
        Param,
        PhysicsCore,
        PhysicsDivergedError,
        Port,
        Problem,
        RollbackError,
        ScenarioError,
        SceneSpec,
        SetupContext,
        UnitError,
        WiringError,
        World,
        WorldClosedError,
        WorldEvent,
        WorldState,
        WorldView,
        check_module,
    )
    from .scenario import RunResult, Scenario, load_scenario, load_world, make_module, run_scenario
