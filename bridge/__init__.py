"""The Zenoh bridge: a World served to remote brains (`server.BridgeServer`, ``dynabrain serve``), the brain
client (`BrainClient`; `BrainClient.batch` asks for N futures in one call), the real-robot link with its
watchdog and shadow mode (`robot_link`), a robot emulator (`robot_emulator`), recordings replayed over
Zenoh (`replay`), and the wire format (`protocol`, `frames`, ``PROTOCOL.md``)."""

from typing import Any

from .client import BrainClient
from .errors import (
    BadRequestError,
    BridgeError,
    CallTimeoutError,
    ConnectError,
    ModuleFailedError,
    NoWorldError,
    TickStoppedError,
    WorldBusyError,
    WorldRefusedError,
    WorldRestartedError,
)
from .replies import BatchReply, Snapshot, StateFrame, View

__all__ = [
    "BadRequestError", "BatchReply", "BrainClient", "BridgeError", "CallTimeoutError", "ConnectError",
    "ModuleFailedError", "NoWorldError", "Snapshot", "StateFrame", "TickStoppedError", "View", "WorldBusyError",
    "WorldRefusedError", "WorldRestartedError", "publish_recording",
]


def publish_recording(path: Any, *, speed: float = 1.0, **options: Any) -> Any:
    """Publish a recorded run over Zenoh as its world served it (``dynabrain replay LOG --publish``);
    see `replay.publish_recording`. Imported on use: it needs the log reader."""
    from .replay import publish_recording as publish

    return publish(path, speed=speed, **options)
