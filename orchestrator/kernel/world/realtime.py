"""The real-time runner: a world's loop in a thread of its own (as libcosim's execution runner), as fast
as it goes, at real time or at a speed factor, until stopped or until a simulated time. Each tick takes
the world lock, so the brain's calls from other threads fall between ticks."""

from __future__ import annotations

import threading
import time as _time

from ..errors import DynabrainError
from ..units import NS_PER_S
from .context import Context
from .stepper import Stepper


class RealtimeRunner:
    """Runs one world's ticks in a thread (see the module docstring)."""

    def __init__(self, ctx: Context, stepper: Stepper):
        self.ctx = ctx
        self.stepper = stepper
        self._thread: threading.Thread | None = None
        self._stop_flag = threading.Event()
        self._error: BaseException | None = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, factor: float | None, stop_tick: int | None) -> None:
        """(The caller holds the lock.) ``factor``: None as fast as possible, else simulated seconds per
        wall second; ``stop_tick``: stop by itself there."""
        if self.running:
            raise DynabrainError("the world is already running")
        self._stop_flag.clear()
        self._error = None
        self._thread = threading.Thread(target=self._loop, args=(factor, stop_tick),
                                        name=f"dynabrain-{self.ctx.name}", daemon=True)
        self._thread.start()

    def _loop(self, factor: float | None, stop_tick: int | None) -> None:
        ctx, wall0, stepped = self.ctx, _time.perf_counter(), 0
        while not self._stop_flag.is_set():
            with ctx.lock:
                if stop_tick is not None and ctx.tick >= stop_tick:
                    break
                try:
                    self.stepper.steps(1)
                except BaseException as exc:
                    self._error = exc
                    break
            stepped += 1
            if factor:
                ahead = wall0 + stepped * ctx.dt_ns / NS_PER_S / factor - _time.perf_counter()
                if ahead > 0:
                    self._stop_flag.wait(ahead)
            elif stepped % 64 == 0:
                _time.sleep(0)  # let callers waiting for the lock in

    def stop(self) -> None:
        """Stop the thread; re-raises an error that stopped it."""
        thread = self._thread
        if thread is None:
            return
        self._stop_flag.set()
        if thread is not threading.current_thread():
            thread.join()
        self._thread = None
        if self._error is not None:
            err, self._error = self._error, None
            raise err

    def wait(self, timeout: float | None) -> bool:
        thread = self._thread
        if thread is None:
            return True
        thread.join(timeout)
        return not thread.is_alive()
