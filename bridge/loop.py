"""The served world's own loop (``start`` / ``stop``): one tick at a time under the world lock, brain
inputs applied at each step boundary, paced to real time (or a speed factor) when asked.

The World has a loop thread of its own (`World.start`); the server uses this one instead because brain
inputs must be applied between ticks, which the World's loop has no hook for.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from dynabrain.orchestrator.kernel.errors import DynabrainError
from dynabrain.orchestrator.kernel.units import NS_PER_S

from .calls import WorldService


class Loop:
    """Runs a service's world in a thread until stopped, ``until`` is reached, or a tick fails."""

    def __init__(self, service: WorldService, on_end: Callable[[str, str | None], None]):
        self._service = service
        self._on_end = on_end
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.error: str | None = None
        self.realtime: float | None = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, realtime: bool | float, until: float | None) -> dict:
        if self.running:
            raise DynabrainError(f"world {self._service.world.name!r} is already running")
        world = self._service.world
        factor = 1.0 if realtime is True else (float(realtime) if realtime else None)
        stop_tick = None if until is None else round(until * NS_PER_S / world.dt_ns)
        if stop_tick is not None and stop_tick <= world.tick_count:
            raise DynabrainError(f"until={until} s is not after the world's time ({world.time} s)")
        self._stop.clear()
        self.error, self.realtime = None, factor
        self._thread = threading.Thread(target=self._run, args=(factor, stop_tick), daemon=True,
                                        name=f"dynabrain-serve-{world.name}")
        self._thread.start()
        return {"running": True, "realtime": factor, "until_tick": stop_tick}

    def stop(self) -> dict:
        thread = self._thread
        if thread is not None:
            self._stop.set()
            if thread is not threading.current_thread():
                thread.join()
            self._thread = None
        return {"running": False, "error": self.error}

    def _run(self, factor: float | None, stop_tick: int | None) -> None:
        svc, world = self._service, self._service.world
        wall0, tick0 = time.perf_counter(), world.tick_count
        reason = "stopped"
        while not self._stop.is_set():
            with world.lock():
                if stop_tick is not None and world.tick_count >= stop_tick:
                    reason = "until"
                    break
                try:
                    if svc.has_pending:
                        svc.apply_pending()
                    world.tick()
                except Exception as exc:  # the World rolled the tick back; report and stop
                    self.error, reason = str(exc), "error"
                    break
                ticks = world.tick_count - tick0
            if factor:
                ahead = wall0 + ticks * world.dt_ns / NS_PER_S / factor - time.perf_counter()
                if ahead > 0:
                    self._stop.wait(ahead)
                elif ahead < -0.5:  # fell far behind (a long call held the lock): do not race to catch up
                    wall0, tick0 = time.perf_counter(), world.tick_count
            elif ticks % 32 == 0:
                time.sleep(0)  # let brains' calls in between ticks
        self._on_end(reason, self.error)
