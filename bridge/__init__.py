"""The Zenoh bridge: a World served to remote brains (`server.BridgeServer`, ``dynabrain serve``), the brain
client (`BrainClient`), the real-robot link with its watchdog and shadow mode (`robot_link`), a robot
emulator (`robot_emulator`), and the wire format (`protocol`, `frames`, ``PROTOCOL.md``)."""

from .client import BrainClient, Snapshot, StateFrame, View
from .errors import (
    BadRequestError,
    BridgeError,
    CallTimeoutError,
    ConnectError,
    ModuleFailedError,
    NoWorldError,
    WorldBusyError,
    WorldRefusedError,
    WorldRestartedError,
)

__all__ = [
    "BadRequestError", "BrainClient", "BridgeError", "CallTimeoutError", "ConnectError", "ModuleFailedError",
    "NoWorldError", "Snapshot", "StateFrame", "View", "WorldBusyError", "WorldRefusedError", "WorldRestartedError",
]
