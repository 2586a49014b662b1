"""The ``processes`` backend: worker processes, each with a world of its own, fed one branch at a
time (a worker that finishes takes the next), so every core is busy until the batch is done.

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

from ..kernel.errors import DynabrainError
from ..kernel.workers import spawn_worker
from .branch import BranchOutcome, BranchStatus, BranchTask
from .messages import Init, InitFailed, Ready, Stop

START_TIMEOUT_S = 120.0
"""How long a worker may take to build its world (a cold import of MuJoCo and a model compile)."""


class _Worker:
    def __init__(self, proc: Popen, conn: Connection):
        self.proc, self.conn = proc, conn
        self.task: BranchTask | None = None
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
        """Every task's outcome, in the order of ``tasks``."""
        queue = deque(tasks)
        outcomes: dict[int, BranchOutcome] = {}
        idle = list(self._workers)
        busy: dict[Connection, _Worker] = {}
        while queue or busy:
            while queue and idle:
                worker = idle.pop()
                worker.task = _take(queue, worker.last)
                with contextlib.suppress(OSError):  # died while idle: read back as a death below
                    worker.conn.send(worker.task)
                busy[worker.conn] = worker
            for conn in wait(list(busy)):
                worker = busy.pop(conn)
                task = worker.task
                assert task is not None
                try:
                    outcome = conn.recv()
                except (EOFError, OSError):
                    outcome = BranchOutcome(task.index, {}, None, BranchStatus(
                        False, f"the worker process running branch {task.index} died ({worker.cause()})"))
                    worker = self._replace(worker)
                outcomes[task.index] = outcome
                worker.task, worker.last = None, outcome.state
                idle.append(worker)
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
