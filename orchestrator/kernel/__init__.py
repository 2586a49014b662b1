"""The kernel: the World, the module and core contracts, ports and the bus, the structure and its
schedule (the master algorithm), the compiled tick, history and rollback, observers, integer time and
units, errors, and `check_module`.

The kernel imports nothing of dynabrain above it (an import contract in the tests keeps it so). The
names below are what modules and the rooms above use; the files behind them are the kernel's own.
"""

from .checks import CheckReport, check_module
from .core import COLORS, BodyInfo, BodySpec, CableSpec, Edits, JointSpec, PhysicsCore, SceneSpec, Weld
from .edited import EditedCore
from .errors import (
    AlgebraicLoopError,
    DynabrainError,
    ForkError,
    ModuleError,
    PhysicsDivergedError,
    Problem,
    RollbackError,
    ScenarioError,
    UnitError,
    WiringError,
    WorldClosedError,
)
from .history import WorldState
from .module import Capabilities, Module, Param, Port, PortBinding, SetupContext
from .observers import Observer, WorldEvent, WorldView
from .structure import Connection
from .world import World

__all__ = [
    "COLORS", "AlgebraicLoopError", "BodyInfo", "BodySpec", "CableSpec", "Capabilities", "CheckReport",
    "Connection", "DynabrainError", "EditedCore", "Edits", "ForkError", "JointSpec", "Module", "ModuleError",
    "Observer", "Param", "PhysicsCore", "PhysicsDivergedError", "Port", "PortBinding", "Problem", "RollbackError",
    "ScenarioError", "SceneSpec", "SetupContext", "UnitError", "Weld", "WiringError", "World", "WorldClosedError",
    "WorldEvent", "WorldState", "WorldView", "check_module",
]
