"""Child processes that talk over a socket pair: the isolated FMU worker and the MCAP log writer.

    proc, conn = spawn_worker("dynabrain.orchestrator.logs.sink")

starts ``python -m MODULE FD [ARGS...]`` with this interpreter; FD is the child's end of the pair,
which it wraps as ``multiprocessing.connection.Connection(int(sys.argv[1]))``. Nothing listens on a
port: the pair is private to the two processes.

What goes through the pair is pickled: give each message a named type (a `typing.NamedTuple` costs no
more than a tuple) defined in a module other than MODULE, which is ``__main__`` in the child, where a
class of its own would not be the parent's (the log writer's are in ``logs.messages``).
"""

from __future__ import annotations

import socket
import subprocess
import sys
from multiprocessing.connection import Connection
from typing import Any


def spawn_worker(module: str, *args: str, **popen: Any) -> tuple[subprocess.Popen, Connection]:
    """Start ``python -m module FD *args`` (``popen``: more `subprocess.Popen` arguments, such as where
    its output goes); its standard input is closed. Raises `OSError` when it cannot start."""
    ours, theirs = socket.socketpair()
    try:
        proc = subprocess.Popen([sys.executable, "-m", module, str(theirs.fileno()), *args],
                                stdin=subprocess.DEVNULL, pass_fds=(theirs.fileno(),), close_fds=True, **popen)
    except BaseException:
        ours.close()
        raise
    finally:
        theirs.close()
    return proc, Connection(ours.detach())
