"""Errors a brain sees when it talks to a world over the bridge.

Three different situations, three different errors:

- `ConnectError`: no session could be made (nothing listens there; or the endpoint refused us:
  wrong credentials, TLS or access control);
- `NoWorldError`: the session is up but no world answered (no server serves that world name, or it
  went away: its liveliness token is gone); `CallTimeoutError`: the world is alive but did not answer in
  time (it may still be running the call);
- `WorldRefusedError` and its subclasses: the world answered and refused, with its reason. Nothing was done,
  except for `ModuleFailedError` where the failed tick was rolled back by the world, and `TickStoppedError`
  where a ``stop`` ended a tick early (the ticks done stay).
"""

from __future__ import annotations

from typing import Any

from dynabrain.orchestrator.kernel.errors import DynabrainError


class BridgeError(DynabrainError):
    """Root of the bridge's errors."""


class ConnectError(BridgeError):
    """No Zenoh session: nothing listens at the endpoint, or the endpoint refused the session."""


class NoWorldError(BridgeError):
    """No world answered: nothing serves this world name (or it went away)."""


class CallTimeoutError(BridgeError):
    """The world is alive but did not answer within the timeout."""


class WorldRefusedError(BridgeError):
    """The world refused the call; ``kind`` says why (see `protocol.ERROR_KINDS`)."""

    def __init__(self, kind: str, message: str, call: str | None = None, detail: dict[str, Any] | None = None):
        self.kind, self.call, self.reason = kind, call, message
        self.detail = detail or {}
        """What the error reply carries beside its message (`TickStoppedError`: the ticks done)."""
        super().__init__(f"world refused {call or 'the call'} ({kind}): {message}")


class BadRequestError(WorldRefusedError):
    """Malformed or oversized payload, unknown call, wrong argument types."""


class WorldBusyError(WorldRefusedError):
    """Another brain holds the world (or owns the fork)."""


class ModuleFailedError(WorldRefusedError):
    """A module failed during the call's ticks; the world rolled the failed tick back."""


class TickStoppedError(WorldRefusedError):
    """A ``stop`` ended this tick early; the ticks done stay (``ticks_done`` of ``ticks_asked``; the world is
    at ``tick``)."""

    @property
    def ticks_done(self) -> int:
        return int(self.detail.get("ticks_done", 0))

    @property
    def ticks_asked(self) -> int:
        return int(self.detail.get("ticks_asked", 0))

    @property
    def tick(self) -> int | None:
        tick = self.detail.get("tick")
        return None if tick is None else int(tick)


class WorldRestartedError(WorldRefusedError):
    """The server restarted since this brain's last call: its world state is new. Call ``reattach()``."""


ERRORS: dict[str, type[WorldRefusedError]] = {
    "bad_request": BadRequestError, "unknown_call": BadRequestError, "busy": WorldBusyError,
    "module_error": ModuleFailedError, "restarted": WorldRestartedError, "stopped": TickStoppedError,
}


class RobotLostError(BridgeError):
    """A robot rig's robot went away (its liveliness token is gone) while a brain waited on it; ``tick`` is
    the world's tick when the link lost it."""

    def __init__(self, robot: str, tick: int | None, message: str):
        self.robot, self.tick = robot, tick
        super().__init__(message)


class RobotStoppedError(BridgeError):
    """A robot did not carry out what a brain waited for: its program was ignored, refused or not sent, or
    the robot safe-stopped while playing it; ``tick`` is the world's tick when that was seen, ``reason`` the
    robot's (or the link's) word."""

    def __init__(self, robot: str, tick: int | None, reason: str, message: str):
        self.robot, self.tick, self.reason = robot, tick, reason
        super().__init__(message)
