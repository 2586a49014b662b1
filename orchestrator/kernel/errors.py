"""One root error, a few subclasses by phase.

Expected outcomes (an expectation that fails, a step an FMU discards) are values, not exceptions.
Exceptions are for things that went wrong; each message names what and where.
"""

from __future__ import annotations

from dataclasses import dataclass


class DynabrainError(Exception):
    """Root of every error dynabrain raises on purpose."""


class UnitError(DynabrainError, ValueError):
    """A value whose unit is unknown or of the wrong dimension."""


@dataclass(frozen=True)
class Problem:
    """One problem found in a scenario, with where it is."""

    message: str
    file: str | None = None
    line: int | None = None
    field: str | None = None

    def __str__(self) -> str:
        where = ""
        if self.file:
            where = self.file + (f":{self.line}" if self.line else "")
        if self.field:
            where = f"{where} [{self.field}]" if where else f"[{self.field}]"
        return f"{where}: {self.message}" if where else self.message


class ScenarioError(DynabrainError):
    """A scenario that does not validate; carries every problem found, not only the first."""

    def __init__(self, problems: list[Problem]):
        self.problems = list(problems)
        count = len(self.problems)
        head = f"{count} problem{'s' if count != 1 else ''} in scenario"
        super().__init__(head + ":\n" + "\n".join(f"  - {p}" for p in self.problems))


class WiringError(DynabrainError):
    """Modules, ports or connections that do not fit together (names, shapes, units, direction)."""


class AlgebraicLoopError(WiringError):
    """A cycle of direct-feedthrough connections; ``path`` lists the signals around it."""

    def __init__(self, path: list[str]):
        self.path = path
        super().__init__("algebraic loop: " + " -> ".join(path) + " (mark one connection `delay: true` "
                         "to break it, make one module non-feedthrough, or declare the loop's modules "
                         "`iterate:` to solve it at every step)")


class ModuleError(DynabrainError):
    """A module call that failed. Names the module, the call and the tick."""

    def __init__(self, module: str, call: str, tick: int | None, cause: BaseException | str):
        self.module, self.call, self.tick = module, call, tick
        self.cause = cause
        at = f" at tick {tick}" if tick is not None else ""
        detail = f"{type(cause).__name__}: {cause}" if isinstance(cause, BaseException) else str(cause)
        super().__init__(f"module {module!r}: {call}(){at} failed: {detail}")

    def at_tick(self, tick: int) -> ModuleError:
        """The same error, saying the tick it happened at (the world adds it to a module's error)."""
        return type(self)(self.module, self.call, tick, self.cause)


class PhysicsDivergedError(ModuleError):
    """The physics produced NaN or ran away; the tick was rolled back."""


class NonFiniteOutputError(ModuleError):
    """A module's output became NaN or infinite (modules say so with ``Capabilities.finite_outputs``
    when that is meant); the tick was rolled back. ``port`` names the output."""

    def __init__(self, module: str, call: str, tick: int | None, cause: BaseException | str, port: str = ""):
        super().__init__(module, call, tick, cause)
        self.port = port

    def at_tick(self, tick: int) -> NonFiniteOutputError:
        return type(self)(self.module, self.call, tick, self.cause, self.port)


class EndRequestedError(ModuleError):
    """A module asked to end the simulation (an FMU's terminate request: FMI 3.0 ``terminateSimulation``,
    FMI 2.0 ``fmi2Terminated``). The world rolls the tick back as for any failed tick and raises this;
    a scenario's run ends there as a normal end, not as a failure (`RunResult.ended`)."""


class RollbackError(DynabrainError):
    """A rollback that cannot be done exactly (beyond the history, or a module that cannot roll back)."""


class ForkError(DynabrainError):
    """A fork that cannot be made (a module that cannot fork)."""


class WorldClosedError(DynabrainError):
    """A call on a world that has been closed."""
