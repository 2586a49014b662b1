"""What a batch's parent and its worker processes say to each other (besides `BranchTask` and
`BranchOutcome`): defined here, not in the worker's own file, which runs as ``__main__``."""

from __future__ import annotations

from typing import Any, NamedTuple


class Init(NamedTuple):
    build: Any
    """A picklable call that builds the world (`World.rebuild`)."""


class Ready(NamedTuple):
    pid: int


class InitFailed(NamedTuple):
    reason: str


class Stop(NamedTuple):
    pass
