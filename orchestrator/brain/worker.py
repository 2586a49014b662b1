"""A batch's worker process: ``python -m dynabrain.orchestrator.brain.worker FD`` (started by
`pool.ProcessPool` through `kernel.workers.spawn_worker`).

Over its end of the socket pair it takes one `Init` (how to build its world), answers `Ready` (or
`InitFailed` with the reason), then runs each `BranchTask` it is sent and answers its
`BranchOutcome`, in order, until `Stop` or the end of the pipe. A thread reads the pipe while a branch
runs, so the parent can hand over the next branch before this one ends (neither side then waits on
the other's full pipe). Only the parent that started it speaks to it.
"""

from __future__ import annotations

import os
import queue
import signal
import sys
import threading
import traceback
from multiprocessing.connection import Connection

from ..kernel.branch import BranchRunner, BranchTask
from .messages import InitFailed, Ready, Stop


def serve(conn: Connection) -> None:
    init = conn.recv()
    try:
        runner = BranchRunner(init.build)
    except Exception as exc:
        conn.send(InitFailed(f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=4)}"))
        return
    conn.send(Ready(os.getpid()))
    inbox: queue.SimpleQueue[object] = queue.SimpleQueue()

    def read() -> None:  # the pipe is read while a branch runs: the parent may hand over the next one
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                inbox.put(None)
                return
            inbox.put(msg)
            if isinstance(msg, Stop):
                return

    threading.Thread(target=read, name="dynabrain-batch-inbox", daemon=True).start()
    try:
        while True:
            msg = inbox.get()
            if msg is None or isinstance(msg, Stop):
                return
            if isinstance(msg, BranchTask):
                conn.send(runner.run(msg))
    finally:
        runner.close()


def main() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's, which stops its workers
    serve(Connection(int(sys.argv[1])))


if __name__ == "__main__":
    main()
