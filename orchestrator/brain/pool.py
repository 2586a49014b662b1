"""The ``processes`` backend: worker processes, each with a world of its own, fed branches as they
finish them (two at a time when all start from one state, so none waits between two), so every core
is busy until the batch is done.

A worker that dies (killed, a segfault in an FMU) fails the branch it was running, with the cause,
and is replaced; the other branches go on. Tasks and outcomes cross a private socket pair as pickles
(only this parent and its own children speak on it).
"""

from __future__ import annotations

import contextlib
import signal
from collections import deque
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection, wait
from subprocess import Popen, TimeoutExpired
from typing import Any

from ..kernel.branch import BranchOutcome, BranchStatus, BranchTask
from ..kernel.errors import DynabrainError
from ..kernel.workers import spawn_worker
from .messages import Init, InitFailed, Ready, Stop

START_TIMEOUT_S = 120.0
"""How long a worker may take to build its world (a cold import of MuJoCo and a model compile)."""
IN_FLIGHT = 2
"""Branches handed to one worker at a time when they all start from one state: the one it runs and
the next."""


class _Worker:
    def __init__(self, proc: Popen, conn: Connection):
        self.proc, self.conn = proc, conn
        self.handed: deque[BranchTask] = deque()  # the branches it was sent and has not answered, in order
        self.last: bytes | None = None  # the state its world ended the last branch in

    def cause(self) -> str:
        try:
            code = self.proc.wait(timeout=5)
        except TimeoutExpired:
            return "its pipe closed"
        if code < 0:
            with contextlib.suppress(ValueError):
                return f"killed by {signal.Signals(-code).name}"
            return f"killed by signal {-code}"
        return f"exit code {code}"

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.conn.send(Stop())
        self.conn.close()
        try:
            self.proc.wait(timeout=5)
        except TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def _take(queue: deque[BranchTask], last: bytes | None) -> BranchTask:
    """The next task for a worker: one that starts where the worker's world is (it skips an import),
    else the first."""
    if last is not None:
        for i, task in enumerate(queue):
            if task.start == last:
                del queue[i]
                return task
    return queue.popleft()


class ProcessPool:
    """``size`` worker processes building their worlds with ``build``."""

    def __init__(self, build: Callable[[], Any], size: int):
        if size < 1:
            raise DynabrainError(f"a process pool needs at least one worker, got {size}")
        self.build, self.size = build, size
        self.replaced = 0
        """Workers started again after one died."""
        self._workers: list[_Worker] = []
        pending: list[_Worker] = []
        try:
            for _ in range(size):
                pending.append(self._spawn())
            for worker in pending:
                self._await_ready(worker)
                self._workers.append(worker)
        except BaseException:
            for worker in pending:
                with contextlib.suppress(Exception):
                    worker.proc.kill()
            raise

    def _spawn(self) -> _Worker:
        try:
            proc, conn = spawn_worker("dynabrain.orchestrator.brain.worker")
        except OSError as exc:
            raise DynabrainError(f"batch: cannot start a worker process: {exc}") from None
        worker = _Worker(proc, conn)
        conn.send(Init(self.build))
        return worker

    def _await_ready(self, worker: _Worker) -> None:
        if not worker.conn.poll(START_TIMEOUT_S):
            worker.proc.kill()
            raise DynabrainError(f"batch: a worker process did not build its world within {START_TIMEOUT_S:.0f} s")
        try:
            answer = worker.conn.recv()
        except EOFError:
            raise DynabrainError(f"batch: a worker process died while building its world ({worker.cause()})") from None
        if isinstance(answer, InitFailed):
            worker.close()
            raise DynabrainError(f"batch: a worker process could not build its world: {answer.reason}")
        assert isinstance(answer, Ready)

    def map(self, tasks: Sequence[BranchTask]) -> list[BranchOutcome]:
        """Every task's outcome, in the order of ``tasks``. When every branch starts from the same state
        (futures fanned out from one), a worker is handed `IN_FLIGHT` at a time, so it starts the next
        as soon as it answers; branches that go on from others (a vector env's steps) go one at a time,
        each to the worker whose world ended where it starts (`_take`: no state to import)."""
        queue = deque(tasks)
        depth = IN_FLIGHT if len({id(t.start) for t in tasks}) <= 1 else 1
        outcomes: dict[int, BranchOutcome] = {}
        for worker in self._workers:
            worker.handed.clear()
        while queue or any(w.handed for w in self._workers):
            for worker in self._workers:
                while queue and len(worker.handed) < depth:
                    task = _take(queue, worker.last if not worker.handed else None)
                    worker.handed.append(task)
                    with contextlib.suppress(OSError):  # died: read back as a death below
                        worker.conn.send(task)
            busy = {w.conn: w for w in self._workers if w.handed}
            for conn in wait(list(busy)):
                worker = busy[conn]
                try:
                    outcome = conn.recv()
                except (EOFError, OSError):
                    # the first branch it was handed was running; those after it never started: they go
                    # back to the queue, for the worker that takes its place
                    running, *later = worker.handed
                    outcomes[running.index] = BranchOutcome(running.index, {}, None, BranchStatus(
                        False, f"the worker process running branch {running.index} died ({worker.cause()})", lost=True))
                    queue.extendleft(reversed(later))
                    self._replace(worker)
                    continue
                task = worker.handed.popleft()
                outcomes[task.index] = outcome
                worker.last = outcome.state
        return [outcomes[t.index] for t in tasks]

    def _replace(self, dead: _Worker) -> _Worker:
        with contextlib.suppress(Exception):
            dead.conn.close()
        fresh = self._spawn()
        self._await_ready(fresh)
        self._workers[self._workers.index(dead)] = fresh
        self.replaced += 1
        return fresh

    def pids(self) -> list[int]:
        return [w.proc.pid for w in self._workers]

    def close(self) -> None:
        for worker in self._workers:
            worker.close()
        self._workers = []
