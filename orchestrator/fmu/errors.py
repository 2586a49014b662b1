"""Errors of the FMU adapter. Each names the FMU, the call and the cause.

Load and build problems are `FMUError` (a `DynabrainError`: the scenario reports it with file and
line). Failures while the world runs are `ModuleError` subclasses, so the kernel rolls the world
back to the last good tick and re-raises them with the module's name and the tick.
"""

from __future__ import annotations

from ..kernel.errors import DynabrainError, EndRequestedError, ModuleError

STATUS_NAMES = ("OK", "Warning", "Discard", "Error", "Fatal", "Pending")


def status_name(version: int, status: int) -> str:
    """``fmi2Error``, ``fmi3Discard``, ... (or the raw number for a status outside the standard)."""
    if 0 <= status < len(STATUS_NAMES):
        return f"fmi{version}{STATUS_NAMES[status]}"
    return f"status {status} (not an FMI status)"


class FMUError(DynabrainError):
    """An FMU that cannot be used: a missing or broken file, an unsupported kind, a missing binary or
    symbol, a variable that does not fit. Raised before the FMU joins a world."""


class FMUBuildError(FMUError):
    """An FMU source folder that does not build (bad fmu.yaml, compiler errors, no compiler)."""


class FMUCallError(ModuleError):
    """An FMI call that returned an error status (``fmi2Error``, ``fmi3Fatal``, ...). ``call`` is
    the FMI function; the message carries the status and the FMU's own log lines."""


class FMUDiscardError(FMUCallError):
    """The FMU discarded a step (it could not complete it). The world rolls back to the last good
    tick; retry with other inputs or a smaller step."""


class FMUTerminatedError(FMUCallError, EndRequestedError):
    """The FMU asked to end the simulation (FMI 3.0 ``terminateSimulation``; FMI 2.0 a step discarded
    with ``fmi2Terminated``). The world rolls the tick back; a scenario's run ends there."""


class FMUUnusableError(FMUCallError):
    """An FMU that failed (an error, a discarded step, a fatal error) and cannot be brought back to a
    state from before (it cannot get and set its state, or restoring one failed): the FMI standard
    allows only to reset or free it then. Every later step is refused naming it; remove the module or
    load the world again. (An isolated FMU is restarted from scratch instead, its state lost.)"""


class FMUCrashError(ModuleError):
    """The process running an isolated FMU died (a segfault, an abort). The world rolls back to the
    last good tick; the next step restarts the FMU from that tick's state."""


class FMUTimeoutError(FMUCrashError):
    """An isolated FMU did not answer a call within its ``call_timeout`` (an endless loop, a deadlock):
    its process is killed, and the world goes on as after a crash."""
